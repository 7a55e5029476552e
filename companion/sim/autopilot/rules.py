"""The fake autopilot's settings and its pure rules: arming, mode changes and PX4's OFFBOARD stream rule.

Timings that differ between the autopilots default to None in `FlightParams` and are resolved per
profile by `flight_timings`: the ArduPilot values were measured against ArduCopter 4.7.0-dev SITL
with the project's extnav preset (sitl_tests/ardupilot/fixtures/arducopter_session.json), the PX4
ones are the fake's earlier values.
"""

from __future__ import annotations

from dataclasses import dataclass

from companion.errors import ConfigError
from companion.sim.autopilot.profiles import Behaviour, ModeDef, Profile
from companion.sim.autopilot.vehicle import Vec3

__all__ = [
    "FlightParams",
    "FlightTimings",
    "Setpoint",
    "arming_refusal",
    "flight_timings",
    "mode_change_refusal",
    "offboard_stream_ok",
]


@dataclass(frozen=True)
class FlightParams:
    """Flight-logic settings (s, m, m/s, m/s², m/s³, 1/s). None = the profile's value (see `flight_timings`).

    ``vision_timeout_s``: vision age (s) at which the EKF stops reporting a position (ArduPilot dead-reckons
    on the IMU and the baro until then). ``vision_failsafe_s``: vision age at which the EKF failsafe acts in
    flight (ArduPilot: FS_EKF after the position is lost; PX4: land). ``ekf_alignment_s``: seconds of
    continuous vision before the EKF is ready to arm. ``takeoff_spool_s``: NAV_TAKEOFF → the climb starts.
    ``land_disarm_delay_s``: touchdown → disarm in the land mode. ``failsafe_land_pause_s``: an EKF failsafe
    LAND holds the height this long before descending. ``guided_accel_m_s2``/``guided_jerk_m_s3``: limits
    of the shaping of GUIDED velocity targets (0 = no shaping). ``fs_ekf_action``: ArduPilot FS_EKF_ACTION
    (1 land, 2 alt-hold, 3 land even in STABILIZE); ``fs_ekf_thresh``: FS_EKF_THRESH (<= 0 disables).
    """

    require_vision: bool = True
    vision_timeout_s: float | None = None
    vision_failsafe_s: float | None = None
    ekf_alignment_s: float | None = None
    guided_timeout_s: float = 3.0
    offboard_loss_s: float = 0.5
    offboard_min_rate_hz: float = 2.0
    takeoff_speed_m_s: float | None = None
    takeoff_gain_per_s: float | None = None
    takeoff_spool_s: float | None = None
    land_speed_m_s: float | None = None
    land_disarm_delay_s: float | None = None
    failsafe_land_pause_s: float | None = None
    guided_accel_m_s2: float | None = None
    guided_jerk_m_s3: float | None = None
    auto_disarm_s: float | None = 10.0
    hold_gain_per_s: float = 1.0
    hold_max_speed_m_s: float = 2.0
    rtl_speed_m_s: float = 2.0
    rtl_min_height_m: float = 2.0
    yaw_gain_per_s: float = 2.0
    default_takeoff_height_m: float = 2.5
    battery_failsafe: bool = True
    braking_time_s: float = 0.55  # hold targets are placed where the vehicle stops, v * braking_time ahead
    fs_ekf_action: int = 1
    fs_ekf_thresh: float = 0.8

    def __post_init__(self) -> None:
        for name in (
            "vision_timeout_s",
            "vision_failsafe_s",
            "ekf_alignment_s",
            "takeoff_spool_s",
            "land_disarm_delay_s",
            "failsafe_land_pause_s",
            "guided_accel_m_s2",
            "guided_jerk_m_s3",
        ):
            value = getattr(self, name)
            if value is not None and not value >= 0.0:
                raise ConfigError(f"flight.{name} must be >= 0 s, got {value}")
        for name in ("takeoff_speed_m_s", "land_speed_m_s"):
            value = getattr(self, name)
            if value is not None and not value > 0.0:
                raise ConfigError(f"flight.{name} must be > 0, got {value}")
        if self.fs_ekf_action not in (1, 2, 3):
            raise ConfigError(f"flight.fs_ekf_action must be 1 (land), 2 (alt-hold) or 3, got {self.fs_ekf_action}")


@dataclass(frozen=True)
class FlightTimings:
    """`FlightParams`' profile-dependent values, resolved (same meanings and units)."""

    vision_timeout_s: float
    vision_failsafe_s: float
    ekf_alignment_s: float
    takeoff_speed_m_s: float
    takeoff_gain_per_s: float  # approach of the take-off height (1/s); 0 = hold_gain_per_s
    takeoff_spool_s: float
    land_speed_m_s: float
    land_disarm_delay_s: float
    failsafe_land_pause_s: float
    guided_accel_m_s2: float
    guided_jerk_m_s3: float


