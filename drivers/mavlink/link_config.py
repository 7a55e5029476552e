"""`LinkConfig`: what the link connects to and how it behaves (validated when built), and the default
telemetry rates it asks the autopilot for."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import ConfigError, InputError
from drivers.mavlink.profiles import profile_named
from drivers.mavlink.url import parse_url

__all__ = ["DEFAULT_MESSAGE_RATES_HZ", "POSE_STAMP_BASES", "LinkConfig"]

DEFAULT_MESSAGE_RATES_HZ: Mapping[str, float] = MappingProxyType(
    {
        "ATTITUDE": 50.0,
        "LOCAL_POSITION_NED": 30.0,
        "SYS_STATUS": 2.0,
        "BATTERY_STATUS": 2.0,
        "DISTANCE_SENSOR": 20.0,
        "HIGHRES_IMU": 100.0,
        "EKF_STATUS_REPORT": 2.0,
        "EXTENDED_SYS_STATE": 2.0,
    }
)

POSE_STAMP_BASES = ("auto", "autopilot", "local")


@dataclass(frozen=True)
class LinkConfig:
    """Configuration of the link (times in seconds, rates in Hz).

    ``system_id`` None = use the autopilot's system id (the MAVLink rule for a companion);
    ``autopilot_profile`` None = detect ArduPilot/PX4 from the heartbeat. ``origin_*`` (degrees,
    metres AMSL) enable SET_GPS_GLOBAL_ORIGIN. ``pose_message`` is "vision" (VISION_POSITION_ESTIMATE
    + VISION_SPEED_ESTIMATE), "odometry", or "auto" (ODOMETRY for PX4,
    "vision" otherwise). ``message_rates_hz`` maps message names to requested
    rates; ``request_sim_state`` adds SIM_STATE (simulator truth). ``forward_urls``: GCS endpoints
    that get every autopilot frame and whose frames go to the autopilot.

    ``pose_stamp_base``: time base of the pose ``usec`` field. "autopilot": the capture time
    converted to the autopilot's clock once TIMESYNC converged (ours if it never answers).
    "local": always our monotonic capture time. "auto" (default): "local" when the autopilot is PX4,
    "autopilot" otherwise (ArduPilot, unknown), decided once the autopilot's profile is known (forced
    by ``autopilot_profile`` or detected from its heartbeat). PX4 wants "local": its receiver
    (``MavlinkReceiver::handle_message_vision_position_estimate``) passes ``usec`` through
    ``Timesync::sync_stamp``, which adds its *own* TIMESYNC offset (from the requests we answer) once
    converged and uses the arrival time before, so an already converted stamp is shifted twice.
    ArduPilot accepts either (it estimates the offset of the stamps itself).
    """

    url: str
    component_id: int = 197
    system_id: int | None = None
    autopilot_profile: str | None = None
    heartbeat_period_s: float = 1.0
    timesync_period_s: float = 1.0
    timesync_fallback_s: float = 3.0
    autopilot_timeout_s: float = 1.5
    reconnect_initial_s: float = 0.1
    reconnect_max_s: float = 2.0
    command_timeout_s: float = 1.0
    command_retries: int = 3
    message_rates_hz: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_MESSAGE_RATES_HZ))
    request_sim_state: bool = False
    sim_state_rate_hz: float = 50.0
    origin_lat_deg: float | None = None
    origin_lon_deg: float | None = None
    origin_alt_m: float | None = None
    origin_period_s: float = 1.0
    pose_message: str = "vision"
    send_vision_speed: bool = True
    pose_max_age_s: float = 0.5
    pose_stamp_base: str = "auto"
    setpoint_rate_hz: float = 20.0
    forward_urls: tuple[str, ...] = ()
    accept_mavlink1: bool = False

    def __post_init__(self) -> None:
        parse_url(self.url)
        for url in self.forward_urls:
            parse_url(url)
        if not 1 <= self.component_id <= 255:
            raise ConfigError(f"link.component_id must be in [1, 255], got {self.component_id}")
        if self.system_id is not None and not 1 <= self.system_id <= 255:
            raise ConfigError(f"link.system_id must be in [1, 255], got {self.system_id}")
        if self.autopilot_profile is not None:
            try:
                profile_named(self.autopilot_profile)
            except InputError as exc:
                raise ConfigError(f"link.autopilot_profile: {exc}") from None
        if self.pose_stamp_base not in POSE_STAMP_BASES:
            raise ConfigError(
                f"link.pose_stamp_base must be one of {', '.join(POSE_STAMP_BASES)}, got {self.pose_stamp_base!r}"
            )
        if self.pose_message not in ("vision", "odometry", "auto"):
            raise ConfigError(f"link.pose_message must be 'vision', 'odometry' or 'auto', got {self.pose_message!r}")
        if self.setpoint_rate_hz < 10.0:
            raise ConfigError(f"link.setpoint_rate_hz must be >= 10, got {self.setpoint_rate_hz}")
        for name in ("heartbeat_period_s", "autopilot_timeout_s", "command_timeout_s", "origin_period_s"):
            if not getattr(self, name) > 0.0:
                raise ConfigError(f"link.{name} must be > 0")
        if self.command_retries < 0:
            raise ConfigError("link.command_retries must be >= 0")
        origin = (self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m)
        if any(v is None for v in origin) and any(v is not None for v in origin):
            raise ConfigError("link.origin_lat_deg/origin_lon_deg/origin_alt_m must be given together")
        for name in self.message_rates_hz:
            if not hasattr(mavlink, f"MAVLINK_MSG_ID_{name}"):
                raise ConfigError(f"link.message_rates_hz: unknown message {name!r}")

    @property
    def origin(self) -> tuple[float, float, float] | None:
        if self.origin_lat_deg is None or self.origin_lon_deg is None or self.origin_alt_m is None:
            return None
        return (self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m)
