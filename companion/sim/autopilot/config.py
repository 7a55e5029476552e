"""Settings and records of the fake autopilot: `FakeAutopilotConfig`, `ImuNoise`, `ReceivedMessage`, `Truth`,
the default telemetry rates and parameters of each profile."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.checks import FloatArray
from companion.errors import ConfigError
from companion.sim.autopilot.battery import (
    BatteryParams,
)
from companion.sim.autopilot.faults import Fault
from companion.sim.autopilot.flight import FlightParams
from companion.sim.autopilot.profiles import profile_by_name
from companion.sim.autopilot.transport import parse_listen_url
from companion.sim.autopilot.vehicle import (
    VehicleParams,
)
from companion.sim.autopilot.wind import DrydenConfig

__all__ = ["DEFAULT_RATES_HZ", "FakeAutopilotConfig", "ImuNoise", "ReceivedMessage", "Truth"]

EARTH_RADIUS_M = 6378137.0

# Telemetry streamed without being asked (per profile), Hz. SET_MESSAGE_INTERVAL changes them.
DEFAULT_RATES_HZ: dict[str, dict[str, float]] = {
    "ardupilot": {
        "SYS_STATUS": 1.0,
        "BATTERY_STATUS": 1.0,
        "EXTENDED_SYS_STATE": 1.0,
        "EKF_STATUS_REPORT": 1.0,
        "ATTITUDE": 10.0,
        "LOCAL_POSITION_NED": 10.0,
        "GLOBAL_POSITION_INT": 5.0,
        "DISTANCE_SENSOR": 10.0,
        "SIM_STATE": 10.0,
        "HIGHRES_IMU": 0.0,
        "ATTITUDE_QUATERNION": 0.0,
        "GPS_GLOBAL_ORIGIN": 0.0,
        "HOME_POSITION": 0.0,
    },
    "px4": {
        "SYS_STATUS": 1.0,
        "BATTERY_STATUS": 1.0,
        "EXTENDED_SYS_STATE": 2.0,
        "EKF_STATUS_REPORT": 1.0,
        "ATTITUDE": 10.0,
        "ATTITUDE_QUATERNION": 10.0,
        "LOCAL_POSITION_NED": 10.0,
        "GLOBAL_POSITION_INT": 5.0,
        "DISTANCE_SENSOR": 10.0,
        "SIM_STATE": 10.0,
        "HIGHRES_IMU": 0.0,
        "GPS_GLOBAL_ORIGIN": 0.0,
        "HOME_POSITION": 0.5,
    },
}

MAX_RATE_HZ = 400.0
MAX_PARSERS = 16  # per-peer frame parsers kept (one per UDP source address / TCP client)
ACCEPTED: int = mavlink.MAV_RESULT_ACCEPTED
FAILED: int = mavlink.MAV_RESULT_FAILED
FORCE_MAGIC = 21196
GCS_SYSID, GCS_COMPID = 255, 190
PARAMS: dict[str, dict[str, float]] = {
    "ardupilot": {
        "GUID_TIMEOUT": 3.0,
        "FS_EKF_ACTION": 1.0,
        "FS_EKF_THRESH": 0.8,
        "DISARM_DELAY": 10.0,
        "LAND_SPEED": 50.0,
        "SYSID_THISMAV": 1.0,
    },
    "px4": {
        "MIS_TAKEOFF_ALT": 2.5,
        "COM_OF_LOSS_T": 0.5,
        "COM_DISARM_PRFLT": 10.0,
        "MPC_LAND_SPEED": 0.5,
        "MAV_SYS_ID": 1.0,
    },
}
REJECT_RESULTS = {
    "denied": mavlink.MAV_RESULT_DENIED,
    "failed": mavlink.MAV_RESULT_FAILED,
    "temporarily_rejected": mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
}


@dataclass(frozen=True)
class ImuNoise:
    """HIGHRES_IMU noise: white noise per sample (std) and constant biases drawn once (std); rad/s, m/s²."""

    gyro_noise_rad_s: float = 0.003
    accel_noise_m_s2: float = 0.03
    gyro_bias_rad_s: float = 0.002
    accel_bias_m_s2: float = 0.04


@dataclass(frozen=True)
class FakeAutopilotConfig:
    """Settings of the fake autopilot.

    ``profile``: "ardupilot" (ArduCopter-like, default) or "px4".
    ``listen``: ``udpin:HOST:PORT`` (UDP server, port 0 = ephemeral), ``tcpin:HOST:PORT`` or ``udpout:HOST:PORT``.
    ``require_vision``: non-GPS configuration; the EKF is healthy only with a vision pose < 300 ms old.
    ``physics_rate_hz``: fixed physics step rate. ``seed``: all randomness (wind, IMU noise, faults).
    ``start_north_m, start_east_m, start_yaw_rad``: where the vehicle rests at boot (on z = 0).
    ``rates_hz``: overrides of the unrequested stream rates (message name -> Hz, 0 = off).
    ``origin_lla``: EKF origin already set at boot (lat deg, lon deg, alt m), e.g. a GPS configuration.
    ``reference_lla``: where SIM_STATE's lat/lon are computed from while no origin is set.
    ``gcs_heartbeat``: also emit GCS heartbeats (sysid 255, MAV_TYPE_GCS) at 1 Hz on the same link.
    ``max_records``: keep at most this many received-message records (oldest dropped in batches of
    1/16 of it; None = all). About 0.5 kB per record: the default holds ~100 MB in a long real-time run.
    ``ekf_position_noise_m`` / ``ekf_attitude_noise_rad``: noise on the reported (EKF) position/attitude.
    """

    profile: str = "ardupilot"
    listen: str = "udpin:127.0.0.1:0"
    system_id: int = 1
    component_id: int = 1
    require_vision: bool = True
    physics_rate_hz: float = 400.0
    seed: int = 0
    start_north_m: float = 0.0
    start_east_m: float = 0.0
    start_yaw_rad: float = 0.0
    wind: DrydenConfig = field(default_factory=DrydenConfig)
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    flight: FlightParams = field(default_factory=FlightParams)
    battery: BatteryParams = field(default_factory=BatteryParams)
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    faults: tuple[Fault, ...] = ()
    rates_hz: Mapping[str, float] | None = None
    origin_lla: tuple[float, float, float] | None = None
    reference_lla: tuple[float, float, float] = (47.397742, 8.545594, 488.0)
    gcs_heartbeat: bool = False
    rangefinder_max_m: float = 40.0
    rangefinder_noise_m: float = 0.01
    ekf_position_noise_m: float = 0.01
    ekf_attitude_noise_rad: float = 0.002
    max_records: int | None = 200_000

    def __post_init__(self) -> None:
        profile_by_name(self.profile)
        parse_listen_url(self.listen)
        if not 1 <= self.system_id <= 255 or not 0 <= self.component_id <= 255:
            raise ConfigError(f"system_id/component_id out of range: {self.system_id}/{self.component_id}")
        if not 50.0 <= self.physics_rate_hz <= 2000.0:
            raise ConfigError(f"physics_rate_hz must be in [50, 2000], got {self.physics_rate_hz}")
        if self.max_records is not None and self.max_records < 1:
            raise ConfigError(f"max_records must be >= 1 or None, got {self.max_records}")
        for name in self.rates_hz or {}:
            if name not in DEFAULT_RATES_HZ["ardupilot"]:
                raise ConfigError(f"rates_hz: cannot stream {name!r}; known: {sorted(DEFAULT_RATES_HZ['ardupilot'])}")


@dataclass(frozen=True)
class ReceivedMessage:
    """One message the fake received: clock time (s), type name, decoded fields, raw frame bytes, sender ids."""

    time_s: float
    type: str
    fields: dict[str, Any]
    raw: bytes
    src_system: int
    src_component: int


@dataclass(frozen=True)
class Truth:
    """The true vehicle state at `stamp_s` (clock time, s): pose in NED, velocity, rates, wind, battery."""

    stamp_s: float
    T_ned_body: FloatArray
    velocity_ned_m_s: FloatArray
    accel_ned_m_s2: FloatArray
    rates_body_rad_s: FloatArray
    wind_ned_m_s: FloatArray
    on_ground: bool
    battery_voltage_v: float
    battery_remaining_pct: float
    battery_current_a: float

    @property
    def position_ned_m(self) -> FloatArray:
        """Body origin in NED (m)."""
        return np.asarray(self.T_ned_body[:3, 3].copy())

    @property
    def height_m(self) -> float:
        """Height above the ground plane (m)."""
        return float(-self.T_ned_body[2, 3])


@dataclass
class Stream:
    interval_s: float  # 0 = off
    next_due_s: float


def msg_fields(msg: Any) -> dict[str, Any]:
    fields: dict[str, Any] = msg.to_dict()
    fields.pop("mavpackettype", None)
    return fields