# Per profile. ArduPilot: measured on ArduCopter SITL (3 recordings; see docs/fake_autopilot.md):
# position lost 7.07-7.27 s after the last pose, FS_EKF (10 checks at 10 Hz) LAND at 7.95 s; pre-arm ready
# 11.8-13.1 s after vision starts; NAV_TAKEOFF → off the ground 3.3 s, 95 % of 1 m at 4.6-4.75 s;
# LAND 0.52-0.55 m/s, "Disarming motors" 2.2 s after touchdown; a failsafe LAND pauses 4 s
# (set_mode_land_with_pause); a 0.5 m/s velocity step starts after 0.27 s and the vehicle slows to
# half speed 0.46 s after GUID_TIMEOUT: the shaping limits are fitted to these two (with this
# airframe's own 0.45 s velocity lag), not ArduPilot's PSC_JERK_XY / WPNAV_ACCEL defaults.
_TIMINGS: dict[str, FlightTimings] = {
    "ardupilot": FlightTimings(
        vision_timeout_s=7.1,
        vision_failsafe_s=7.95,
        ekf_alignment_s=11.8,
        takeoff_speed_m_s=1.0,
        takeoff_gain_per_s=1.5,
        takeoff_spool_s=3.1,
        land_speed_m_s=0.53,
        land_disarm_delay_s=2.2,
        failsafe_land_pause_s=4.0,
        guided_accel_m_s2=2.0,
        guided_jerk_m_s3=10.0,
    ),
    "px4": FlightTimings(
        vision_timeout_s=0.3,
        vision_failsafe_s=1.0,
        ekf_alignment_s=0.0,
        takeoff_speed_m_s=1.0,
        takeoff_gain_per_s=0.0,
        takeoff_spool_s=0.0,
        land_speed_m_s=0.5,
        land_disarm_delay_s=1.0,
        failsafe_land_pause_s=0.0,
        guided_accel_m_s2=0.0,
        guided_jerk_m_s3=0.0,
    ),
}


def flight_timings(params: FlightParams, profile: Profile) -> FlightTimings:
    """The profile's timings with every value set in `params` taking precedence."""
    base = _TIMINGS[profile.name]
    values = {name: getattr(params, name) for name in FlightTimings.__dataclass_fields__}
    return FlightTimings(**{k: (getattr(base, k) if v is None else float(v)) for k, v in values.items()})


@dataclass(frozen=True)
class Setpoint:
    """A decoded SET_POSITION_TARGET_LOCAL_NED, already rotated into NED.

    Any of the targets may be None (ignored by the type mask). `stamp_s` is the receipt time.
    """

    stamp_s: float
    velocity_ned_m_s: Vec3 | None = None
    position_ned_m: Vec3 | None = None
    yaw_rad: float | None = None
    yaw_rate_rad_s: float | None = None


def offboard_stream_ok(setpoint_times_s: list[float], now_s: float, min_rate_hz: float, loss_s: float) -> bool:
    """PX4's OFFBOARD entry rule: the last setpoint is younger than `loss_s` and more than
    `min_rate_hz` setpoints arrived over the last second."""
    if not setpoint_times_s or now_s - setpoint_times_s[-1] > loss_s:
        return False
    recent = sum(1 for t in setpoint_times_s if now_s - t <= 1.0)
    return recent > min_rate_hz


def arming_refusal(
    mode: ModeDef, ekf_healthy: bool, require_vision: bool, battery_critical: bool, airborne: bool
) -> str | None:
    """Why arming is refused (a pre-arm failure text), or None when it may arm (PX4's texts; the
    ArduPilot profile reports its EKF reasons from `EkfModel.prearm_failures` first)."""
    if airborne:
        return None
    if require_vision and not ekf_healthy:
        return "Need Position Estimate"
    if not mode.armable:
        return "Mode not armable"
    if battery_critical:
        return "Battery critical"
    return None


def mode_change_refusal(
    target: ModeDef, ekf_healthy: bool, offboard_ok: bool, armed: bool = True, checks_when_disarmed: bool = True
) -> str | None:
    """Why a mode change is refused, or None when it is allowed.

    ArduCopter skips the position check while disarmed (`checks_when_disarmed=False`): it checks the
    mode again when arming.
    """
    if target.needs_position and not ekf_healthy and (armed or checks_when_disarmed):
        return f"{target.name} requires position estimate"
    if target.behaviour is Behaviour.OFFBOARD and not offboard_ok:
        return "Offboard: no setpoint stream"
    return None
