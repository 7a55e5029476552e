"""MAVLink link to the flight controller (pymavlink on bytes, MAVLink 2, ``ardupilotmega`` dialect).

Example (``clock`` is any `companion.clock.Clock`; tests pass a ManualClock)::

    async with MavLink(LinkConfig(url="udpout:127.0.0.1:14550"), clock=clock) as link:
        await link.wait_autopilot(5.0)
        await link.set_mode("GUIDED")
        await link.arm()
        link.send_pose(PoseOut(stamp_s, T_ned_body, pose_covariance))

Modules: `url` (connection URLs), `transport` (UDP/TCP/serial on asyncio), `wire` (encode and a
robust frame parser), `state` (decoding into `VehicleState`), `timesync`, `profiles` (ArduPilot /
PX4 modes), `sendqueue` (the writer's bounded priority queue), `tlog`, `link` (`MavLink`).
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
