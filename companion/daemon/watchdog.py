"""The safety watchdog task (10 Hz): battery, GCS, vision, autopilot link, ceiling -> hold / land / stop poses.

`SafetyManager.step` decides; this module applies its actions to the mission and the vehicle."""

from __future__ import annotations

import contextlib
import logging
from typing import Any

import numpy as np

from companion.daemon.state import DaemonState
from companion.errors import CompanionError, MissionError

__all__ = ["SafetyWatchdog"]


class SafetyWatchdog(DaemonState):
    """The watchdog loop, its inputs and its actions."""

    def _ceiling_clearance(self) -> float | None:
        """Upward rangefinder distance (m) from the link's state; None when unknown or older than 1 s."""
        state = self.link.state if self.link is not None else None
        if state is None or state.rangefinder_up_m is None or state.rangefinder_up_stamp_s is None:
            return None
        if self.clock.now() - float(state.rangefinder_up_stamp_s) > 1.0:
            return None
        return float(state.rangefinder_up_m)

    def _safety_inputs(self) -> Any:
        from companion.safety import SafetyInputs

        state = self.link.state if self.link is not None else None
        nav = self.last_nav
        pos: tuple[float, float, float] | None = None
        altitude = None
        if nav is not None and bool(nav.ok):
            p = np.asarray(nav.position_ned_m, dtype=np.float64)
            pos = (float(p[0]), float(p[1]), float(p[2]))
        elif state is not None and state.position_ned_m is not None:
            p = np.asarray(state.position_ned_m, dtype=np.float64)
            pos = (float(p[0]), float(p[1]), float(p[2]))
        if pos is not None:
            home_z = 0.0 if self._home_T_ned_body is None else float(self._home_T_ned_body[2, 3])
            altitude = home_z - pos[2]
        return SafetyInputs(
            battery_v=None if state is None else state.battery_voltage_v,
            battery_pct=None if state is None else state.battery_remaining_pct,
            altitude_m=altitude,
            ceiling_clearance_m=self._ceiling_clearance(),
            last_gcs_heartbeat_s=None if state is None else state.last_gcs_heartbeat_s,
            last_pose_s=self.last_fresh_pose_s,
            last_autopilot_heartbeat_s=None if state is None else state.last_autopilot_heartbeat_s,
            position_ned_m=pos,
            armed=bool(state.armed) if state is not None else False,
            landed=self._landed(),
        )

    async def _watchdog_loop(self) -> None:
        from companion.safety import SafetyAction

        period = self.options.watchdog_period_s
        while True:
            await self.clock.sleep(period)
            self.counters.watchdog_steps += 1
            if self.safety is None:
                continue
            now = self.clock.now()
            out = self.safety.step(self._safety_inputs(), now)
            self.safety_output = out
            for ev in out.events:
                record = {"time_s": ev.time_s, "kind": ev.kind, "action": str(ev.action), "message": ev.message,
                          "severity": ev.severity}
                self._safety_view.events.append(record)
                self._event("safety", level=logging.WARNING, **record)
                if self.link is not None:
                    sev = ev.severity if ev.severity in ("info", "warning", "error", "critical") else "warning"
                    with contextlib.suppress(Exception):
                        self.link.statustext(f"SAFETY {ev.message}"[:200], sev)
            self._safety_view.send_poses = bool(out.send_poses)
            self._safety_view.allow_mission = bool(out.allow_commands)
            changed = out.action != self._safety_view.last_action
            if self._safety_view.last_action == "retry" and now < self._safety_retry_s:
                continue
            self._safety_view.last_action = str(out.action)
            if changed and out.action is not SafetyAction.NONE:
                await self._apply_safety_action(out.action)
            elif changed and self._safety_paused:
                self._resume_after_safety()

    def _resume_after_safety(self) -> None:
        """The fault that paused the mission has cleared: resume it (the guided mode is claimed again)."""
        from companion.mission import State

        self._safety_paused = False
        ex = self.executor
        if ex is None or ex.state is not State.PAUSED:
            return
        with contextlib.suppress(MissionError):
            ex.resume(self.clock.now())
            self.mode_owner.claim()
            self._event("mission-resumed", reason="safety hold cleared")
            self._gcs_text("safety hold cleared: mission resumed", "info")

    async def _apply_safety_action(self, action: Any) -> None:
        from companion.safety import SafetyAction

        link = self.link
        if link is None:
            return
        if self._mission_active():
            from companion.mission import State

            assert self.executor is not None
            # a hold (vision, GCS or autopilot link briefly lost) pauses the mission so that it can resume
            # when the fault clears; a landing ends it
            pause = action in (SafetyAction.HOVER, SafetyAction.STOP_COMMANDS) and \
                (self.executor.state is State.RUNNING or self._safety_paused)
            with contextlib.suppress(CompanionError):
                if pause:
                    if self.executor.state is State.RUNNING:
                        self.executor.pause(self.clock.now())
                    self._safety_paused = True
                else:
                    self.executor.abort(self.clock.now(), f"safety: {action}")
                    self._safety_paused = False
            if self._request_task is not None and not self._request_task.done():
                self._request_task.cancel()
        link.set_velocity_command(None)
        self._last_command = None
        self._event("safety-action", level=logging.WARNING, action=str(action))
        if action is SafetyAction.STOP_COMMANDS or not link.state.armed:
            return
        try:
            if action is SafetyAction.HOVER:
                await self._hold()
            elif action in (SafetyAction.LAND, SafetyAction.LAND_NOW):
                await link.land()
        except CompanionError as exc:
            self._event("safety-action-failed", level=logging.ERROR, action=str(action), error=str(exc))
            self._safety_view.last_action = "retry"  # try again in a second
            self._safety_retry_s = self.clock.now() + 1.0
