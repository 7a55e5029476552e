"""The safety manager's command filter: every velocity command on its way to the autopilot is blocked
(commanding forbidden) or clamped (ceiling, ceiling clearance, geofence)."""

from __future__ import annotations

import numpy as np

from companion.control.types import VelocityCommand
from companion.safety.manager_state import ManagerState
from companion.safety.readings import _age, _sanitized
from companion.safety.types import Fault, SafetyAction, SafetyInputs

__all__ = ["CommandFilter"]


class CommandFilter(ManagerState):
    """`SafetyManager.filter` (a mixin of `ManagerState`)."""

    # ------------------------------------------------------------------ filter
    def filter(self, command: VelocityCommand, inputs: SafetyInputs, now_s: float) -> VelocityCommand | None:
        """The command to send (clamped), or None when commanding is forbidden.

        Unknown (None or non-finite) altitude: no climbing at all. Geofence configured but the
        position unknown: no translation at all (yaw only). The ceiling and clearance limits are
        applied last, so no other limit can turn a command into a climb through them.
        """
        c = self.config
        now_s = float(now_s)
        inputs = _sanitized(inputs)
        autopilot_ok = _age(now_s, inputs.last_autopilot_heartbeat_s) <= c.autopilot_timeout_s
        watchdog_ok = _age(now_s, self._last_step_s) <= c.watchdog_stale_s
        blocked = not autopilot_ok or not watchdog_ok or self._action is not SafetyAction.NONE
        if blocked != self._blocked:
            if not watchdog_ok:
                why = "safety watchdog not running"
            elif not autopilot_ok:
                why = "autopilot link lost"
            else:
                why = f"safety action {self._action.value}"
            self._emit(now_s, "commands", f"mission commands blocked: {why}" if blocked else "mission commands allowed",
                       "warning" if blocked else "info")
            self._blocked = blocked
        if blocked:
            return None
        v = np.array([command.vx_m_s, command.vy_m_s, command.vz_m_s])
        clamping: set[Fault] = set()
        # Geofence: velocity toward a face <= k * distance to it; pushes back in when outside.
        if c.geofence_min_ned_m is not None and c.geofence_max_ned_m is not None:
            if inputs.position_ned_m is None:
                clipped = np.zeros(3)
            else:
                p = np.asarray(inputs.position_ned_m, dtype=np.float64)
                hi = c.geofence_gain_per_s * (np.asarray(c.geofence_max_ned_m) - p)
                lo = c.geofence_gain_per_s * (np.asarray(c.geofence_min_ned_m) - p)
                clipped = np.minimum(np.maximum(v, lo), hi)
            if np.any(clipped != v):
                clamping.add(Fault.GEOFENCE)
            v = clipped
        # Ceiling: climb rate (-vz) <= k * room; pushes down when above; no climb when the height is unknown.
        vz_min = 0.0 if inputs.altitude_m is None else -c.ceiling_gain_per_s * (c.ceiling_m - inputs.altitude_m)
        if v[2] < vz_min:
            v[2] = vz_min
            clamping.add(Fault.CEILING)
        if inputs.ceiling_clearance_m is not None and c.min_ceiling_clearance_m is not None:
            vz_min = -c.ceiling_gain_per_s * (inputs.ceiling_clearance_m - c.min_ceiling_clearance_m)
            if v[2] < vz_min:
                v[2] = vz_min
                clamping.add(Fault.CEILING_CLEARANCE)
        changed = frozenset(clamping)
        for fault in sorted(changed - self._clamping):
            self._emit(now_s, fault.value, f"{fault.value}: command clamped", "warning")
        for fault in sorted(self._clamping - changed):
            self._emit(now_s, fault.value, f"{fault.value}: command no longer clamped", "info")
        self._clamping = changed
        if not clamping:
            return command
        return VelocityCommand(float(v[0]), float(v[1]), float(v[2]), command.yaw_rate_rad_s, command.frame)
