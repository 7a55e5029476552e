"""The control task (20 Hz): mission executor -> servo law -> `SafetyManager.filter` -> link setpoint.

Also the mode-ownership glue (`companion.daemon.arming.ModeOwner`) and the turn-first rule. While the
executor waits for the along-pipe position, the goal is the rack-end search leg's
(`companion.daemon.along_pipe_task`)."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.daemon.arming import ModeDecision, enter_guided
from companion.daemon.state import DaemonState
from companion.errors import MissionError
from companion.geometry import frames

__all__ = ["ControlTask"]


class ControlTask(DaemonState):
    """The control loop, mode ownership and turn-first."""

    def _nav_snapshot(self) -> Any:
        from companion.mission import NavSnapshot

        nav = self.last_nav
        state = self.link.state if self.link is not None else None
        armed = bool(state.armed) if state is not None else False
        landed = self._landed()
        now = self.clock.now()
        fresh = nav is not None and bool(nav.ok) and self.last_pose_sent_s is not None and \
            now - self.last_pose_sent_s <= 0.5
        T = np.asarray(nav.T_ned_body) if nav is not None else np.eye(4)
        return NavSnapshot(stamp_s=now, T_ned_body=T, ok=bool(fresh), armed=armed, landed=landed,
                           home_T_ned_body=self._home_T_ned_body, along_pipe_known=self._along_pipe_known())

    async def _control_loop(self) -> None:
        from companion.control.types import VelocityCommand

        period = self.options.control_period_s
        while True:
            await self.clock.sleep(period)
            self.counters.control_steps += 1
            if self.link is None:
                continue
            ex = self.executor
            if ex is None:
                continue
            now = self.clock.now()
            snap = self._nav_snapshot()
            if self._home_T_ned_body is None and snap.ok:
                self._home_T_ned_body = np.asarray(snap.T_ned_body).copy()
                snap = dataclasses.replace(snap, home_T_ned_body=self._home_T_ned_body)
            out = ex.step(now, snap)
            for ev in out.events:
                self._mission_event(ev)
            if out.request is not None:
                self._start_request(out.request)
            goal = out.goal
            if out.needs_along_pipe or self._along_pipe_search is not None:
                # stepped while a leg is under way even when the executor is paused (its clock stops then)
                search_goal = self._along_pipe_goal(ex, out, snap, now)
                goal = search_goal if out.needs_along_pipe else goal
            if not self._mission_active():
                if self._last_command is not None:
                    self.link.set_velocity_command(None)
                    self._last_command = None
                continue
            cmd: Any = None
            if goal is not None and snap.ok and self._safety_view.allow_mission:
                assert self._servo is not None
                speed = min(goal.max_speed_m_s, self.config.safety.max_speed_m_s)
                goal_T = self._turn_first(goal, np.asarray(snap.T_ned_body))
                cmd = self._servo.update(snap.T_ned_body, goal_T, now, max_speed_m_s=speed)
            elif (goal is not None or out.needs_along_pipe) and self._safety_view.allow_mission and \
                    out.pending_request is None:
                cmd = VelocityCommand.zero()  # no fresh pose, or waiting for the along-pipe position: hover
            if cmd is not None and self.safety is not None:
                cmd = self.safety.filter(cmd, self._safety_inputs(), now)
            self._own_mode(ex, now, moving=goal is not None and self._safety_view.allow_mission,
                           request_pending=out.pending_request is not None)
            if cmd is not None and out.pending_request is None:
                self.link.set_velocity_command(cmd)
                self._last_command = cmd
            elif self._last_command is not None and out.pending_request is None:
                self.link.set_velocity_command(None)
                self._last_command = None
            if self._servo is not None:
                # rate limiting continues from what the autopilot was actually given (post-filter), so a
                # clamp that releases does not make the next command jump; nothing sent = at rest
                sent = cmd if cmd is not None and out.pending_request is None else None
                self._servo.record_sent(sent, now)

    def _own_mode(self, ex: Any, now: float, *, moving: bool, request_pending: bool) -> None:
        """Apply the mode-ownership rule (`companion.daemon.arming.ModeOwner`) for this control step."""
        from companion.mission import State

        link = self.link
        profile = None if link is None else link.profile
        if link is None or profile is None or ex.state is not State.RUNNING:
            return
        busy = request_pending or (self._request_task is not None and not self._request_task.done())
        decision = self.mode_owner.decide(moving=moving, armed=bool(link.state.armed), airborne=not self._landed(),
                                          mode=link.state.mode, guided_mode=profile.guided_mode,
                                          request_pending=busy,
                                          mode_stamp_s=link.state.last_autopilot_heartbeat_s)
        if decision is ModeDecision.ENTER_GUIDED:
            self._mode_task = asyncio.create_task(self._claim_guided(profile.guided_mode), name="enter-guided")
        elif decision is ModeDecision.PAUSE:
            reason = f"mode changed to {link.state.mode} outside the companion: mission paused (resume to continue)"
            with contextlib.suppress(MissionError):
                ex.pause(now)
            self._event("mission-paused", level=logging.WARNING, reason=reason)
            self._gcs_text(reason, "warning")

    async def _claim_guided(self, guided_mode: str) -> None:
        failure = await enter_guided(self.mode_owner, self._enter_guided, self.clock.now)
        if failure is None:
            self._event("mode", mode=guided_mode, reason="motion starts or resumes")
            return
        from companion.mission import State

        reason = f"cannot switch the autopilot to {guided_mode}: {failure}; mission paused"
        self._event("mission-paused", level=logging.WARNING, reason=reason)
        self._gcs_text(reason, "warning")
        ex = self.executor
        if ex is not None and ex.state is State.RUNNING:
            with contextlib.suppress(MissionError):
                ex.pause(self.clock.now())

    def _turn_first(self, goal: Any, T_ned_body: FloatArray) -> FloatArray:
        """The pose to servo to now: for a large heading change, first turn in place, then go.

        The SE(3)-log law couples rotation and translation: a 180 deg turn combined with a move
        follows a screw arc that can swing the vehicle a metre off the straight line (off the rack,
        where the tracker loses it). Above `turn_first_rad` of heading error the goal becomes the
        goal's heading at the position where the turn started; below it, the goal itself.
        """
        T_goal = np.asarray(goal.T_ned_body_goal, dtype=np.float64)
        yaw_err = float(frames.wrap_angle(frames.yaw_from_rotation(T_goal[:3, :3])
                                          - frames.yaw_from_rotation(T_ned_body[:3, :3])))
        key = (goal.action_index, goal.action_id)
        threshold = self.turn_first_rad
        if threshold <= 0.0:
            return T_goal
        if self._turn_key != key:
            self._turn_key = key
            self._turn_pivot = T_ned_body[:3, 3].copy() if abs(yaw_err) > threshold else None
        if self._turn_pivot is not None:
            if abs(yaw_err) > 0.5 * threshold:
                T = T_goal.copy()
                T[:3, 3] = self._turn_pivot
                return T
            self._turn_pivot = None
        return T_goal
