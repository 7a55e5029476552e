"""Pure mission executor: a state machine turning actions into goals and discrete requests.

Time and navigation come in as arguments; nothing here does I/O or reads a clock. The daemon
calls `step(now_s, nav)` at its control rate (10-50 Hz) and acts on the output:

- `output.goal` (a `Goal`): servo toward `goal.T_ned_body_goal` (ServoLaw + SafetyManager.filter);
- `output.request` (a new `Request`, issued once): ARM, TAKEOFF(height_m), LAND, PHOTO(camera) --
  do it, then call `notify(request.id, ok)`; HOLD -- switch the autopilot to its hold/loiter
  mode (no notify needed);
- `output.hold`: no goal is active and the vehicle should hold where it is (paused, aborted,
  failed, or completed in the air);
- `output.events`: mission events for the console, STATUSTEXT and the control API;
- `output.needs_along_pipe`: the current action is about to place a goal with the horizontal
  position (`servo`, `gotoxy`, and `takeoff`'s climb to its height once the autopilot's take-off is
  done) while `nav.along_pipe_known` is false (the position along the pipes is still a prior's, e.g.
  the configured start's after an acquisition on the deck): it waits without a goal, its timers
  frozen, until the daemon has found that position (or holds the vehicle and pauses the mission).

States: IDLE -> RUNNING <-> PAUSED -> COMPLETED | FAILED (an action failed or timed out:
abort and hover) | ABORTED (operator or safety abort: hover). Action timers exclude paused time.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from companion.checks import FloatArray, check_transform
from companion.errors import MissionError
from companion.geometry.frames import default_T_ned_rack
from companion.mission.executor_actions import _ActionSteps
from companion.mission.executor_types import (
    _ALONG_PIPE_WAIT,
    TERMINAL_STATES,
    ActionResult,
    EventKind,
    ExecutorOutput,
    Goal,
    MissionEvent,
    NavSnapshot,
    Progress,
    Request,
    RequestKind,
    State,
    _Running,
)
from companion.mission.model import Hover, Mission, RackLayout, Servo

__all__ = [
    "ActionResult",
    "EventKind",
    "ExecutorOutput",
    "Goal",
    "MissionEvent",
    "MissionExecutor",
    "NavSnapshot",
    "Progress",
    "Request",
    "RequestKind",
    "State",
]


class MissionExecutor(_ActionSteps):
    """Runs a `Mission` step by step (pure; time injected).

    T_ned_rack: rack-to-NED transform (4x4) or a callable returning it (read whenever a goal in
        the rack frame is resolved); None = `frames.default_T_ned_rack()`.
    rack: pipe layout for `servo` actions; None = the mission's `<rack>` declaration.
    reference_yaw_rate_rad_s: yaw rate used only for the ETA estimate (rad/s).
    """

    def __init__(
        self,
        mission: Mission,
        T_ned_rack: Any | Callable[[], Any] | None = None,
        rack: RackLayout | None = None,
        reference_yaw_rate_rad_s: float = 0.2,
    ) -> None:
        self.mission = mission
        self._T_ned_rack_source: Any | Callable[[], Any] = (
            T_ned_rack if T_ned_rack is not None else default_T_ned_rack()
        )
        if not callable(self._T_ned_rack_source):
            self._T_ned_rack_source = check_transform(self._T_ned_rack_source, "T_ned_rack")
        self.rack = rack if rack is not None else mission.rack
        for action in mission.actions:
            if isinstance(action, Servo):
                where = f"{mission.source_name}:{action.line}: servo.pipe"
                if self.rack is None:
                    raise MissionError(
                        f"{where}: servo actions need a rack layout: declare <rack> in the mission or pass rack="
                    )
                if not 1 <= action.pipe <= self.rack.count:
                    raise MissionError(f"{where}: pipe {action.pipe} does not exist (the rack has {self.rack.count})")
                # A rack passed here was not seen by the parser: check the goal height before flight too.
                top_m = self.rack.pipe_top_z_m(action.pipe)
                if top_m + action.height_m > mission.limits.ceiling_m:
                    raise MissionError(
                        f"{mission.source_name}:{action.line}: servo.height: goal height {top_m + action.height_m:g} m "
                        f"(pipe top {top_m:g} m + {action.height_m:g} m) is above the ceiling "
                        f"{mission.limits.ceiling_m:g} m"
                    )
                if not 0.0 <= action.y_m <= self.rack.length_m:
                    raise MissionError(
                        f"{mission.source_name}:{action.line}: servo.y: {action.y_m:g} m is off the pipes "
                        f"(0..{self.rack.length_m:g} m)"
                    )
        self._reference_yaw_rate = float(reference_yaw_rate_rad_s)
        self._state = State.IDLE
        self._current: _Running | None = None
        self._next_index = 0
        self._home: FloatArray | None = None
        self._paused_at: float | None = None
        self._events: list[MissionEvent] = []
        self._new_request: Request | None = None
        self._request_counter = 0
        self._results: list[ActionResult] = []
        self._last_time_s: float | None = None
        self._last_nav: NavSnapshot | None = None

    # ------------------------------------------------------------------ public state
    @property
    def state(self) -> State:
        """Current state."""
        return self._state

    @property
    def results(self) -> tuple[ActionResult, ...]:
        """Outcomes of the actions finished so far, in order."""
        return tuple(self._results)

    @property
    def pending_request(self) -> Request | None:
        """The discrete request the current action waits for, if any."""
        cur = self._current
        if cur is None or cur.request is None or cur.request_ok is not None:
            return None
        return cur.request

    @property
    def home_T_ned_body(self) -> FloatArray | None:
        """The home pose (4x4 NED) once known."""
        return None if self._home is None else self._home.copy()

    def set_T_ned_rack(self, T_ned_rack: Any) -> None:
        """Replace the rack-to-NED transform used for goals resolved from now on."""
        self._T_ned_rack_source = check_transform(T_ned_rack, "T_ned_rack")

    # ------------------------------------------------------------------ commands
    def start(self, now_s: float) -> None:
        """IDLE -> RUNNING; the first action starts at the next step."""
        if self._state is not State.IDLE:
            raise MissionError(f"cannot start: mission is {self._state.value}")
        self._state = State.RUNNING
        self._emit(now_s, EventKind.MISSION_STARTED, f"mission '{self.mission.name}' started "
                   f"({len(self.mission.actions)} actions)")

    def pause(self, now_s: float) -> None:
        """RUNNING -> PAUSED: hold; the current action's timers stop."""
        if self._state is not State.RUNNING:
            raise MissionError(f"cannot pause: mission is {self._state.value}")
        self._state = State.PAUSED
        self._paused_at = float(now_s)
        if self._current is not None:
            self._current.within_since_s = None
        self._issue(RequestKind.HOLD, None)
        self._emit(now_s, EventKind.MISSION_PAUSED, "mission paused: holding", "warning")

    def resume(self, now_s: float) -> None:
        """PAUSED -> RUNNING: the current action continues with its remaining time."""
        if self._state is not State.PAUSED:
            raise MissionError(f"cannot resume: mission is {self._state.value}")
        paused_s = max(0.0, float(now_s) - (self._paused_at if self._paused_at is not None else float(now_s)))
        cur = self._current
        if cur is not None:
            cur.started_s += paused_s
            for key in ("hover_start_s", _ALONG_PIPE_WAIT):
                if key in cur.extra:
                    cur.extra[key] += paused_s
            if cur.request is not None and cur.request_ok is None:
                # The pause's hold superseded the request this action waited for (the daemon runs one request
                # at a time): a take-off cut short by a vision-loss brake would wait for its climb forever.
                # The action starts its discrete part again from what the vehicle does now (airborne: the
                # servo climbs; on the ground: take off again; disarmed: arm again).
                cur.phase, cur.request = "start", None
        self._paused_at = None
        self._state = State.RUNNING
        if self._new_request is not None and self._new_request.kind is RequestKind.HOLD:
            self._new_request = None  # the pause's hold was never delivered: drop it
        self._emit(now_s, EventKind.MISSION_RESUMED, f"mission resumed after {paused_s:.1f} s")

    def abort(self, now_s: float, reason: str = "operator abort") -> None:
        """Any non-terminal state -> ABORTED: the vehicle holds where it is."""
        if self._state in TERMINAL_STATES or self._state is State.IDLE:
            raise MissionError(f"cannot abort: mission is {self._state.value}")
        if self._current is not None:
            self._finish(now_s, "aborted", reason)
        self._state = State.ABORTED
        self._issue(RequestKind.HOLD, None)
        self._emit(now_s, EventKind.MISSION_ABORTED, f"mission aborted: {reason}; holding", "error")

    def notify(self, request_id: int, ok: bool, now_s: float | None = None, message: str = "") -> bool:
        """Report the completion of a discrete request; False if it is not the pending one."""
        pending = self.pending_request
        if pending is None or pending.id != request_id:
            return False
        assert self._current is not None
        self._current.request_ok = bool(ok)
        self._current.request_message = message
        t = now_s if now_s is not None else (self._last_time_s if self._last_time_s is not None else 0.0)
        self._emit(
            t, EventKind.REQUEST_DONE, f"{pending.kind.value} {'done' if ok else 'failed'}"
            + (f": {message}" if message else ""), "info" if ok else "error",
        )
        return True

    # ------------------------------------------------------------------ the step
    def step(self, now_s: float, nav: NavSnapshot) -> ExecutorOutput:
        """Advance the state machine to now_s (s) with the latest navigation snapshot."""
        now_s = float(now_s)
        self._last_time_s = now_s
        self._last_nav = nav
        if self._home is None and self._state is not State.IDLE:
            if nav.home_T_ned_body is not None:
                self._home = check_transform(nav.home_T_ned_body, "nav.home_T_ned_body").copy()
            elif nav.ok:
                self._home = check_transform(nav.T_ned_body, "nav.T_ned_body").copy()
        if self._state is State.RUNNING:
            self._run(now_s, nav)
        return self._output(now_s, nav)

    def _run(self, now_s: float, nav: NavSnapshot) -> None:
        if self._current is None:
            self._start_next(now_s, nav)
            if self._current is None:
                return
        cur = self._current
        self._advance(cur, now_s, nav)
        if self._current is not cur or self._state is not State.RUNNING:
            return
        outcome = self._evaluate(cur, now_s, nav)
        if outcome is None:
            if _ALONG_PIPE_WAIT in cur.extra:
                return  # the wait is not the action's time: the daemon bounds it (search leg, then a hold)
            if now_s - cur.started_s > cur.action.timeout_s:
                self._fail(now_s, "timeout", f"timed out after {cur.action.timeout_s:g} s")
            return
        ok, message = outcome
        if not ok:
            self._fail(now_s, "failed", message)
            return
        self._finish(now_s, "succeeded", message)
        if self._next_index >= len(self.mission.actions):
            self._state = State.COMPLETED
            if not nav.landed:
                self._issue(RequestKind.HOLD, None)
            self._emit(now_s, EventKind.MISSION_COMPLETED, f"mission '{self.mission.name}' completed")
        else:
            self._start_next(now_s, nav)

    def _start_next(self, now_s: float, nav: NavSnapshot) -> None:
        index = self._next_index
        action = self.mission.actions[index]
        self._next_index += 1
        self._current = _Running(index=index, action=action, started_s=now_s, wall_started_s=now_s)
        self._emit(now_s, EventKind.ACTION_STARTED, f"action {index + 1}/{len(self.mission.actions)} "
                   f"{action.tag} '{action.id}' started")
        self._advance(self._current, now_s, nav)

    # ------------------------------------------------------------------ outcomes and output
    def _finish(self, now_s: float, result: str, message: str) -> None:
        cur = self._current
        assert cur is not None
        self._results.append(ActionResult(
            index=cur.index, action_id=cur.action.id, action=cur.action.tag, result=result,
            started_s=cur.wall_started_s, ended_s=float(now_s), message=message,
            T_ned_body_goal=None if cur.goal is None else cur.goal.T_ned_body_goal,
        ))
        if result == "succeeded":
            self._emit(now_s, EventKind.ACTION_SUCCEEDED, f"action {cur.index + 1} {cur.action.tag} "
                       f"'{cur.action.id}' succeeded: {message}", action=cur)
        else:
            self._emit(now_s, EventKind.ACTION_FAILED, f"action {cur.index + 1} {cur.action.tag} "
                       f"'{cur.action.id}' {result}: {message}", "error", action=cur)
        self._current = None

    def _fail(self, now_s: float, result: str, message: str) -> None:
        cur = self._current
        assert cur is not None
        label = f"action {cur.index + 1} {cur.action.tag} '{cur.action.id}' {result}"
        self._finish(now_s, result, message)
        self._state = State.FAILED
        self._issue(RequestKind.HOLD, None)
        self._emit(now_s, EventKind.MISSION_FAILED, f"mission aborted ({label}): holding", "error")

    def _progress(self, now_s: float, nav: NavSnapshot) -> Progress | None:
        cur = self._current
        if cur is None:
            return None
        a = cur.action
        end_s = self._paused_at if self._state is State.PAUSED and self._paused_at is not None else now_s
        if _ALONG_PIPE_WAIT in cur.extra:  # the wait is not the action's time (as a pause is not)
            end_s = min(end_s, float(cur.extra[_ALONG_PIPE_WAIT]))
        elapsed = end_s - cur.started_s
        dist: float | None = None
        yaw_err: float | None = None
        eta: float | None = None
        if cur.goal is not None and nav.ok:
            dist, yaw_err = self._errors(cur.goal, nav)
            eta = max(dist / cur.goal.max_speed_m_s, abs(yaw_err) / self._reference_yaw_rate)
        if isinstance(a, Hover):
            start = cur.extra.get("hover_start_s")
            eta = a.duration_s - (end_s - float(start)) if start is not None else a.duration_s
            eta = max(0.0, eta)
        return Progress(index=cur.index, count=len(self.mission.actions), action=a.tag, action_id=a.id,
                        elapsed_s=elapsed, timeout_s=a.timeout_s, distance_m=dist, yaw_error_rad=yaw_err,
                        eta_s=eta)

    def _output(self, now_s: float, nav: NavSnapshot) -> ExecutorOutput:
        goal = None
        if self._state is State.RUNNING and self._current is not None:
            goal = self._current.goal
        hold = self._state in (State.PAUSED, State.FAILED, State.ABORTED) or (
            self._state is State.COMPLETED and not nav.landed
        )
        request, self._new_request = self._new_request, None
        if request is not None:
            self._events.append(MissionEvent(
                time_s=now_s, kind=EventKind.REQUEST,
                message=f"request {request.kind.value}"
                + (f" {request.height_m:g} m" if request.height_m is not None else "")
                + (f" camera {request.camera}" if request.camera is not None else ""),
                action_index=request.action_index, action_id=request.action_id,
            ))
        events, self._events = tuple(self._events), []
        waiting = self._state is State.RUNNING and self._current is not None and \
            _ALONG_PIPE_WAIT in self._current.extra
        return ExecutorOutput(time_s=now_s, state=self._state, goal=goal, request=request,
                              pending_request=self.pending_request, hold=hold,
                              progress=self._progress(now_s, nav), events=events, needs_along_pipe=waiting)
