"""The per-action half of `MissionExecutor`: resolving each action's goal, issuing its requests and
judging its outcome, with the pose helpers they share (`companion.mission.executor` holds the state
machine; its `MissionExecutor` inherits these methods from `_ActionSteps`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.checks import FloatArray, check_transform
from companion.geometry import se3
from companion.geometry.frames import wrap_angle, yaw_from_rotation
from companion.mission.executor_types import (
    _ALONG_PIPE_WAIT,
    _TIME_EPS_S,
    EventKind,
    Goal,
    MissionEvent,
    NavSnapshot,
    Request,
    RequestKind,
    _Running,
)
from companion.mission.model import (
    Frame,
    GotoXY,
    GotoZ,
    Home,
    Hover,
    Land,
    Mission,
    RackLayout,
    Servo,
    Takeoff,
    TakePhoto,
)


def _heading_rotation(yaw_rad: float) -> FloatArray:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _ActionSteps:
    """Per-action steps of `MissionExecutor` (its base class; the attributes are set by its `__init__`)."""

    mission: Mission
    rack: RackLayout | None
    _T_ned_rack_source: Any | Callable[[], Any]
    _home: FloatArray | None
    _new_request: Request | None
    _request_counter: int
    _events: list[MissionEvent]

    # ------------------------------------------------------------------ per action
    def _advance(self, cur: _Running, now_s: float, nav: NavSnapshot) -> None:
        """Resolve goals and issue requests for the current action (idempotent)."""
        a = cur.action
        if isinstance(a, Takeoff):
            if cur.phase == "start":
                if nav.armed and not nav.landed:
                    cur.phase = "climb"  # already flying: climb/descend to the height with the servo
                elif nav.armed:
                    cur.phase = "takeoff"
                else:
                    cur.phase = "arm"
                    cur.request = self._issue(RequestKind.ARM, cur)
            if cur.phase == "arm" and cur.request_ok:
                cur.phase = "takeoff"
            if cur.phase == "takeoff" and (cur.request is None or cur.request.kind is RequestKind.ARM):
                cur.request = self._issue(RequestKind.TAKEOFF, cur, height_m=a.height_m)
                cur.request_ok = None
            if cur.phase == "takeoff" and cur.request_ok:
                cur.phase = "climb"
            # the climb's goal is "here": placed with an unobserved along-pipe position it (and the action's
            # recorded waypoint) would be off by that position's error, so it waits like servo / gotoxy
            if cur.phase == "climb" and cur.goal is None and nav.ok and self._home is not None \
                    and self._along_pipe_ready(cur, now_s, nav):
                T = self._T(nav)
                p = T[:3, 3].copy()
                p[2] = self._home[2, 3] - a.height_m
                cur.goal = self._goal(cur, self._flat(T, p), self.mission.speed_m_s, a.threshold_m,
                                      self.mission.yaw_threshold_rad)
        elif isinstance(a, Land):
            if cur.phase == "start":
                cur.phase = "landing"
                if not (nav.landed and not nav.armed):
                    cur.request = self._issue(RequestKind.LAND, cur)
        elif isinstance(a, TakePhoto):
            if cur.phase == "start":
                cur.phase = "photo"
                cur.request = self._issue(RequestKind.PHOTO, cur, camera=a.camera)
            if cur.goal is None and nav.ok:
                T = self._T(nav)
                cur.goal = self._goal(cur, self._flat(T, T[:3, 3]), self.mission.speed_m_s,
                                      self.mission.threshold_m, self.mission.yaw_threshold_rad)
        elif cur.goal is None and isinstance(a, Servo | GotoXY) and not self._along_pipe_ready(cur, now_s, nav):
            return
        elif cur.goal is None and nav.ok:
            cur.goal = self._resolve_motion_goal(cur, nav)
            if isinstance(a, Hover) and cur.goal is not None:
                cur.extra["hover_start_s"] = now_s

    def _along_pipe_ready(self, cur: _Running, now_s: float, nav: NavSnapshot) -> bool:
        """Whether a horizontal goal may be resolved now; starts / ends the action's wait otherwise.

        A goal placed with an along-pipe position the daemon has not observed would be off by that
        position's error (up to the start error): the action waits instead, and its timers resume
        with the time it waited added back.
        """
        waiting_since = cur.extra.get(_ALONG_PIPE_WAIT)
        if not nav.along_pipe_known:
            if waiting_since is None:
                cur.extra[_ALONG_PIPE_WAIT] = now_s
                self._emit(now_s, EventKind.ACTION_WAITING, f"action {cur.index + 1} {cur.action.tag} "
                           f"'{cur.action.id}' waits for the along-pipe position", "warning", action=cur)
            return False
        if waiting_since is not None:
            del cur.extra[_ALONG_PIPE_WAIT]
            cur.started_s += max(0.0, now_s - float(waiting_since))
            self._emit(now_s, EventKind.ACTION_CONTINUED, f"action {cur.index + 1} {cur.action.tag} "
                       f"'{cur.action.id}' goes on: along-pipe position known after "
                       f"{now_s - float(waiting_since):.1f} s", action=cur)
        return True

    def _resolve_motion_goal(self, cur: _Running, nav: NavSnapshot) -> Goal | None:
        a = cur.action
        m = self.mission
        T = self._T(nav)
        p_ned = T[:3, 3].copy()
        yaw_now = float(yaw_from_rotation(T[:3, :3]))
        if isinstance(a, Hover):
            return self._goal(cur, self._flat(T, p_ned), m.speed_m_s, m.threshold_m, m.yaw_threshold_rad)
        if isinstance(a, Home):
            if self._home is None:
                return None
            p = np.array([self._home[0, 3], self._home[1, 3], p_ned[2]])
            return self._goal(cur, self._flat(T, p), a.speed_m_s, a.threshold_m, m.yaw_threshold_rad)
        if isinstance(a, GotoXY):
            if m.frame is Frame.NED:
                p = np.array([a.x_m, a.y_m, p_ned[2]])
                yaw = yaw_now if a.yaw_rad is None else a.yaw_rad
            else:
                T_ned_rack = self._T_ned_rack()
                p_rack = se3.act(se3.inverse(T_ned_rack), p_ned)
                p = se3.act(T_ned_rack, np.array([a.x_m, a.y_m, p_rack[2]]))
                yaw = yaw_now if a.yaw_rad is None else self._ned_yaw_from_rack_yaw(a.yaw_rad, T_ned_rack)
            return self._goal(cur, se3.make(_heading_rotation(yaw), p), a.speed_m_s, a.threshold_m,
                              a.yaw_threshold_rad)
        if isinstance(a, GotoZ):
            if a.height_m is not None:
                if self._home is None:
                    return None
                p = np.array([p_ned[0], p_ned[1], self._home[2, 3] - a.height_m])
            elif m.frame is Frame.NED:
                p = np.array([p_ned[0], p_ned[1], float(a.z_m if a.z_m is not None else p_ned[2])])
            else:
                T_ned_rack = self._T_ned_rack()
                p_rack = se3.act(se3.inverse(T_ned_rack), p_ned)
                p_rack[2] = float(a.z_m if a.z_m is not None else p_rack[2])
                p = se3.act(T_ned_rack, p_rack)
            return self._goal(cur, self._flat(T, p), a.speed_m_s, a.threshold_m, m.yaw_threshold_rad)
        if isinstance(a, Servo):
            assert self.rack is not None
            T_ned_rack = self._T_ned_rack()
            p_rack = np.array(
                [self.rack.pipe_axis_x_m(a.pipe), a.y_m, self.rack.pipe_top_z_m(a.pipe) + a.height_m]
            )
            yaw = self._ned_yaw_from_rack_yaw(a.yaw_rad, T_ned_rack)
            return self._goal(cur, se3.make(_heading_rotation(yaw), se3.act(T_ned_rack, p_rack)),
                              a.speed_m_s, a.threshold_m, a.yaw_threshold_rad)
        return None

    def _evaluate(self, cur: _Running, now_s: float, nav: NavSnapshot) -> tuple[bool, str] | None:
        """None while running, (True, msg) on success, (False, msg) on failure."""
        a = cur.action
        if cur.request is not None and cur.request_ok is False:
            detail = f": {cur.request_message}" if cur.request_message else ""
            return False, f"{cur.request.kind.value} failed{detail}"
        if isinstance(a, Land):
            if nav.landed and (cur.request is None or cur.request_ok):
                return True, "landed"
            return None
        if isinstance(a, TakePhoto):
            return (True, "photo taken") if cur.request_ok else None
        if isinstance(a, Hover):
            start = cur.extra.get("hover_start_s")
            if start is not None and now_s - float(start) >= a.duration_s - _TIME_EPS_S:
                return True, f"hovered {a.duration_s:g} s"
            return None
        if isinstance(a, Takeoff) and cur.phase != "climb":
            return None
        if cur.goal is None or not nav.ok:
            cur.within_since_s = None
            return None
        dist, yaw_err = self._errors(cur.goal, nav)
        if dist <= cur.goal.threshold_m and abs(yaw_err) <= cur.goal.yaw_threshold_rad:
            if cur.within_since_s is None:
                cur.within_since_s = now_s
            if now_s - cur.within_since_s >= self.mission.settle_s - _TIME_EPS_S:
                return True, f"reached within {dist:.2f} m"
        else:
            cur.within_since_s = None
        return None

    # ------------------------------------------------------------------ helpers
    def _T(self, nav: NavSnapshot) -> FloatArray:
        return check_transform(nav.T_ned_body, "nav.T_ned_body")

    def _T_ned_rack(self) -> FloatArray:
        src = self._T_ned_rack_source
        return check_transform(src() if callable(src) else src, "T_ned_rack")

    @staticmethod
    def _flat(T_ned_body: FloatArray, p_ned: FloatArray) -> FloatArray:
        """Pose at p_ned with the heading of T_ned_body and no roll/pitch."""
        return se3.make(_heading_rotation(float(yaw_from_rotation(T_ned_body[:3, :3]))), p_ned)

    @staticmethod
    def _ned_yaw_from_rack_yaw(yaw_rack_rad: float, T_ned_rack: FloatArray) -> float:
        """Rack heading (from rack +y toward +x) to NED heading (from north toward east)."""
        d_rack = np.array([math.sin(yaw_rack_rad), math.cos(yaw_rack_rad), 0.0])
        d_ned = T_ned_rack[:3, :3] @ d_rack
        return math.atan2(float(d_ned[1]), float(d_ned[0]))

    def _goal(self, cur: _Running, T_goal: FloatArray, speed: float, thr: float, yaw_thr: float) -> Goal:
        return Goal(T_ned_body_goal=T_goal, max_speed_m_s=speed, threshold_m=thr, yaw_threshold_rad=yaw_thr,
                    action_index=cur.index, action_id=cur.action.id)

    @staticmethod
    def _errors(goal: Goal, nav: NavSnapshot) -> tuple[float, float]:
        T = nav.T_ned_body
        dist = float(np.linalg.norm(goal.T_ned_body_goal[:3, 3] - T[:3, 3]))
        yaw_err = float(wrap_angle(yaw_from_rotation(goal.T_ned_body_goal[:3, :3]) - yaw_from_rotation(T[:3, :3])))
        return dist, yaw_err

    def _issue(self, kind: RequestKind, cur: _Running | None, height_m: float | None = None,
               camera: str | None = None) -> Request:
        self._request_counter += 1
        req = Request(
            id=self._request_counter, kind=kind,
            action_index=None if cur is None else cur.index,
            action_id=None if cur is None else cur.action.id,
            height_m=height_m, camera=camera,
        )
        self._new_request = req  # a later request replaces an undelivered one
        return req

    def _emit(self, now_s: float, kind: EventKind, message: str, severity: str = "info",
              action: _Running | None = None) -> None:
        self._events.append(MissionEvent(
            time_s=float(now_s), kind=kind, message=message, severity=severity,
            action_index=None if action is None else action.index,
            action_id=None if action is None else action.action.id,
        ))
