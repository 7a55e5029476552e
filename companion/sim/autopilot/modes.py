"""The fake autopilot's mode and arming state machine: arm/disarm, mode changes, take-off and land commands.

A synchronous state machine (no I/O, no clock: every call takes `now_s`); `flight.py` adds the per-step
update (guidance and failsafes) on top of it as `FlightLogic`.
"""

from __future__ import annotations

import collections
import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.autopilot.ekf import EkfModel, FsEkfCheck
from companion.sim.autopilot.guidance import ShapedVelocity, hold_velocity
from companion.sim.autopilot.profiles import Behaviour, ModeDef, Profile
from companion.sim.autopilot.rules import (
    FlightParams,
    Setpoint,
    arming_refusal,
    flight_timings,
    mode_change_refusal,
    offboard_stream_ok,
)
from companion.sim.autopilot.vehicle import Vec3, VehicleState

__all__ = ["ModeLogic"]

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED


class ModeLogic:
    """Mode/arming state of the fake autopilot (mutable; one per simulated vehicle). See `FlightLogic`."""

    def __init__(self, profile: Profile, params: FlightParams, home_ne_m: tuple[float, float] = (0.0, 0.0)) -> None:
        self.profile = profile
        self.params = params
        self.timing = flight_timings(params, profile)
        self.ardupilot = profile.name == "ardupilot"
        self.ekf = EkfModel(
            self.ardupilot, params.require_vision, self.timing.vision_timeout_s, self.timing.ekf_alignment_s
        )
        self.home_set = False  # ArduPilot: home is set once the EKF has an origin and a position
        self.mode: ModeDef = profile.mode(profile.initial_mode)
        self.armed = False
        self.events: list[tuple[int, str]] = []  # (MAV_SEVERITY, text) for STATUSTEXT
        self.setpoint: Setpoint | None = None
        self.battery_critical = False
        self.home_ne_m = home_ne_m
        self._setpoint_times: collections.deque[float] = collections.deque(maxlen=64)
        self._hold_target: Vec3 | None = None
        self._takeoff_target_z: float | None = None
        self._guided_stopped = False
        self._ground_since_s: float | None = None
        self._armed_since_s: float | None = None
        self._rtl_landing = False
        self._battery_failsafe_done = False
        self._braking = False
        self._spool_until_s: float | None = None  # ArduPilot NAV_TAKEOFF: motors spool, then climb
        self._takeoff_cmd_s: float | None = None
        self._land_pause_until_s = -math.inf  # an EKF-failsafe LAND holds the height until then
        self._fs_ekf_check = FsEkfCheck()
        self._shaped: ShapedVelocity | None = None  # GUIDED velocity after accel/jerk shaping
        self._last_update_s: float | None = None

    # ----- queries ---------------------------------------------------------------------------

    @property
    def last_vision_s(self) -> float | None:
        """Clock time of the last vision pose (None before the first)."""
        return self.ekf.last_vision_s

    def ekf_healthy(self, now_s: float) -> bool:
        """True when the EKF has a position estimate (always, unless `require_vision`)."""
        return self.ekf.has_position(now_s)

    def offboard_ok(self, now_s: float) -> bool:
        """Whether PX4 would accept OFFBOARD now."""
        p = self.params
        return offboard_stream_ok(list(self._setpoint_times), now_s, p.offboard_min_rate_hz, p.offboard_loss_s)

    def taking_off(self) -> bool:
        """A takeoff (spool-up or climb) is in progress."""
        return self._takeoff_target_z is not None

    def landed_state(self, vehicle: VehicleState, now_s: float | None = None) -> int:
        """MAV_LANDED_STATE for EXTENDED_SYS_STATE (ArduPilot still reports ON_GROUND for the first
        0.25 s of a take-off's spool-up, as the SITL does)."""
        spool_start = (
            self.ardupilot
            and now_s is not None
            and self._takeoff_cmd_s is not None
            and now_s - self._takeoff_cmd_s < 0.25
        )
        if vehicle.on_ground and (not self.taking_off() or spool_start):
            return int(mavlink.MAV_LANDED_STATE_ON_GROUND)
        if self.taking_off():
            return int(mavlink.MAV_LANDED_STATE_TAKEOFF)
        if self.armed and (self.mode.behaviour is Behaviour.LAND or self._rtl_landing):
            return int(mavlink.MAV_LANDED_STATE_LANDING)
        return int(mavlink.MAV_LANDED_STATE_IN_AIR)

    # ----- inputs ----------------------------------------------------------------------------

    def on_vision(self, now_s: float) -> None:
        """A vision pose (or odometry) arrived."""
        self.ekf.on_vision(now_s)

    def on_setpoint(self, setpoint: Setpoint) -> None:
        """A SET_POSITION_TARGET_LOCAL_NED arrived (PX4 counts them in any mode, ArduPilot uses them in GUIDED)."""
        self._setpoint_times.append(setpoint.stamp_s)
        if self.profile.guided_mode == "GUIDED" and self.mode.behaviour is not Behaviour.GUIDED:
            return
        self.setpoint = setpoint
        self._guided_stopped = False

    def _event(self, severity: int, text: str) -> None:
        self.events.append((severity, text))

    def _stop_point(self, vehicle: VehicleState) -> Vec3:
        k = self.params.braking_time_s
        p, v = vehicle.position_ned_m, vehicle.velocity_ned_m_s
        return (p[0] + k * v[0], p[1] + k * v[1], p[2] + k * v[2])

    def _brake_then_hold(self, vehicle: VehicleState, hold: Vec3) -> Vec3:
        """Like ArduPilot's stop: command zero velocity until nearly stopped, then hold that point."""
        if self._braking:
            if math.sqrt(sum(v * v for v in vehicle.velocity_ned_m_s)) > 0.1:
                return (0.0, 0.0, 0.0)
            self._braking = False
            self._hold_target = hold = vehicle.position_ned_m
        return self._hold_velocity(vehicle, hold)

    def _enter(self, mode: ModeDef, vehicle: VehicleState) -> None:
        self.mode = mode
        self._hold_target = self._stop_point(vehicle)
        self._braking = not vehicle.on_ground
        self._rtl_landing = False
        if mode.behaviour is not Behaviour.TAKEOFF:
            self._takeoff_target_z = None
        if mode.behaviour is Behaviour.GUIDED:
            self.setpoint = None
        self._land_pause_until_s = -math.inf
        self._shaped = None

    def prearm_failures(self, now_s: float, vehicle: VehicleState) -> list[str]:
        """Why arming would be refused now (texts without the profile's prefix; empty = ready)."""
        if not vehicle.on_ground:
            return []
        reasons = self.ekf.prearm_failures(now_s, self.home_set) if self.ardupilot else []
        reason = arming_refusal(
            self.mode, self.ekf.aligned(now_s), self.params.require_vision, self.battery_critical, False
        )
        if reason is not None and not (reasons and reason == "Need Position Estimate"):
            reasons.append(reason)
        return reasons

    def arm(self, now_s: float, vehicle: VehicleState, force: bool = False) -> tuple[int, str | None]:
        """MAV_CMD_COMPONENT_ARM_DISARM(1): (MAV_RESULT, refusal text)."""
        if self.armed:
            return ACCEPTED, None
        reasons = [] if force else self.prearm_failures(now_s, vehicle)
        if reasons:
            for reason in reasons:
                self._event(mavlink.MAV_SEVERITY_CRITICAL, self.profile.statustext_prefix + reason)
            return self.profile.arm_denied_result, reasons[0]
        self.armed = True
        self.ekf.height_agl_valid = False
        self._armed_since_s = now_s
        self._ground_since_s = now_s
        self._hold_target = vehicle.position_ned_m
        self.home_ne_m = (vehicle.position_ned_m[0], vehicle.position_ned_m[1])
        self._battery_failsafe_done = False
        self._event(mavlink.MAV_SEVERITY_INFO, "Arming motors")
        return ACCEPTED, None

    def disarm(self, now_s: float, vehicle: VehicleState, force: bool = False) -> tuple[int, str | None]:
        """MAV_CMD_COMPONENT_ARM_DISARM(0): refused in flight unless forced."""
        if not self.armed:
            return ACCEPTED, None
        if not vehicle.on_ground and not force:
            self._event(mavlink.MAV_SEVERITY_CRITICAL, "Disarm refused: flying")
            return self.profile.arm_denied_result, "flying"
        self._disarm("Disarming motors")
        return ACCEPTED, None

    def _disarm(self, text: str) -> None:
        self.armed = False
        self._takeoff_target_z = None
        self._spool_until_s = None
        self._armed_since_s = None
        self._rtl_landing = False
        self._event(mavlink.MAV_SEVERITY_INFO, text)

    def set_mode(self, mode: ModeDef, now_s: float, vehicle: VehicleState) -> tuple[int, str | None]:
        """Change mode (DO_SET_MODE or SET_MODE): (MAV_RESULT, refusal text)."""
        if mode == self.mode:
            return ACCEPTED, None
        reason = mode_change_refusal(
            mode, self.ekf_healthy(now_s), self.offboard_ok(now_s), self.armed, self.profile.mode_checks_when_disarmed
        )
        if reason is not None:
            self._event(mavlink.MAV_SEVERITY_WARNING, f"Mode change to {mode.name} failed: {reason}")
            return self.profile.mode_denied_result, reason
        self._enter(mode, vehicle)
        if mode.behaviour is Behaviour.TAKEOFF:
            self._takeoff_target_z = -self.params.default_takeoff_height_m
        return ACCEPTED, None

    def takeoff(self, height_m: float, now_s: float, vehicle: VehicleState) -> tuple[int, str | None]:
        """MAV_CMD_NAV_TAKEOFF to `height_m` above the ground."""
        if not self.armed:
            return mavlink.MAV_RESULT_FAILED, "not armed"
        if not vehicle.on_ground:
            return mavlink.MAV_RESULT_FAILED, "already flying"
        if not (math.isfinite(height_m) and height_m > 0.0):
            height_m = self.params.default_takeoff_height_m
        if self.profile.takeoff_mode is not None:
            takeoff = self.profile.mode(self.profile.takeoff_mode)
            if self.mode != takeoff:
                result, reason = self.set_mode(takeoff, now_s, vehicle)
                if result != ACCEPTED:
                    return result, reason
        elif self.mode.behaviour is not Behaviour.GUIDED:
            return mavlink.MAV_RESULT_FAILED, "takeoff needs GUIDED"
        self._takeoff_target_z = -height_m
        self._takeoff_cmd_s = now_s
        self._spool_until_s = now_s + self.timing.takeoff_spool_s
        self._event(mavlink.MAV_SEVERITY_INFO, f"Takeoff to {height_m:.1f} m")
        return ACCEPTED, None

    def land(self, now_s: float, vehicle: VehicleState) -> tuple[int, str | None]:
        """MAV_CMD_NAV_LAND: switch to the land mode."""
        return self.set_mode(self.profile.mode(self.profile.land_mode), now_s, vehicle)

    def _hold_velocity(self, vehicle: VehicleState, target: Vec3) -> Vec3:
        p = self.params
        return hold_velocity(vehicle.position_ned_m, target, p.hold_gain_per_s, p.hold_max_speed_m_s)
