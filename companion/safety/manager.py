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

import enum
import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from companion.control.types import VelocityCommand
from companion.errors import ConfigError

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


class SafetyState(enum.StrEnum):
    """Overall safety state."""

    NOMINAL = "nominal"
    HOLD = "hold"  # hovering in the autopilot's hold mode (GCS or vision lost)
    LANDING = "landing"  # battery low, or a loss that lasted past its land timeout
    EMERGENCY_LANDING = "emergency-landing"  # battery critical
    NO_AUTOPILOT = "no-autopilot"  # autopilot heartbeats missing, nothing else pending


class SafetyAction(enum.StrEnum):
    """What the daemon must do now."""

    NONE = "none"
    HOVER = "hover"  # switch the autopilot to its hold / loiter mode, stop the mission's commands
    LAND = "land"  # land where the vehicle is
    LAND_NOW = "land-now"  # land immediately (battery critical)
    STOP_COMMANDS = "stop-commands"  # autopilot link lost: send no commands, keep reconnecting


class Fault(enum.StrEnum):
    """Conditions the manager watches (also the `kind` of their events)."""

    CEILING = "ceiling"
    CEILING_CLEARANCE = "ceiling-clearance"
    GEOFENCE = "geofence"
    BATTERY_LOW = "battery-low"
    BATTERY_CRITICAL = "battery-critical"
    GCS_LOST = "gcs-lost"
    GCS_LOST_LAND = "gcs-lost-land"
    VISION_LOST = "vision-lost"
    VISION_LOST_LAND = "vision-lost-land"
    AUTOPILOT_LOST = "autopilot-lost"


