"""Safety manager (Ortiz et al., section 4.2, extended): pure watchdog + command filter, time injected.

Two entry points, both pure apart from the manager's own bookkeeping:

- `step(inputs, now_s)` -- the 10 Hz watchdog. It debounces and latches faults and returns a
  `SafetyOutput` whose `action` overrides the mission: NONE, HOVER (autopilot hold mode),
  LAND, LAND_NOW, or STOP_COMMANDS (autopilot link lost: send nothing, keep reconnecting),
  plus `send_poses` (False while vision is stale: never forward a stale pose),
  `allow_commands` (mission velocity commands may pass) and the events of the decisions.
- `filter(command, inputs, now_s)` -- every velocity command on its way to the autopilot. It
  returns None when commanding is forbidden (override active, autopilot link lost, or no
  watchdog `step` within `watchdog_stale_s`) and
  otherwise clamps the command: climbing near the ceiling (height above ground and, when an
  upward rangefinder exists, the measured clearance) and leaving the geofence box are limited
  by a proportional law v <= k * distance_to_limit, which also pushes the vehicle back in
  when it is beyond a limit. Unknown height: no climbing; unknown position with a geofence:
  no translation. The climb limits are applied last and always win.

Impossible readings (NaN/inf, a 0 V battery, a percentage outside 0..100) count as unknown.

Priority when several faults hold at once: battery critical (LAND_NOW) > battery low (LAND) >
GCS-loss or vision-loss land timeout (LAND) > GCS loss or vision loss (HOVER) > nothing.
Autopilot link loss never hides a pending landing: the action stays and `allow_commands` is
False until the link is back. Overrides only apply while the vehicle is airborne (armed and
not landed); on the ground the faults are still reported and block `allow_takeoff`.

Every decision (fault raised or cleared, action change, clamp start/stop, blocked commands,
operator resume) emits a `SafetyEvent` (time, kind, action, message, severity); events from
`filter` and `operator_resume` are delivered with the next `step` output.
"""

from __future__ import annotations

from companion.safety.command_filter import CommandFilter
from companion.safety.config import SafetyConfig
from companion.safety.failsafes import FailsafeRules
from companion.safety.readings import _age, _fmt, _sanitized
from companion.safety.types import Fault, SafetyAction, SafetyEvent, SafetyInputs, SafetyOutput, SafetyState

__all__ = [
    "Fault",
    "SafetyAction",
    "SafetyConfig",
    "SafetyEvent",
    "SafetyInputs",
    "SafetyManager",
    "SafetyOutput",
    "SafetyState",
]


