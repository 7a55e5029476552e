"""The safety manager's vocabulary: its states, actions and faults, and the inputs, events and output of a step."""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["Fault", "SafetyAction", "SafetyEvent", "SafetyInputs", "SafetyOutput", "SafetyState"]


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
