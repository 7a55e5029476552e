"""The fake autopilot's flight logic: arming, modes, takeoff/land, setpoints and failsafes.

A synchronous state machine (no I/O, no clock: every call takes `now_s`). The
MAVLink endpoint in `autopilot.py` feeds it decoded commands and setpoints and
asks it each physics step for the `MotionCommand` of the airframe.

Rules modelled on the real autopilots (details in docs/fake_autopilot.md):
- arming is refused without a ready EKF when `require_vision` (non-GPS configuration;
  `ekf.py`), in a mode that is not armable, or with a critical battery;
- ArduPilot GUIDED: a velocity setpoint is flown for at most `guided_timeout_s`
  (GUID_TIMEOUT, 3 s) after it arrived, then the vehicle stops and holds;
  setpoints are ignored while landed; NAV_TAKEOFF climbs inside GUIDED;
- PX4 OFFBOARD: the mode is refused unless setpoints are streaming (more than
  `offboard_min_rate_hz` over the last second and the last one < `offboard_loss_s`
  old); when the stream stops for `offboard_loss_s` it falls back to AUTO.LOITER
  (or AUTO.LAND without a position estimate); NAV_TAKEOFF switches to AUTO.TAKEOFF
  which hands over to AUTO.LOITER at the takeoff height;
- in flight, a lost position estimate (vision stale for `vision_failsafe_s`) or a
  critical battery switches to the land mode; landing disarms on the ground;
- ArduPilot (measured on ArduCopter SITL): no mode check while disarmed, the EKF's pre-arm texts,
  a spool-up before the take-off climb, shaped GUIDED velocities, FS_EKF instead of a vision failsafe.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.autopilot.guidance import ShapedVelocity, shape_velocity_ne
from companion.sim.autopilot.modes import ModeLogic
from companion.sim.autopilot.profiles import Behaviour
from companion.sim.autopilot.rules import (
    FlightParams,
    Setpoint,
    arming_refusal,
    mode_change_refusal,
    offboard_stream_ok,
)
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


def _wrap(angle_rad: float) -> float:
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


class FlightLogic(ModeLogic):
    """The fake's flight logic: `ModeLogic` plus the per-step update (mutable; one per simulated vehicle)."""

    def _failsafe(self, mode_name: str, text: str, vehicle: VehicleState) -> None:
        self._event(mavlink.MAV_SEVERITY_CRITICAL, text)
        self._enter(self.profile.mode(mode_name), vehicle)

    def update(self, now_s: float, vehicle: VehicleState) -> MotionCommand:
        """Advance the logic to `now_s` given the true vehicle state; return the airframe command."""
        p, timing = self.params, self.timing
        dt = 0.0 if self._last_update_s is None else max(0.0, now_s - self._last_update_s)
        self._last_update_s = now_s
        if not self.armed:
            return MotionCommand(motors_on=False)
        airborne = not vehicle.on_ground
        if self._takeoff_cmd_s is not None and now_s - self._takeoff_cmd_s >= 1.0:
            self.ekf.height_agl_valid = True  # the SITL's EKF reports a height above ground ~1 s after NAV_TAKEOFF

        # Failsafes in flight.
        if self.ardupilot:
            self._fs_ekf(now_s, vehicle)
        elif airborne and self.mode.behaviour is not Behaviour.LAND and p.require_vision:
            age = self.ekf.vision_age_s(now_s)
            if age is None or age > timing.vision_failsafe_s:
                self._failsafe(self.profile.land_mode, "EKF failsafe: position estimate lost, landing", vehicle)
        if (
            airborne
            and self.mode.behaviour is not Behaviour.LAND
            and p.battery_failsafe
            and self.battery_critical
            and not self._battery_failsafe_done
        ):
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
                if idle >= timing.land_disarm_delay_s:
                    self._disarm("Disarming motors" if self.ardupilot else "Land complete, disarming")
                    return MotionCommand(motors_on=False)
            elif p.auto_disarm_s is not None and idle >= p.auto_disarm_s:
                self._disarm("Auto disarm: landed and idle")
                return MotionCommand(motors_on=False)
        else:
            self._ground_since_s = None

        yaw_rate = 0.0
        velocity: Vec3 = (0.0, 0.0, 0.0)
        hold = self._hold_target if self._hold_target is not None else vehicle.position_ned_m

        if self._spool_until_s is not None and now_s < self._spool_until_s:
            return MotionCommand(velocity_ned_m_s=(0.0, 0.0, 0.0), yaw_rate_rad_s=0.0, motors_on=True)
        if self._takeoff_target_z is not None:
            target_z = self._takeoff_target_z
            vx, vy, _ = self._hold_velocity(vehicle, (hold[0], hold[1], target_z))
            remaining_m = vehicle.position_ned_m[2] - target_z
            gain = timing.takeoff_gain_per_s or p.hold_gain_per_s
            velocity = (vx, vy, -min(timing.takeoff_speed_m_s, max(0.3, gain * remaining_m)))
            if vehicle.position_ned_m[2] <= target_z + 0.05:
                self._takeoff_target_z = None
                self._spool_until_s = None
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
            vx, vy, vz = self._hold_velocity(vehicle, hold)
            velocity = (vx, vy, vz if now_s < self._land_pause_until_s else timing.land_speed_m_s)
        elif behaviour is Behaviour.RTL:
            velocity = self._rtl_velocity(vehicle)
        if behaviour is Behaviour.GUIDED and timing.guided_jerk_m_s3 > 0.0 and not vehicle.on_ground:
            if self._shaped is None:
                v = vehicle.velocity_ned_m_s
                self._shaped = ShapedVelocity((v[0], v[1]), (0.0, 0.0))
            self._shaped = shape_velocity_ne(
                self._shaped, (velocity[0], velocity[1]), timing.guided_accel_m_s2, timing.guided_jerk_m_s3, dt
            )
            velocity = (self._shaped.velocity_ne_m_s[0], self._shaped.velocity_ne_m_s[1], velocity[2])
        else:
            self._shaped = None
        return MotionCommand(velocity_ned_m_s=velocity, yaw_rate_rad_s=yaw_rate, motors_on=True)

    def _fs_ekf(self, now_s: float, vehicle: VehicleState) -> None:
        """ArduCopter's FS_EKF (ekf_check.cpp): once the EKF has no position (or its variances exceed
        FS_EKF_THRESH) for 10 checks at 10 Hz: "EKF variance", then LAND with a pause (ALT_HOLD with
        FS_EKF_ACTION 2), only in a mode that needs a position unless FS_EKF_ACTION is 3. Cleared
        ("EKF Failsafe Cleared") after as long with a position again; the mode stays."""
        p = self.params
        if p.fs_ekf_thresh <= 0.0 or not p.require_vision:
            return
        age = self.ekf.vision_age_s(now_s)
        failing = self.ekf.had_position and (age is None or age > self.timing.vision_failsafe_s)
        change = self._fs_ekf_check.update(now_s, failing, self.ekf.has_position(now_s))
        if change == "cleared":
            self._event(mavlink.MAV_SEVERITY_CRITICAL, "EKF Failsafe Cleared")
        if change != "triggered":
            return
        self._event(mavlink.MAV_SEVERITY_CRITICAL, "EKF variance")
        if (not self.mode.needs_position and p.fs_ekf_action != 3) or self.mode.behaviour is Behaviour.LAND:
            return
        target = "ALT_HOLD" if p.fs_ekf_action == 2 else self.profile.land_mode
        self._enter(self.profile.mode(target), vehicle)
        if target == self.profile.land_mode:
            self._land_pause_until_s = now_s + self.timing.failsafe_land_pause_s
        self._event(mavlink.MAV_SEVERITY_CRITICAL, f"EKF Failsafe: changed to {target} Mode")

    def _rtl_velocity(self, vehicle: VehicleState) -> Vec3:
        p = self.params
        if vehicle.on_ground and not self._rtl_landing:
            return (0.0, 0.0, 0.0)
        z_target = min(vehicle.position_ned_m[2], -p.rtl_min_height_m)
        if self._hold_target is None or self._hold_target[2] > z_target:
            self._hold_target = (vehicle.position_ned_m[0], vehicle.position_ned_m[1], z_target)
        if self._rtl_landing:
            vx, vy, _ = self._hold_velocity(vehicle, (self.home_ne_m[0], self.home_ne_m[1], 0.0))
            return (vx, vy, self.timing.land_speed_m_s)
        dn = self.home_ne_m[0] - vehicle.position_ned_m[0]
        de = self.home_ne_m[1] - vehicle.position_ned_m[1]
        dist = math.hypot(dn, de)
        if dist < 0.3:
            self._rtl_landing = True
            self._event(mavlink.MAV_SEVERITY_INFO, "RTL: landing")
            return (0.0, 0.0, self.timing.land_speed_m_s)
        speed = min(p.rtl_speed_m_s, p.hold_gain_per_s * dist + 0.2)
        vz = max(-1.0, min(1.0, p.hold_gain_per_s * (self._hold_target[2] - vehicle.position_ned_m[2])))
        return (speed * dn / dist, speed * de / dist, vz)