class SafetyManager(FailsafeRules, CommandFilter):
    """Watchdog + command filter (see the module docstring). Pure: time comes in as now_s."""

    # ------------------------------------------------------------------ watchdog
    @property
    def action(self) -> SafetyAction:
        """The action decided by the last step."""
        return self._action

    @property
    def state(self) -> SafetyState:
        """The state decided by the last step."""
        return self._state

    def step(self, inputs: SafetyInputs, now_s: float) -> SafetyOutput:
        """Run the watchdog at now_s (s); call at about 10 Hz."""
        now_s = float(now_s)
        inputs = _sanitized(inputs)
        self._last_inputs = inputs
        self._last_step_s = now_s
        faults: set[Fault] = set()
        low_cond = self._battery_rule(inputs, now_s, faults)
        self._gcs_link_rule(inputs, now_s, faults)
        vision_fresh = self._vision_rule(inputs, now_s, faults)
        autopilot_ok = self._autopilot_link_rule(inputs, now_s, faults)
        self._ceiling_and_geofence_rule(inputs, faults)

        # Latches left over on the ground are cleared (the flight is over).
        if not inputs.armed:
            self._gcs_hover = self._gcs_land = self._vision_hover = self._vision_land = False

        self._report_fault_changes(now_s, frozenset(faults), inputs)
        action, state = self._decide(inputs, autopilot_ok)
        if action is not self._action:
            self._emit(now_s, "action", f"safety action {self._action.value} -> {action.value} "
                       f"({self._reason(action)})", "critical" if action is SafetyAction.LAND_NOW else "warning",
                       action=action)
        self._action, self._state = action, state
        battery_ok = not (self._low.latched or self._critical.latched or low_cond)
        allow_takeoff = autopilot_ok and battery_ok and Fault.GCS_LOST not in faults
        events, self._events = tuple(self._events), []
        return SafetyOutput(
            time_s=now_s, state=state, action=action, send_poses=vision_fresh,
            allow_commands=autopilot_ok and action is SafetyAction.NONE, allow_takeoff=allow_takeoff,
            faults=self._faults, events=events,
        )

    def _decide(self, inputs: SafetyInputs, autopilot_ok: bool) -> tuple[SafetyAction, SafetyState]:
        if inputs.airborne:
            if self._critical.latched:
                return SafetyAction.LAND_NOW, SafetyState.EMERGENCY_LANDING
            if self._low.latched or self._gcs_land or self._vision_land:
                return SafetyAction.LAND, SafetyState.LANDING
            if self._gcs_hover or self._vision_hover:
                return SafetyAction.HOVER, SafetyState.HOLD
        if not autopilot_ok and inputs.last_autopilot_heartbeat_s is not None:
            return SafetyAction.STOP_COMMANDS, SafetyState.NO_AUTOPILOT
        return SafetyAction.NONE, SafetyState.NOMINAL

    def _reason(self, action: SafetyAction) -> str:
        if action is SafetyAction.LAND_NOW:
            return "battery critical"
        if action is SafetyAction.LAND:
            flags = ((self._low.latched, "battery low"), (self._gcs_land, "GCS lost too long"),
                     (self._vision_land, "vision lost too long"))
            return ", ".join(name for flag, name in flags if flag)
        if action is SafetyAction.HOVER:
            return ", ".join(name for flag, name in ((self._gcs_hover, "GCS link lost"),
                                                     (self._vision_hover, "vision lost")) if flag)
        if action is SafetyAction.STOP_COMMANDS:
            return "autopilot link lost"
        return "all clear"

    def _report_fault_changes(self, now_s: float, faults: frozenset[Fault], inputs: SafetyInputs) -> None:
        c = self.config
        details = {
            Fault.BATTERY_LOW: f"battery {self._battery_text(inputs)} below the low threshold for "
                               f"{c.battery_low_debounce_s:g} s",
            Fault.BATTERY_CRITICAL: f"battery {self._battery_text(inputs)} critical for "
                                    f"{c.battery_critical_debounce_s:g} s",
            Fault.GCS_LOST: f"no GCS heartbeat for {c.gcs_timeout_s} s",
            Fault.GCS_LOST_LAND: f"no GCS heartbeat for {c.gcs_land_timeout_s} s",
            Fault.VISION_LOST: f"no fresh pose for {c.vision_timeout_s * 1000:.0f} ms: pose stream stopped",
            Fault.VISION_LOST_LAND: f"no fresh pose for {c.vision_land_timeout_s} s",
            Fault.AUTOPILOT_LOST: f"no autopilot heartbeat for {c.autopilot_timeout_s:g} s",
            Fault.CEILING: f"height {_fmt(inputs.altitude_m)} m at the ceiling {c.ceiling_m:g} m: climb clamped",
            Fault.CEILING_CLEARANCE: f"ceiling clearance {_fmt(inputs.ceiling_clearance_m)} m below "
                                     f"{c.min_ceiling_clearance_m} m: climb clamped",
            Fault.GEOFENCE: "position ("
            + ", ".join(_fmt(x) for x in (inputs.position_ned_m or ()))
            + ") m NED outside the geofence",
        }
        severity = {Fault.BATTERY_CRITICAL: "critical", Fault.AUTOPILOT_LOST: "error", Fault.GCS_LOST_LAND: "error",
                    Fault.VISION_LOST_LAND: "error"}
        for fault in sorted(faults - self._faults):
            self._emit(now_s, fault.value, details[fault], severity.get(fault, "warning"))
        for fault in sorted(self._faults - faults):
            self._emit(now_s, fault.value, f"{fault.value} cleared", "info")
        self._faults = faults

    # ------------------------------------------------------------------ operator
    def operator_resume(self, now_s: float) -> bool:
        """Operator command ending a GCS-loss or vision-loss hover/landing; refused while the cause persists
        or a battery landing is latched. Returns whether it was accepted (an event says why)."""
        inputs = self._last_inputs
        c = self.config
        reasons = []
        if self._low.latched or self._critical.latched:
            reasons.append("battery landing cannot be cancelled")
        if inputs is not None and c.gcs_timeout_s is not None and inputs.last_gcs_heartbeat_s is not None \
                and _age(now_s, inputs.last_gcs_heartbeat_s) > c.gcs_timeout_s:
            reasons.append("GCS link still lost")
        if (self._vision_hover or self._vision_land) and (
                inputs is None or _age(now_s, inputs.last_pose_s) > c.vision_timeout_s):
            reasons.append("vision still lost")
        if reasons:
            self._emit(now_s, "resume", "operator resume refused: " + ", ".join(reasons), "warning")
            return False
        self._gcs_hover = self._gcs_land = self._vision_hover = self._vision_land = False
        self._emit(now_s, "resume", "operator resume accepted", "info")
        return True

    ack_gcs = operator_resume