def _check_positive(cfg: Any, name: str, allow_none: bool = False) -> None:
    value = getattr(cfg, name)
    if value is None and allow_none:
        return
    if value is None or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"safety.{name}: must be a finite number > 0, got {value!r}")


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds, timeouts and gains of the safety behaviours (SI units; None disables a check).

    ceiling_m: highest allowed height above ground (m); climbing is limited to
        ceiling_gain_per_s * (ceiling_m - height) and the vehicle is pushed down above it.
    ceiling_hysteresis_m: the CEILING fault clears below ceiling_m - this (m).
    min_ceiling_clearance_m: smallest allowed distance to an overhead obstacle measured by an
        upward rangefinder (m); climbing limited like the ceiling.
    battery_low_v / battery_low_pct: land when below either for battery_low_debounce_s (s).
    battery_critical_v / battery_critical_pct: land now when below either for
        battery_critical_debounce_s (s).
    battery_hysteresis_v / battery_hysteresis_pct: a debounce restarts only once the reading is
        back above threshold + hysteresis.
    gcs_timeout_s: no GCS heartbeat for this long -> hover; gcs_land_timeout_s -> land.
        Only after a first GCS heartbeat was seen (a vehicle flown without a GCS is not "lost").
    vision_timeout_s: no fresh pose for this long -> stop poses, hover; vision_land_timeout_s -> land.
    vision_auto_resume_s: when set, a vision hover ends by itself after poses have been fresh for
        this long (s); None = only `operator_resume` ends it.
    gcs_auto_resume_s: when set, a GCS-loss hover (not a landing) ends by itself after GCS
        heartbeats have been back for this long (s); None = only `operator_resume` ends it.
    autopilot_timeout_s: no autopilot heartbeat for this long -> STOP_COMMANDS.
    geofence_min_ned_m / geofence_max_ned_m: NED box (m) or None; velocities toward a face are
        limited to geofence_gain_per_s * distance to it.
    watchdog_stale_s: `filter` blocks every command when the last `step` is older than this (s)
        or `step` never ran: commands only pass while the watchdog is alive.
    """

    ceiling_m: float = 10.0
    ceiling_hysteresis_m: float = 0.3
    ceiling_gain_per_s: float = 1.0
    min_ceiling_clearance_m: float | None = 1.0
    battery_low_v: float | None = 14.0
    battery_low_pct: float | None = 20.0
    battery_critical_v: float | None = 13.2
    battery_critical_pct: float | None = 8.0
    battery_low_debounce_s: float = 3.0
    battery_critical_debounce_s: float = 1.0
    battery_hysteresis_v: float = 0.2
    battery_hysteresis_pct: float = 2.0
    gcs_timeout_s: float | None = 5.0
    gcs_land_timeout_s: float | None = 30.0
    vision_timeout_s: float = 0.5
    vision_land_timeout_s: float | None = 10.0
    vision_auto_resume_s: float | None = None
    gcs_auto_resume_s: float | None = None
    autopilot_timeout_s: float = 3.0
    geofence_min_ned_m: tuple[float, float, float] | None = None
    geofence_max_ned_m: tuple[float, float, float] | None = None
    geofence_gain_per_s: float = 1.0
    watchdog_stale_s: float = 1.0

    def __post_init__(self) -> None:
        optional = {
            "min_ceiling_clearance_m", "battery_low_v", "battery_low_pct", "battery_critical_v",
            "battery_critical_pct", "gcs_timeout_s", "gcs_land_timeout_s", "vision_land_timeout_s",
            "vision_auto_resume_s", "gcs_auto_resume_s",
        }
        for f in fields(self):
            if f.name.startswith("geofence_") and f.name != "geofence_gain_per_s":
                continue
            _check_positive(self, f.name, allow_none=f.name in optional)
        for low, crit in (("battery_low_v", "battery_critical_v"), ("battery_low_pct", "battery_critical_pct")):
            lo, cr = getattr(self, low), getattr(self, crit)
            if lo is not None and cr is not None and cr > lo:
                raise ConfigError(f"safety.{crit}: {cr} must not exceed safety.{low} ({lo})")
        for hover, land in (("gcs_timeout_s", "gcs_land_timeout_s"), ("vision_timeout_s", "vision_land_timeout_s")):
            h, ld = getattr(self, hover), getattr(self, land)
            if h is not None and ld is not None and ld < h:
                raise ConfigError(f"safety.{land}: {ld} s must not be shorter than safety.{hover} ({h} s)")
        if (self.geofence_min_ned_m is None) != (self.geofence_max_ned_m is None):
            raise ConfigError("safety.geofence_min_ned_m / geofence_max_ned_m: give both or neither")
        if self.geofence_min_ned_m is not None and self.geofence_max_ned_m is not None:
            lo_arr = np.asarray(self.geofence_min_ned_m, dtype=np.float64)
            hi_arr = np.asarray(self.geofence_max_ned_m, dtype=np.float64)
            if lo_arr.shape != (3,) or hi_arr.shape != (3,) or not np.all(np.isfinite(lo_arr + hi_arr)):
                raise ConfigError("safety.geofence_min_ned_m / geofence_max_ned_m: three finite numbers each")
            if np.any(lo_arr >= hi_arr):
                raise ConfigError("safety.geofence_min_ned_m: every component must be below geofence_max_ned_m")


@dataclass(frozen=True)
class SafetyInputs:
    """One snapshot of what the safety manager watches (None = unknown / not available).

    battery_v (V), battery_pct (0-100); altitude_m: height above ground (m, up; -z NED when the
    ground is at z = 0); ceiling_clearance_m: upward rangefinder distance to the ceiling (m);
    last_gcs_heartbeat_s, last_pose_s, last_autopilot_heartbeat_s: monotonic times (s) of the
    last GCS heartbeat, last fresh vision pose and last autopilot heartbeat;
    position_ned_m: (north, east, down) in m; armed, landed: from the autopilot.
    Unknown altitude makes `filter` refuse any climb; unknown position with a geofence
    configured makes it refuse any translation. NaN/inf readings count as unknown.
    """

    battery_v: float | None = None
    battery_pct: float | None = None
    altitude_m: float | None = None
    ceiling_clearance_m: float | None = None
    last_gcs_heartbeat_s: float | None = None
    last_pose_s: float | None = None
    last_autopilot_heartbeat_s: float | None = None
    position_ned_m: tuple[float, float, float] | None = None
    armed: bool = False
    landed: bool = True

    @property
    def airborne(self) -> bool:
        """Armed and not landed."""
        return self.armed and not self.landed


@dataclass(frozen=True)
class SafetyEvent:
    """One safety decision: time (s), kind (a `Fault` value, 'action', 'resume', 'commands'), action, text."""

    time_s: float
    kind: str
    action: SafetyAction
    message: str
    severity: str = "warning"  # "info" | "warning" | "error" | "critical"


@dataclass(frozen=True)
class SafetyOutput:
    """Result of one watchdog step."""

    time_s: float
    state: SafetyState
    action: SafetyAction
    send_poses: bool
    allow_commands: bool
    allow_takeoff: bool
    faults: frozenset[Fault]
    events: tuple[SafetyEvent, ...]

    @property
    def message(self) -> str:
        """One-line status, e.g. 'landing: battery-low' or 'nominal'."""
        if not self.faults:
            return self.state.value
        return f"{self.state.value}: {', '.join(sorted(f.value for f in self.faults))}"


def _fmt(value: float | None) -> str:
    return "?" if value is None else f"{value:.2f}"


def _age(now_s: float, last_s: float | None) -> float:
    """Seconds since last_s; infinite when there is none or it is not a finite time."""
    return math.inf if last_s is None or not math.isfinite(last_s) else now_s - last_s


def _finite(value: float | None, lo: float = -math.inf, hi: float = math.inf) -> float | None:
    """value as a float when it is a finite reading within [lo, hi], else None (unknown)."""
    if value is None:
        return None
    x = float(value)
    return x if math.isfinite(x) and lo <= x <= hi else None


def _sanitized(inputs: SafetyInputs) -> SafetyInputs:
    """The inputs with impossible readings turned into "unknown" (None).

    NaN/inf anywhere, a battery voltage <= 0 V (an autopilot without a battery monitor reports
    0), a percentage outside 0..100 and a negative ceiling clearance are not readings: treating
    them as values would either trigger a false landing or silently disable a limit (NaN compares
    false). Unknown altitude and position are then handled conservatively by `filter`.
    """
    pos: tuple[float, float, float] | None = None
    if inputs.position_ned_m is not None:
        p = np.asarray(inputs.position_ned_m, dtype=np.float64)
        if p.shape == (3,) and bool(np.all(np.isfinite(p))):
            pos = (float(p[0]), float(p[1]), float(p[2]))
    return replace(
        inputs,
        battery_v=_finite(inputs.battery_v, lo=1e-6),
        battery_pct=_finite(inputs.battery_pct, lo=0.0, hi=100.0),
        altitude_m=_finite(inputs.altitude_m),
        ceiling_clearance_m=_finite(inputs.ceiling_clearance_m, lo=0.0),
        position_ned_m=pos,
    )


def _below(value: float | None, threshold: float | None) -> bool:
    return value is not None and threshold is not None and value < threshold


def _above(value: float | None, threshold: float | None) -> bool:
    """value >= threshold, or no reading/threshold at all (nothing keeps a debounce running)."""
    return value is None or threshold is None or value >= threshold


class _Debounce:
    """Condition true for `hold_s` -> latched; a reading back in the clear-zone restarts the timer."""

    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s
        self.since_s: float | None = None
        self.latched = False

    def update(self, now_s: float, condition: bool, clear: bool) -> bool:
        """Return True exactly when the latch sets."""
        if self.latched:
            return False
        if condition:
            if self.since_s is None:
                self.since_s = now_s
            if now_s - self.since_s >= self.hold_s - 1e-9:
                self.latched = True
                return True
        elif clear:
            self.since_s = None
        return False

    def reset(self) -> None:
        self.since_s = None
        self.latched = False


class SafetyManager:
    """Watchdog + command filter (see the module docstring). Pure: time comes in as now_s."""

    def __init__(self, config: SafetyConfig | None = None) -> None:
        self.config = config if config is not None else SafetyConfig()
        c = self.config
        self._low = _Debounce(c.battery_low_debounce_s)
        self._critical = _Debounce(c.battery_critical_debounce_s)
        self._gcs_hover = False
        self._gcs_land = False
        self._vision_hover = False
        self._vision_land = False
        self._vision_fresh_since_s: float | None = None
        self._gcs_back_since_s: float | None = None
        self._faults: frozenset[Fault] = frozenset()
        self._action = SafetyAction.NONE
        self._state = SafetyState.NOMINAL
        self._events: list[SafetyEvent] = []
        self._clamping: frozenset[Fault] = frozenset()
        self._blocked = False
        self._last_inputs: SafetyInputs | None = None
        self._last_step_s: float | None = None

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
        c = self.config
        now_s = float(now_s)
        inputs = _sanitized(inputs)
        self._last_inputs = inputs
        self._last_step_s = now_s
        faults: set[Fault] = set()

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

        # Autopilot link.
        autopilot_ok = _age(now_s, inputs.last_autopilot_heartbeat_s) <= c.autopilot_timeout_s
        # an autopilot never heard yet (the daemon starting before it) is not a lost link: nothing can be
        # commanded (allow_commands/allow_takeoff stay False) but there is no fault to report
        if not autopilot_ok and inputs.last_autopilot_heartbeat_s is not None:
            faults.add(Fault.AUTOPILOT_LOST)

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

    @staticmethod
    def _battery_text(inputs: SafetyInputs) -> str:
        parts = []
        if inputs.battery_v is not None:
            parts.append(f"{inputs.battery_v:.2f} V")
        if inputs.battery_pct is not None:
            parts.append(f"{inputs.battery_pct:.0f} %")
        return " / ".join(parts) if parts else "unknown"

    def _outside_geofence(self, inputs: SafetyInputs) -> bool:
        c = self.config
        if c.geofence_min_ned_m is None or c.geofence_max_ned_m is None or inputs.position_ned_m is None:
            return False
        p = np.asarray(inputs.position_ned_m, dtype=np.float64)
        return bool(np.any(p < np.asarray(c.geofence_min_ned_m)) or np.any(p > np.asarray(c.geofence_max_ned_m)))

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

    # ------------------------------------------------------------------ events
    def _emit(self, now_s: float, kind: Fault | str, message: str, severity: str = "warning",
              action: SafetyAction | None = None) -> None:
        self._events.append(SafetyEvent(time_s=float(now_s), kind=str(kind), action=action or self._action,
                                        message=message, severity=severity))
