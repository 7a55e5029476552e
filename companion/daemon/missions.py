"""Missions: start / pause / resume / abort, the take-off gate, and the executor's requests
(arm, take-off, land, hold, photo) carried out on the link."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import Any

import numpy as np

from companion.daemon.arming import arm_when_ready
from companion.daemon.state import DaemonState
from companion.errors import CompanionError, LinkError, MissionError

__all__ = ["Missions"]


class Missions(DaemonState):
    """Mission commands, requests and photos."""

    async def start_mission(self, mission: Any, mission_id: str = "mission") -> None:
        """Start a parsed `Mission` (refused while another one runs or when safety forbids it)."""
        from companion.mission import MissionExecutor

        if self._mission_active():
            raise MissionError(f"mission '{self.mission_id}' is still running; abort it first")
        reason = None
        if not self._safety_view.allow_mission:
            reason = f"safety forbids starting a mission ({self._safety_view.last_action})"
        elif self.link is None or self.link.state.last_autopilot_heartbeat_s is None:
            reason = "no autopilot on the link"
        else:
            reason = self.takeoff_refusal()
        if reason is not None:
            self._refuse_mission(mission_id, reason)
            raise MissionError(f"mission '{mission_id}' refused: {reason}")
        self.mission_refused = None
        self.executor = MissionExecutor(mission, T_ned_rack=self.T_ned_rack)
        self._along_pipe_search = None  # a new mission gets a new rack-end search (along_pipe_task)
        self.mission_id = mission_id
        self._servo.reset() if self._servo is not None else None
        self.executor.start(self.clock.now())
        self.mode_owner.claim()  # motion starts (even while airborne): the guided mode is ours to set
        self._event("mission-start", mission=mission.name, id=mission_id, actions=len(mission.actions))

    def _active_executor(self, mission_id: str | None) -> Any:
        ex = self.executor
        if ex is None:
            raise MissionError("no mission")
        if mission_id is not None and mission_id != self.mission_id:
            raise MissionError(f"mission '{mission_id}' is not the active one ('{self.mission_id}')")
        return ex

    def pause_mission(self, mission_id: str | None = None) -> None:
        """Operator pause: the vehicle holds (autopilot hold mode); `resume_mission` continues."""
        self._active_executor(mission_id).pause(self.clock.now())

    def resume_mission(self, mission_id: str | None = None) -> None:
        """Operator resume. After an operator pause the mission continues and the daemon switches the
        autopilot back to its guided mode; during a safety hold it ends the hold (refused while the cause
        persists) and the watchdog resumes the mission."""
        ex = self._active_executor(mission_id)
        if self.safety is not None and self._safety_view.last_action not in ("none", ""):
            if not self.safety.operator_resume(self.clock.now()):
                raise MissionError(f"resume refused: safety hold ({self._safety_view.last_action}) still needed")
            return
        ex.resume(self.clock.now())
        self._along_pipe_resumed_by_operator()  # after a failed rack-end search: fly on without it (along_pipe_task)
        self.mode_owner.claim()  # motion resumes: the guided mode is ours to set again

    def abort_mission(self, mission_id: str | None = None) -> None:
        """Operator abort: the mission ends, the vehicle holds where it is."""
        self._active_executor(mission_id).abort(self.clock.now(), "operator abort")

    def takeoff_refusal(self) -> str | None:
        """Why arming / taking off must not happen now, or None when it may.

        The safety manager's ``allow_takeoff`` (autopilot link, battery low/critical, GCS link) from the
        watchdog's last step, and a vision pose sent to the autopilot within ``safety.vision_loss_hover_ms``.
        """
        out = self.safety_output
        if out is None:
            return "safety watchdog has not evaluated the vehicle yet"
        if not bool(out.allow_takeoff):
            reasons = sorted(str(getattr(f, "value", f)) for f in out.faults)
            state = self.link.state if self.link is not None else None
            lim = self.config.safety
            if state is not None and not any(r.startswith("battery") for r in reasons):
                v, pct = state.battery_voltage_v, state.battery_remaining_pct
                if (v is not None and v < lim.battery_low_v) or (pct is not None and pct < lim.battery_low_pct):
                    # below the threshold but not yet debounced into a fault: still no take-off
                    reasons.append(f"battery low ({'?' if v is None else f'{v:.2f}'} V, "
                                   f"{'?' if pct is None else f'{pct:.0f}'} %)")
            return f"safety forbids take-off ({', '.join(reasons) or out.message})"
        max_age_s = float(self.config.safety.vision_loss_hover_ms) / 1000.0
        sent = self.last_pose_sent_s
        if sent is None or self.clock.now() - sent > max_age_s:
            age = "never" if sent is None else f"{self.clock.now() - sent:.2f} s ago"
            return f"no fresh vision pose (last sent {age}, limit {max_age_s:g} s)"
        return None

    def _refuse_mission(self, mission_id: str | None, reason: str) -> None:
        """Record, log and tell the GCS why a mission (or its take-off) was refused."""
        self.mission_refused = {"id": mission_id, "time_s": self.clock.now(), "reason": reason}
        self._event("mission-refused", level=logging.WARNING, id=mission_id, reason=reason)
        if self.link is not None:
            with contextlib.suppress(Exception):
                self.link.statustext(f"companion: mission refused: {reason}"[:200], "warning")

    def _mission_event(self, ev: Any) -> None:
        self._event("mission", kind=str(ev.kind), message=ev.message, severity=ev.severity,
                    action=ev.action_id)
        if self.link is not None and str(ev.kind) != "request":
            with contextlib.suppress(Exception):
                self.link.statustext(ev.message[:200], ev.severity if ev.severity in ("info", "warning", "error")
                                     else "info")

    def _start_request(self, request: Any) -> None:
        if self._request_task is not None and not self._request_task.done():
            self._request_task.cancel()
        self._request_task = asyncio.create_task(self._do_request(request), name=f"request-{request.kind}")

    async def _do_request(self, request: Any) -> None:
        from companion.mission import RequestKind

        link = self.link
        ex = self.executor
        if link is None or ex is None:
            return
        ok = True
        message = ""
        try:
            if request.kind in (RequestKind.ARM, RequestKind.TAKEOFF):
                refusal = self.takeoff_refusal()
                if refusal is not None:
                    self._refuse_mission(self.mission_id, f"{request.kind}: {refusal}")
                    if request.kind is RequestKind.TAKEOFF and link.state.armed and self._landed():
                        with contextlib.suppress(CompanionError):
                            await link.disarm()
                    raise MissionError(f"{request.kind} refused: {refusal}")
            if request.kind is RequestKind.ARM:
                profile = link.profile
                if profile is None:
                    raise LinkError("autopilot type unknown: cannot arm")
                if profile.name == "ardupilot":  # arm in GUIDED and take off inside it
                    await link.set_mode(profile.guided_mode)
                waited = await arm_when_ready(link, self.clock.sleep, self.clock.now,
                                              timeout_s=float(self.config.mission.arm_ready_timeout_s),
                                              say=lambda text: self._gcs_text(text, "info"))
                self._event("armed", waited_s=round(waited, 2))
            elif request.kind is RequestKind.TAKEOFF:
                await link.takeoff(float(request.height_m))
                await self._wait_height(float(request.height_m))
                await self._enter_guided()
                self.mode_owner.accepted(self.clock.now())
            elif request.kind is RequestKind.LAND:
                await link.land()
            elif request.kind is RequestKind.HOLD:
                # the daemon only takes the vehicle out of the mode it drives (guided): a pilot's LOITER or an
                # autopilot failsafe's LAND is left alone
                ours = link.profile is not None and link.state.mode in (link.profile.guided_mode,
                                                                         link.profile.takeoff_mode)
                if link.state.armed and ours and self._safety_view.last_action in ("none", ""):
                    with contextlib.suppress(CompanionError):
                        await self._hold()
                return
            elif request.kind is RequestKind.PHOTO:
                fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
                self._pending_photo = (request.id, fut)
                await fut
                return
        except CompanionError as exc:
            ok = False
            message = str(exc)
        except asyncio.CancelledError:
            raise
        ex.notify(request.id, ok, self.clock.now(), message)

    async def _enter_guided(self) -> None:
        """Switch to the profile's velocity-setpoint mode; PX4 needs the setpoint stream before OFFBOARD."""
        from companion.control.types import VelocityCommand

        link = self.link
        assert link is not None
        profile = link.profile
        if profile is None:
            raise LinkError("autopilot type unknown")
        if link.state.mode == profile.guided_mode:
            return
        link.set_velocity_command(VelocityCommand.zero())
        await self.clock.sleep(0.5)
        await link.set_mode(profile.guided_mode)

    async def _wait_height(self, height_m: float, tolerance_m: float = 0.25, timeout_s: float = 30.0) -> None:
        """Wait until the autopilot reports a height within `tolerance_m` of `height_m` above home."""
        link = self.link
        assert link is not None
        home_z = 0.0 if self._home_T_ned_body is None else float(self._home_T_ned_body[2, 3])
        deadline = self.clock.now() + timeout_s
        while self.clock.now() < deadline:
            nav = self.last_nav
            z = None
            if nav is not None and bool(nav.ok):
                z = float(nav.position_ned_m[2])
            elif link.state.position_ned_m is not None:
                z = float(link.state.position_ned_m[2])
            if z is not None and home_z - z >= height_m - tolerance_m:
                return
            await self.clock.sleep(0.1)
        raise LinkError(f"take-off did not reach {height_m:g} m within {timeout_s:g} s")

    def _take_photo_now(self, frame: Any, nav: Any) -> None:
        assert self._pending_photo is not None
        request_id, fut = self._pending_photo
        self._pending_photo = None
        ex = self.executor
        try:
            assert self.flight is not None
            self._photo_index += 1
            sidecar = {
                "time_s": float(frame.stamp_s),
                "wall_time": time.time(),
                "seq": int(frame.seq),
                "pose": {
                    "T_ned_body": np.asarray(nav.T_ned_body),
                    "covariance_xyz_rpy": np.asarray(nav.pose_covariance),
                    "ok": bool(nav.ok),
                    "source": str(nav.source),
                },
                "mission": None if ex is None else ex.mission.name,
                "mission_id": self.mission_id,
                "action_id": None if ex is None or ex.pending_request is None else ex.pending_request.action_id,
                "camera_calibration": self.config.camera.calibration or None,
            }
            path = self.flight.save_photo(frame.image, sidecar)
            if self.link is not None:
                R_ned_cam = np.asarray(nav.T_ned_body)[:3, :3] @ self.T_body_cam[:3, :3]
                self.link.camera_image_captured(self._photo_index, file_url=path.name, R_ned_cam=R_ned_cam)
            self._event("photo", file=path.name)
            if ex is not None:
                ex.notify(request_id, True, self.clock.now(), path.name)
        except (OSError, CompanionError) as exc:
            if ex is not None:
                ex.notify(request_id, False, self.clock.now(), str(exc))
        if not fut.done():
            fut.set_result(None)
