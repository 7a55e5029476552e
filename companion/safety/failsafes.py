"""The safety manager's failsafe rules, one method each: battery, GCS link, vision, autopilot link, and the
ceiling / clearance / geofence limits. `SafetyManager.step` runs them in that order on one sanitized snapshot;
each adds the faults it finds, sets its hover / land latches and emits the events of its decisions."""

from __future__ import annotations

import numpy as np

from companion.safety.manager_state import ManagerState
from companion.safety.readings import _above, _age, _below
from companion.safety.types import Fault, SafetyInputs

__all__ = ["FailsafeRules"]


class FailsafeRules(ManagerState):
    """The failsafe rules of `SafetyManager.step` (a mixin of `ManagerState`)."""

    def _battery_rule(self, inputs: SafetyInputs, now_s: float, faults: set[Fault]) -> bool:
        """Battery failsafe; returns whether a reading is below a low threshold now (no takeoff then)."""
        c = self.config
        # Battery: debounced, latched; the latch clears only once disarmed on a healthy battery.
        low_cond = _below(inputs.battery_v, c.battery_low_v) or _below(inputs.battery_pct, c.battery_low_pct)
        low_clear = _above(inputs.battery_v, None if c.battery_low_v is None else c.battery_low_v
                           + c.battery_hysteresis_v) and _above(
            inputs.battery_pct, None if c.battery_low_pct is None else c.battery_low_pct + c.battery_hysteresis_pct)
        crit_cond = _below(inputs.battery_v, c.battery_critical_v) or _below(inputs.battery_pct,
                                                                             c.battery_critical_pct)
        crit_clear = _above(inputs.battery_v, None if c.battery_critical_v is None else c.battery_critical_v
                            + c.battery_hysteresis_v) and _above(
            inputs.battery_pct,
            None if c.battery_critical_pct is None else c.battery_critical_pct + c.battery_hysteresis_pct)
        if not inputs.armed and low_clear:
            for latch, kind in ((self._low, Fault.BATTERY_LOW), (self._critical, Fault.BATTERY_CRITICAL)):
                if latch.latched:
                    latch.reset()
                    self._emit(now_s, kind, f"{kind.value} cleared: battery {self._battery_text(inputs)}", "info")
        self._low.update(now_s, low_cond, low_clear)
        self._critical.update(now_s, crit_cond, crit_clear)
        if self._low.latched:
            faults.add(Fault.BATTERY_LOW)
        if self._critical.latched:
            faults.add(Fault.BATTERY_CRITICAL)
        return low_cond

    def _gcs_link_rule(self, inputs: SafetyInputs, now_s: float, faults: set[Fault]) -> None:
        """GCS-link failsafe, with its automatic resume when configured."""
        c = self.config
        # GCS link: only once a GCS has been heard; hover, then land; latched until operator resume.
        gcs_age = _age(now_s, inputs.last_gcs_heartbeat_s)
        if c.gcs_timeout_s is not None and inputs.last_gcs_heartbeat_s is not None:
            if gcs_age > c.gcs_timeout_s:
                faults.add(Fault.GCS_LOST)
                if inputs.airborne:
                    self._gcs_hover = True
            if c.gcs_land_timeout_s is not None and gcs_age > c.gcs_land_timeout_s:
                faults.add(Fault.GCS_LOST_LAND)
                if inputs.airborne:
                    self._gcs_land = True
            if gcs_age <= c.gcs_timeout_s and self._gcs_hover and not self._gcs_land \
                    and c.gcs_auto_resume_s is not None and self._gcs_back_since_s is not None \
                    and now_s - self._gcs_back_since_s >= c.gcs_auto_resume_s:
                self._gcs_hover = False
                self._emit(now_s, "resume", "GCS link back: hover ended automatically", "info")
            if gcs_age > c.gcs_timeout_s:
                self._gcs_back_since_s = None
            elif self._gcs_back_since_s is None:
                self._gcs_back_since_s = now_s

    def _vision_rule(self, inputs: SafetyInputs, now_s: float, faults: set[Fault]) -> bool:
        """Vision failsafe; returns whether the poses are fresh (they may be forwarded)."""
        c = self.config
        # Vision: stale poses are never forwarded; airborne -> hover, then land.
        pose_age = _age(now_s, inputs.last_pose_s)
        vision_fresh = pose_age <= c.vision_timeout_s
        if not vision_fresh and (inputs.airborne or inputs.last_pose_s is not None):
            faults.add(Fault.VISION_LOST)
            if inputs.airborne:
                self._vision_hover = True
            if c.vision_land_timeout_s is not None and pose_age > c.vision_land_timeout_s:
                faults.add(Fault.VISION_LOST_LAND)
                if inputs.airborne:
                    self._vision_land = True
        if vision_fresh:
            if self._vision_fresh_since_s is None:
                self._vision_fresh_since_s = now_s
            if (c.vision_auto_resume_s is not None and self._vision_hover and not self._vision_land
                    and now_s - self._vision_fresh_since_s >= c.vision_auto_resume_s):
                self._vision_hover = False
                self._emit(now_s, "resume", "vision back: hover ended automatically", "info")
        else:
            self._vision_fresh_since_s = None
        return vision_fresh

    def _autopilot_link_rule(self, inputs: SafetyInputs, now_s: float, faults: set[Fault]) -> bool:
        """Autopilot-link failsafe; returns whether the link is alive."""
        c = self.config
        # Autopilot link.
        autopilot_ok = _age(now_s, inputs.last_autopilot_heartbeat_s) <= c.autopilot_timeout_s
        # an autopilot never heard yet (the daemon starting before it) is not a lost link: nothing can be
        # commanded (allow_commands/allow_takeoff stay False) but there is no fault to report
        if not autopilot_ok and inputs.last_autopilot_heartbeat_s is not None:
            faults.add(Fault.AUTOPILOT_LOST)
        return autopilot_ok

    def _ceiling_and_geofence_rule(self, inputs: SafetyInputs, faults: set[Fault]) -> None:
        """Ceiling, ceiling-clearance and geofence faults."""
        c = self.config
        # Ceiling, clearance and geofence (enforced by filter(); reported here with hysteresis).
        if inputs.altitude_m is not None:
            was = Fault.CEILING in self._faults
            limit = c.ceiling_m - (c.ceiling_hysteresis_m if was else 0.0)
            if inputs.altitude_m >= limit:
                faults.add(Fault.CEILING)
        if inputs.ceiling_clearance_m is not None and c.min_ceiling_clearance_m is not None:
            was = Fault.CEILING_CLEARANCE in self._faults
            limit = c.min_ceiling_clearance_m + (c.ceiling_hysteresis_m if was else 0.0)
            if inputs.ceiling_clearance_m <= limit:
                faults.add(Fault.CEILING_CLEARANCE)
        if self._outside_geofence(inputs):
            faults.add(Fault.GEOFENCE)

    def _outside_geofence(self, inputs: SafetyInputs) -> bool:
        c = self.config
        if c.geofence_min_ned_m is None or c.geofence_max_ned_m is None or inputs.position_ned_m is None:
            return False
        p = np.asarray(inputs.position_ned_m, dtype=np.float64)
        return bool(np.any(p < np.asarray(c.geofence_min_ned_m)) or np.any(p > np.asarray(c.geofence_max_ned_m)))
