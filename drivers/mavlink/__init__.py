"""MAVLink link to the flight controller (pymavlink on bytes, MAVLink 2, ``ardupilotmega`` dialect).

Example (``clock`` is any `companion.clock.Clock`; tests pass a ManualClock)::

    async with MavLink(LinkConfig(url="udpout:127.0.0.1:14550"), clock=clock) as link:
        await link.wait_autopilot(5.0)
        await link.set_mode("GUIDED")
        await link.arm()
        link.send_pose(PoseOut(stamp_s, T_ned_body, pose_covariance))

Modules: `url` (connection URLs), `transport` (UDP/TCP/serial on asyncio), `wire` (encode and a
robust frame parser), `state` (decoding into `VehicleState`), `state_types` (`VehicleState`, `SimTruth`,
`PoseOut`), `geodetic` (flat-earth NED), `timesync`, `profiles` (ArduPilot / PX4 modes), `sendqueue`
(the writer's bounded priority queue), `tlog`, `link` (`MavLink`), `link_config` (`LinkConfig`),
`link_status` (`LinkHealth`, `LinkStats`), and the parts of `MavLink`: `link_core`, `link_outbound`,
`link_commands`, `link_reader`, `link_tasks`.
"""

from companion.control.types import VelocityCommand
from drivers.mavlink.link import LinkConfig, LinkHealth, LinkStats, MavLink
from drivers.mavlink.profiles import ARDUPILOT_COPTER, PX4, AutopilotProfile
from drivers.mavlink.state import ImuSample, PoseOut, SimTruth, VehicleState

__all__ = [
    "ARDUPILOT_COPTER",
    "PX4",
    "AutopilotProfile",
    "ImuSample",
    "LinkConfig",
    "LinkHealth",
    "LinkStats",
    "MavLink",
    "PoseOut",
    "SimTruth",
    "VehicleState",
    "VelocityCommand",
]
