"""The mission executor's types: its states, requests, events and per-step input and output
(`companion.mission.executor.MissionExecutor`; re-exported there)."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any

from companion.checks import FloatArray
from companion.mission.model import Action

__all__ = [
    "TERMINAL_STATES",
    "ActionResult",
    "EventKind",
    "ExecutorOutput",
    "Goal",
    "MissionEvent",
    "NavSnapshot",
    "Progress",
    "Request",
    "RequestKind",
    "State",
]


class State(enum.StrEnum):
    """Executor states."""

    IDLE = "idle"  # loaded, not started
    RUNNING = "running"
    PAUSED = "paused"  # operator pause: hold, timers frozen
    COMPLETED = "completed"  # every action succeeded
    FAILED = "failed"  # an action failed or timed out: mission aborted, vehicle holds
    ABORTED = "aborted"  # abort() by the operator or the safety manager: vehicle holds


_TIME_EPS_S = 1e-9  # float slack on time comparisons (s)
_ALONG_PIPE_WAIT = "along_pipe_wait_s"  # _Running.extra key: when the action began waiting for the along-pipe position

TERMINAL_STATES = frozenset({State.COMPLETED, State.FAILED, State.ABORTED})


class RequestKind(enum.StrEnum):
    """Discrete things the daemon must do for the executor."""

    ARM = "arm"
    TAKEOFF = "takeoff"  # height_m above home
    LAND = "land"
    HOLD = "hold"  # autopilot hold / loiter mode; no notify expected
    PHOTO = "photo"  # camera


class EventKind(enum.StrEnum):
    """Kinds of mission events."""

    MISSION_STARTED = "mission-started"
    ACTION_STARTED = "action-started"
    ACTION_SUCCEEDED = "action-succeeded"
    ACTION_FAILED = "action-failed"
    ACTION_WAITING = "action-waiting"  # waits for the along-pipe position (NavSnapshot.along_pipe_known)
    ACTION_CONTINUED = "action-continued"  # ... and goes on
    REQUEST = "request"
    REQUEST_DONE = "request-done"
    MISSION_PAUSED = "mission-paused"
    MISSION_RESUMED = "mission-resumed"
    MISSION_ABORTED = "mission-aborted"
    MISSION_FAILED = "mission-failed"
    MISSION_COMPLETED = "mission-completed"


@dataclass(frozen=True)
class NavSnapshot:
    """What the executor needs to know about the vehicle at one instant.

    stamp_s: time of the estimate (s, monotonic); T_ned_body: body pose in NED (4x4);
    ok: the pose is fresh and trustworthy; armed, landed: from the autopilot;
    home_T_ned_body: the home pose (4x4) if the daemon knows it, else the executor takes the
    first ok pose it sees after start() as home.
    along_pipe_known: the position along the rack's pipes (rack y) has been observed; False holds
    `servo`, `gotoxy` and `takeoff`'s climb before their goal is resolved (see the module docstring).
    """

    stamp_s: float
    T_ned_body: FloatArray
    ok: bool = True
    armed: bool = False
    landed: bool = True
    home_T_ned_body: FloatArray | None = None
    along_pipe_known: bool = True


@dataclass(frozen=True)
class Goal:
    """A pose to servo to (NED) with the action's limits and thresholds (m, rad, m/s)."""

    T_ned_body_goal: FloatArray
    max_speed_m_s: float
    threshold_m: float
    yaw_threshold_rad: float
    action_index: int
    action_id: str


@dataclass(frozen=True)
class Request:
    """A discrete request; `id` is echoed in `MissionExecutor.notify`."""

    id: int
    kind: RequestKind
    action_index: int | None
    action_id: str | None
    height_m: float | None = None
    camera: str | None = None


@dataclass(frozen=True)
class Progress:
    """Where the mission is: action `index` (0-based) of `count`, errors to the goal, ETA (s)."""

    index: int
    count: int
    action: str
    action_id: str
    elapsed_s: float
    timeout_s: float
    distance_m: float | None
    yaw_error_rad: float | None
    eta_s: float | None

    @property
    def number(self) -> int:
        """1-based action number."""
        return self.index + 1

    def text(self) -> str:
        """One line for the console / GCS, e.g. 'action 5/11 gotoxy move-2m: 1.20 m, ETA 2.4 s'."""
        parts = [f"action {self.number}/{self.count} {self.action} {self.action_id}"]
        if self.distance_m is not None:
            parts.append(f"{self.distance_m:.2f} m")
        if self.yaw_error_rad is not None:
            parts.append(f"yaw {math.degrees(self.yaw_error_rad):+.0f} deg")
        if self.eta_s is not None:
            parts.append(f"ETA {self.eta_s:.1f} s")
        return parts[0] + (": " + ", ".join(parts[1:]) if len(parts) > 1 else "")


@dataclass(frozen=True)
class MissionEvent:
    """One mission event (time in s, severity 'info' | 'warning' | 'error')."""

    time_s: float
    kind: EventKind
    message: str
    severity: str = "info"
    action_index: int | None = None
    action_id: str | None = None


@dataclass(frozen=True)
class ActionResult:
    """Outcome of one action: result is 'succeeded', 'failed', 'timeout' or 'aborted'."""

    index: int
    action_id: str
    action: str
    result: str
    started_s: float
    ended_s: float
    message: str = ""
    T_ned_body_goal: FloatArray | None = None

    @property
    def seconds(self) -> float:
        """Duration of the action (s), paused time included."""
        return self.ended_s - self.started_s


@dataclass(frozen=True)
class ExecutorOutput:
    """What one `step` returns (see the module docstring)."""

    time_s: float
    state: State
    goal: Goal | None
    request: Request | None
    pending_request: Request | None
    hold: bool
    progress: Progress | None
    events: tuple[MissionEvent, ...]
    needs_along_pipe: bool = False


@dataclass
class _Running:
    """Mutable bookkeeping of the current action (private)."""

    index: int
    action: Action
    started_s: float  # shifted forward by paused time
    wall_started_s: float
    goal: Goal | None = None
    request: Request | None = None
    request_ok: bool | None = None
    request_message: str = ""
    phase: str = "start"
    within_since_s: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)
