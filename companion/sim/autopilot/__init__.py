"""The scripted fake autopilot: a real MAVLink endpoint (UDP/TCP) behaving like ArduCopter or PX4.

    from companion.sim.autopilot import FakeAutopilot, FakeAutopilotConfig, Fault
    async with FakeAutopilot(FakeAutopilotConfig(profile="px4", listen="udpin:127.0.0.1:0"), clock=clock) as ap:
        url = ap.url_for_client           # "udpout:127.0.0.1:PORT" for the client
        ap.schedule(Fault("link-loss", at_s=20.0, duration_s=1.0))
        ap.truth.T_ned_body; ap.received_of("VISION_POSITION_ESTIMATE")

See docs/fake_autopilot.md.
"""

from companion.sim.autopilot.autopilot import (
    DEFAULT_RATES_HZ,
    FakeAutopilot,
    FakeAutopilotConfig,
    ImuNoise,
    ReceivedMessage,
    Truth,
)
from companion.sim.autopilot.battery import BatteryParams
from companion.sim.autopilot.faults import FAULT_KINDS, Fault
from companion.sim.autopilot.flight import FlightParams
from companion.sim.autopilot.profiles import ARDUPILOT, PX4, Profile
from companion.sim.autopilot.vehicle import VehicleParams
from companion.sim.autopilot.wind import DrydenConfig

__all__ = [
    "ARDUPILOT",
    "DEFAULT_RATES_HZ",
    "FAULT_KINDS",
    "PX4",
    "BatteryParams",
    "DrydenConfig",
    "FakeAutopilot",
    "FakeAutopilotConfig",
    "Fault",
    "FlightParams",
    "ImuNoise",
    "Profile",
    "ReceivedMessage",
    "Truth",
    "VehicleParams",
]
