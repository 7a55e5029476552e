"""The fake autopilot's flight logic: arming, modes, takeoff/land, setpoints and failsafes.

A synchronous state machine (no I/O, no clock: every call takes `now_s`). The
MAVLink endpoint in `autopilot.py` feeds it decoded commands and setpoints and
asks it each physics step for the `MotionCommand` of the airframe.

Rules modelled on the real autopilots:
- arming is refused without a healthy position estimate when `require_vision`
  (non-GPS configuration: the EKF is healthy only while vision poses are < 300 ms
  old), in a mode that is not armable, or with a critical battery;
- ArduPilot GUIDED: a velocity setpoint is flown for at most `guided_timeout_s`
  (GUID_TIMEOUT, 3 s) after it arrived, then the vehicle stops and holds;
  setpoints are ignored while landed; NAV_TAKEOFF climbs inside GUIDED;
- PX4 OFFBOARD: the mode is refused unless setpoints are streaming (more than
  `offboard_min_rate_hz` over the last second and the last one < `offboard_loss_s`
  old); when the stream stops for `offboard_loss_s` it falls back to AUTO.LOITER
  (or AUTO.LAND without a position estimate); NAV_TAKEOFF switches to AUTO.TAKEOFF
  which hands over to AUTO.LOITER at the takeoff height;
- in flight, a lost position estimate (vision stale for `vision_failsafe_s`) or a
  critical battery switches to the land mode; landing disarms on the ground.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.autopilot.profiles import Behaviour, ModeDef, Profile
from companion.sim.autopilot.vehicle import MotionCommand, Vec3, VehicleState

__all__ = [
    "FlightLogic",
    "FlightParams",
    "Setpoint",
    "arming_refusal",
    "mode_change_refusal",
    "offboard_stream_ok",
]

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED


@dataclass(frozen=True)
class FlightParams:
    """Flight-logic settings (s, m, m/s, 1/s)."""

    require_vision: bool = True
    vision_timeout_s: float = 0.3
    vision_failsafe_s: float = 1.0
    guided_timeout_s: float = 3.0
    offboard_loss_s: float = 0.5
    offboard_min_rate_hz: float = 2.0
    takeoff_speed_m_s: float = 1.0
    land_speed_m_s: float = 0.5
    land_disarm_delay_s: float = 1.0
    auto_disarm_s: float | None = 10.0
    hold_gain_per_s: float = 1.0
    hold_max_speed_m_s: float = 2.0
    rtl_speed_m_s: float = 2.0
    rtl_min_height_m: float = 2.0
    yaw_gain_per_s: float = 2.0
    default_takeoff_height_m: float = 2.5
    battery_failsafe: bool = True
    braking_time_s: float = 0.55  # hold targets are placed where the vehicle stops, v * braking_time ahead


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
    """Why arming is refused (a pre-arm failure text), or None when it may arm."""
    if airborne:
        return None
    if require_vision and not ekf_healthy:
        return "Need Position Estimate"
    if not mode.armable:
        return "Mode not armable"
    if battery_critical:
        return "Battery critical"
    return None


def mode_change_refusal(target: ModeDef, ekf_healthy: bool, offboard_ok: bool) -> str | None:
    """Why a mode change is refused, or None when it is allowed."""
    if target.needs_position and not ekf_healthy:
        return f"{target.name} requires position estimate"
    if target.behaviour is Behaviour.OFFBOARD and not offboard_ok:
        return "Offboard: no setpoint stream"
    return None


def _wrap(angle_rad: float) -> float:
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


class FlightLogic:
    """Mode/arming state machine of the fake autopilot (mutable; one per simulated vehicle)."""

    def __init__(self, profile: Profile, params: FlightParams, home_ne_m: tuple[float, float] = (0.0, 0.0)) -> None:
        self.profile = profile
        self.params = params
        self.mode: ModeDef = profile.mode(profile.initial_mode)
        self.armed = False
        self.events: list[tuple[int, str]] = []  # (MAV_SEVERITY, text) for STATUSTEXT
        self.last_vision_s: float | None = None
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

    # ----- queries ---------------------------------------------------------------------------

    def ekf_healthy(self, now_s: float) -> bool:
        """True when the position estimate is usable (always, unless `require_vision`)."""
        if not self.params.require_vision:
            return True
        return self.last_vision_s is not None and now_s - self.last_vision_s <= self.params.vision_timeout_s

    def offboard_ok(self, now_s: float) -> bool:
        """Whether PX4 would accept OFFBOARD now."""
        p = self.params
        return offboard_stream_ok(list(self._setpoint_times), now_s, p.offboard_min_rate_hz, p.offboard_loss_s)

    def taking_off(self) -> bool:
        """A takeoff climb is in progress."""
        return self._takeoff_target_z is not None

    def landed_state(self, vehicle: VehicleState) -> int:
        """MAV_LANDED_STATE for EXTENDED_SYS_STATE."""
        if vehicle.on_ground and not self.taking_off():
            return int(mavlink.MAV_LANDED_STATE_ON_GROUND)
        if self.taking_off():
            return int(mavlink.MAV_LANDED_STATE_TAKEOFF)
        if self.armed and (self.mode.behaviour is Behaviour.LAND or self._rtl_landing):
            return int(mavlink.MAV_LANDED_STATE_LANDING)
        return int(mavlink.MAV_LANDED_STATE_IN_AIR)

    # ----- inputs ----------------------------------------------------------------------------

    def on_vision(self, now_s: float) -> None:
        """A vision pose (or odometry) arrived."""
        self.last_vision_s = now_s

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

    def arm(self, now_s: float, vehicle: VehicleState, force: bool = False) -> tuple[int, str | None]:
        """MAV_CMD_COMPONENT_ARM_DISARM(1): (MAV_RESULT, refusal text)."""
        if self.armed:
            return ACCEPTED, None
        reason = None
        if not force:
            reason = arming_refusal(
                self.mode,
                self.ekf_healthy(now_s),
                self.params.require_vision,
                self.battery_critical,
                not vehicle.on_ground,
            )
        if reason is not None:
            self._event(mavlink.MAV_SEVERITY_CRITICAL, self.profile.statustext_prefix + reason)
            return self.profile.arm_denied_result, reason
        self.armed = True
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
        self._armed_since_s = None
        self._rtl_landing = False
        self._event(mavlink.MAV_SEVERITY_INFO, text)

    def set_mode(self, mode: ModeDef, now_s: float, vehicle: VehicleState) -> tuple[int, str | None]:
        """Change mode (DO_SET_MODE or SET_MODE): (MAV_RESULT, refusal text)."""
        if mode == self.mode:
            return ACCEPTED, None
        reason = mode_change_refusal(mode, self.ekf_healthy(now_s), self.offboard_ok(now_s))
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
        self._event(mavlink.MAV_SEVERITY_INFO, f"Takeoff to {height_m:.1f} m")
        return ACCEPTED, None

    def land(self, now_s: float, vehicle: VehicleState) -> tuple[int, str | None]:
        """MAV_CMD_NAV_LAND: switch to the land mode."""
        return self.set_mode(self.profile.mode(self.profile.land_mode), now_s, vehicle)

    # ----- the per-step update ---------------------------------------------------------------

    def _hold_velocity(self, vehicle: VehicleState, target: Vec3) -> Vec3:
        p = self.params
        k = p.hold_gain_per_s
        vx = k * (target[0] - vehicle.position_ned_m[0])
        vy = k * (target[1] - vehicle.position_ned_m[1])
        vz = k * (target[2] - vehicle.position_ned_m[2])
        speed = math.hypot(vx, vy)
        if speed > p.hold_max_speed_m_s:
            vx, vy = vx * p.hold_max_speed_m_s / speed, vy * p.hold_max_speed_m_s / speed
        return (vx, vy, max(-1.0, min(1.0, vz)))

    def _failsafe(self, mode_name: str, text: str, vehicle: VehicleState) -> None:
        self._event(mavlink.MAV_SEVERITY_CRITICAL, text)
        self._enter(self.profile.mode(mode_name), vehicle)

    def update(self, now_s: float, vehicle: VehicleState) -> MotionCommand:
        """Advance the logic to `now_s` given the true vehicle state; return the airframe command."""
        p = self.params
        if not self.armed:
            return MotionCommand(motors_on=False)
        airborne = not vehicle.on_ground
        behaviour = self.mode.behaviour

        # Failsafes in flight.
        if airborne and behaviour is not Behaviour.LAND:
            if p.require_vision and (self.last_vision_s is None or now_s - self.last_vision_s > p.vision_failsafe_s):
                self._failsafe(self.profile.land_mode, "EKF failsafe: position estimate lost, landing", vehicle)
            elif p.battery_failsafe and self.battery_critical and not self._battery_failsafe_done:
                self._battery_failsafe_done = True
                self._failsafe(self.profile.land_mode, "Battery failsafe: critical, landing", vehicle)
        behaviour = self.mode.behaviour
        if behaviour is Behaviour.OFFBOARD and (
            self.setpoint is None or now_s - self.setpoint.stamp_s > p.offboard_loss_s
        ):
            fallback = self.profile.hold_mode if (self.ekf_healthy(now_s) or not airborne) else self.profile.land_mode
            self._failsafe(fallback, f"Failsafe: offboard setpoints lost, switching to {fallback}", vehicle)
            behaviour = self.mode.behaviour

        # Ground handling: disarm after landing, auto-disarm when idle.
        if vehicle.on_ground and not self.taking_off():
            if self._ground_since_s is None:
                self._ground_since_s = now_s
            idle = now_s - self._ground_since_s
            if behaviour is Behaviour.LAND or self._rtl_landing:
                if idle >= p.land_disarm_delay_s:
                    self._disarm("Land complete, disarming")
                    return MotionCommand(motors_on=False)
            elif p.auto_disarm_s is not None and idle >= p.auto_disarm_s:
                self._disarm("Auto disarm: landed and idle")
                return MotionCommand(motors_on=False)
        else:
            self._ground_since_s = None

        yaw_rate = 0.0
        velocity: Vec3 = (0.0, 0.0, 0.0)
        hold = self._hold_target if self._hold_target is not None else vehicle.position_ned_m

        if self._takeoff_target_z is not None:
            target_z = self._takeoff_target_z
            vx, vy, _ = self._hold_velocity(vehicle, (hold[0], hold[1], target_z))
            remaining_m = vehicle.position_ned_m[2] - target_z
            velocity = (vx, vy, -min(p.takeoff_speed_m_s, max(0.3, p.hold_gain_per_s * remaining_m)))
            if vehicle.position_ned_m[2] <= target_z + 0.05:
                self._takeoff_target_z = None
                self._hold_target = (hold[0], hold[1], target_z)
                self._event(mavlink.MAV_SEVERITY_INFO, "Takeoff complete")
                if behaviour is Behaviour.TAKEOFF:
                    self._enter(self.profile.mode(self.profile.hold_mode), vehicle)
                    self._hold_target = (hold[0], hold[1], target_z)
                    self._braking = False
                velocity = self._hold_velocity(vehicle, self._hold_target)
        elif behaviour in (Behaviour.GUIDED, Behaviour.OFFBOARD):
            sp = self.setpoint
            timeout = p.guided_timeout_s if behaviour is Behaviour.GUIDED else math.inf
            landed_guided = behaviour is Behaviour.GUIDED and vehicle.on_ground
            if sp is not None and now_s - sp.stamp_s <= timeout and not landed_guided:
                if sp.velocity_ned_m_s is not None:
                    velocity = sp.velocity_ned_m_s
                    self._hold_target = vehicle.position_ned_m
                elif sp.position_ned_m is not None:
                    self._hold_target = sp.position_ned_m
                    velocity = self._hold_velocity(vehicle, sp.position_ned_m)
                else:
                    velocity = self._hold_velocity(vehicle, hold)
                if sp.yaw_rate_rad_s is not None:
                    yaw_rate = sp.yaw_rate_rad_s
                elif sp.yaw_rad is not None:
                    yaw_rate = p.yaw_gain_per_s * _wrap(sp.yaw_rad - vehicle.yaw_rad)
            else:
                if sp is not None and not self._guided_stopped and behaviour is Behaviour.GUIDED and not landed_guided:
                    self._guided_stopped = True
                    self._hold_target = self._stop_point(vehicle)
                    self._braking = True
                    hold = self._hold_target
                if not vehicle.on_ground:
                    velocity = self._brake_then_hold(vehicle, hold)
        elif behaviour is Behaviour.HOLD:
            if not vehicle.on_ground:
                velocity = self._brake_then_hold(vehicle, hold)
        elif behaviour is Behaviour.MANUAL:
            velocity = (0.0, 0.0, 0.0)
        elif behaviour is Behaviour.LAND:
            vx, vy, _ = self._hold_velocity(vehicle, hold)
            velocity = (vx, vy, p.land_speed_m_s)
        elif behaviour is Behaviour.RTL:
            velocity = self._rtl_velocity(vehicle)
        return MotionCommand(velocity_ned_m_s=velocity, yaw_rate_rad_s=yaw_rate, motors_on=True)

    def _rtl_velocity(self, vehicle: VehicleState) -> Vec3:
        p = self.params
        if vehicle.on_ground and not self._rtl_landing:
            return (0.0, 0.0, 0.0)
        z_target = min(vehicle.position_ned_m[2], -p.rtl_min_height_m)
        if self._hold_target is None or self._hold_target[2] > z_target:
            self._hold_target = (vehicle.position_ned_m[0], vehicle.position_ned_m[1], z_target)
        if self._rtl_landing:
            vx, vy, _ = self._hold_velocity(vehicle, (self.home_ne_m[0], self.home_ne_m[1], 0.0))
            return (vx, vy, p.land_speed_m_s)
        dn = self.home_ne_m[0] - vehicle.position_ned_m[0]
        de = self.home_ne_m[1] - vehicle.position_ned_m[1]
        dist = math.hypot(dn, de)
        if dist < 0.3:
            self._rtl_landing = True
            self._event(mavlink.MAV_SEVERITY_INFO, "RTL: landing")
            return (0.0, 0.0, p.land_speed_m_s)
        speed = min(p.rtl_speed_m_s, p.hold_gain_per_s * dist + 0.2)
        vz = max(-1.0, min(1.0, p.hold_gain_per_s * (self._hold_target[2] - vehicle.position_ned_m[2])))
        return (speed * dn / dist, speed * de / dist, vz)
