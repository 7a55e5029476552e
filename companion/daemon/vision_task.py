"""The vision task: newest camera frame -> trackers (worker thread or inline) -> filter -> pose to the autopilot.

The camera's lost / recovered callbacks land here too; `FrameRecord`s go to the frame observers."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from typing import Any

import numpy as np

from companion.daemon.hint_task import HintCheckTask
from companion.daemon.pipeline import FrameInputs, Measurement
from companion.daemon.state import FrameRecord
from companion.errors import CameraError, CompanionError

__all__ = ["VisionTask"]


class VisionTask(HintCheckTask):
    """The vision loop and what happens to each measured frame (the start-hint lock check: `HintCheckTask`)."""

    def _on_camera_lost(self, reason: str) -> None:
        self.camera_ok = False
        self._event("camera-lost", level=logging.WARNING, reason=reason)

    def _on_camera_recovered(self) -> None:
        self.camera_ok = True
        self._event("camera-recovered")

    def _frame_inputs(self) -> FrameInputs:
        link = self.link
        state = link.state if link is not None else None
        roll = pitch = 0.0
        attitude_known = state is not None and state.attitude_rpy_rad is not None
        if state is not None and state.attitude_rpy_rad is not None:
            roll, pitch = float(state.attitude_rpy_rad[0]), float(state.attitude_rpy_rad[1])
        height = None
        z_cam_body = float(self.T_body_cam[2, 3])
        nf = self.nav_filter
        use_range = bool(getattr(nf.config, "use_range", True)) if nf is not None else True
        vg = self.visual_ground_z_ned_m
        if vg is None and use_range and state is not None and state.rangefinder_m is not None:
            height = float(state.rangefinder_m) * math.cos(roll) * math.cos(pitch) - z_cam_body
        elif nf is not None:
            est = nf.estimate_latest()
            if math.isfinite(float(est.stamp_s)):
                gz = float(getattr(nf.config, "ground_z_ned_m", 0.0)) if vg is None else float(vg)
                height = gz - float(est.position_ned_m[2]) - z_cam_body
        reset = None
        # after a gap in the frames the tracker was fine, only its motion model is stale: the re-seed keeps what
        # it learnt of the scene (one solve instead of four; the four made the next frame late on a loaded CPU)
        keep = self._rack_reset_reason.startswith("frame gap")
        if self._rack_reset_pending and self._hold_rack_reseed:
            self._rack_reset_pending = False  # the acquired pose is better than the filter's estimate
        if self._rack_reset_pending and nf is not None:
            latest = nf.estimate_latest()
            pos_std = math.sqrt(max(float(np.max(np.diag(np.asarray(latest.pose_covariance))[:3])), 0.0))
            if math.isfinite(float(latest.stamp_s)) and pos_std < 0.3:
                reset = np.asarray(latest.T_ned_body)
                self._rack_reset_pending = False
                self._event("rack-tracker-reset", level=logging.DEBUG, position_std_m=pos_std,
                            reason=self._rack_reset_reason)
        return FrameInputs(height_m=height, roll_rad=roll, pitch_rad=pitch, reset_T_ned_body=reset,
                           attitude_known=attitude_known, acquisition=self._acquisition_inputs(roll, pitch),
                           reset_keeps_appearance=keep)

    def _acquisition_inputs(self, roll: float, pitch: float) -> Any | None:
        """The vehicle's prior for a rack acquisition, when the pipeline is acquiring or a check of the start-hint
        lock is due (else None)."""
        acq = None if self.pipeline is None else self.pipeline.acquirer
        if acq is None:
            return None
        if not acq.acquiring:
            return self._hint_check_inputs(roll, pitch)
        from companion.daemon.acquisition import AcquisitionInputs

        nf = self.nav_filter
        hint = self.options.initial_T_ned_body
        T_start = np.eye(4) if hint is None else np.asarray(hint, dtype=np.float64)
        T_hint = T_start
        from_start = True
        y_std = 1.0
        state = self.link.state if self.link is not None else None
        # disarmed on the deck and never located by vision: the filter only dead-reckons from the start hint
        # (decimetres of drift in seconds); the start hint's height (the deck) and position are the prior
        resting = state is not None and not bool(state.armed)
        if nf is not None:
            est = nf.estimate_latest()
            if math.isfinite(float(est.stamp_s)) and not (resting and str(est.source) == "none"
                                                          and self.counters.poses_sent == 0):
                T_hint = np.asarray(est.T_ned_body, dtype=np.float64)
                from_start = False
                y_std = max(1.0, math.sqrt(float(np.max(np.diag(np.asarray(est.pose_covariance))[:2]))))
        # camera height above the rack's support plane: the autopilot's own height (baro / rangefinder EKF)
        # when it has one, else on the deck the start's (the vehicle rests where the configuration puts the
        # deck) and in flight the estimate's; the support plane is rack z = 0. At rest the height is the
        # surveyed deck-to-rack offset (3 cm): at 0.6 m over the pipes a pose one pipe off fits the edges
        # about as well 10 cm higher, and only the height tells them apart.
        z_body = float(T_start[2, 3] if resting else T_hint[2, 3])
        if state is not None and state.position_ned_m is not None:
            z_body = float(state.position_ned_m[2])
        z_cam = z_body + float(self.T_body_cam[2, 3])
        height = float(self.T_ned_rack[2, 3]) - z_cam
        return AcquisitionInputs(roll_rad=roll, pitch_rad=pitch, height_above_rack_m=height,
                                 height_std_m=0.03 if resting else max(0.05 * abs(height), 0.1),
                                 T_ned_body_hint=T_hint, y_std_m=y_std, from_start_hint=from_start)

    async def _vision_loop(self) -> None:
        assert self.pipeline is not None and self.camera is not None
        loop = asyncio.get_running_loop()
        while True:
            try:
                frame = await self.camera.next_frame(timeout_s=0.25)
            except CameraError as exc:
                self._event("camera-error", level=logging.ERROR, error=str(exc))
                self.camera_ok = False
                await self.clock.sleep(0.5)
                continue
            if frame is None:
                if getattr(self.camera, "ended", False):
                    self._event("camera-ended", level=logging.WARNING)
                    return
                continue
            prev = self._latest_frame
            gap_s = 0.0 if prev is None else float(frame.stamp_s) - float(prev.stamp_s)
            if gap_s > self.frame_gap_reset_s:
                # the tracker's own motion model is stale after a gap: restart it from the IMU-propagated filter
                self._rack_reset_pending = True
                self._rack_reset_reason = f"frame gap {gap_s:.2f} s"
            self._latest_frame = frame
            inputs = self._frame_inputs()
            try:
                if self._worker is None:
                    m = self.pipeline.measure(frame.image, frame.stamp_s, frame.seq, inputs)
                else:
                    m = await loop.run_in_executor(self._worker, self.pipeline.measure, frame.image, frame.stamp_s,
                                                   frame.seq, inputs)
            except CompanionError as exc:
                self.counters.vision_errors += 1
                self._event("vision-error", level=logging.WARNING, error=str(exc))
                continue
            self._after_measure(frame, m)

    def _report_acquisition(self, m: Measurement) -> None:
        """Acquisition state to the log, and to the GCS (STATUSTEXT on a lock, at most every 5 s otherwise;
        NAMED_VALUE_FLOAT ACQ_HYP = hypothesis count of each attempt)."""
        res: Any = m.acquisition
        n = len(res.hypotheses)
        if self.link is not None:
            with contextlib.suppress(Exception):
                self.link.named_value_float("ACQ_HYP", float(n))
        now = self.clock.now()
        if m.rack_acquired:
            best = res.best
            self._event("rack-acquired", hypotheses=n, score=round(float(best.score), 3), pipes=list(best.pipes),
                        y_observed=bool(best.y_observed))
            self._gcs_text(f"rack acquired ({n} hypotheses, pipes {list(best.pipes)})", "info")
        elif now - self._last_acq_text_s >= 5.0:
            self._last_acq_text_s = now
            self._event("rack-acquiring", hypotheses=n, status=str(res.status))
            self._gcs_text(f"acquiring the rack: {res.status or 'no confident pose'} ({n} hypotheses)", "info")

    def _after_measure(self, frame: Any, m: Measurement) -> None:
        assert self.nav_filter is not None and self.pipeline is not None
        self.counters.frames += 1
        self._vision_ms.append(float(m.process_s) * 1e3)
        if m.acquisition is not None:
            self._report_acquisition(m)
        if m.hint_check is not None:
            self._report_hint_check(m)
        self._hint_lock_update()
        if m.rack_y_fixed and self.pipeline.acquirer is not None:
            dy = float(self.pipeline.acquirer.last_y_fix_m)
            self._event("rack-y-fixed", dy_m=round(dy, 3))
            self._gcs_text(f"rack end in view: along-pipe position corrected by {100.0 * dy:+.0f} cm", "info")
        try:
            nav = self.pipeline.fuse(m, self.nav_filter)
        except CompanionError as exc:
            self.counters.vision_errors += 1
            self._event("fusion-error", level=logging.WARNING, error=str(exc))
            return
        # mirrored here, after the filter has taken the fix: the control task reads it on this thread
        self.along_pipe_from_start_hint = self.pipeline.along_pipe_from_start_hint
        self.last_nav = nav
        fresh = bool(nav.ok) and abs(float(nav.stamp_s) - float(frame.stamp_s)) < 1e-6
        acq = self.pipeline.acquirer
        if m.rack_acquired or m.rack_y_fixed:
            # the tracker was moved to a pose better than the filter's: hold the re-seeds from the filter
            # until it has taken a pose from there (or the tracker is lost and acquiring again)
            self._hold_rack_reseed, self._rack_fail_streak = True, 0
        elif (m.rack_ok and fresh and str(nav.source) == "rack") or (acq is not None and acq.acquiring):
            self._hold_rack_reseed = False
        if m.rack is not None:
            # a rack pose the filter did not accept (gated) counts as a tracker failure too
            accepted = m.rack_ok and fresh and str(nav.source) == "rack"
            self._rack_fail_streak = 0 if accepted or (m.rack_ok and str(nav.source) != "rack") else \
                self._rack_fail_streak + 1
            if self._rack_fail_streak >= 2:
                self._rack_reset_pending = True
                status = str(getattr(m.rack, "status", "") or "")
                self._rack_reset_reason = f"tracker: {status}" if not m.rack_ok else "pose not taken by the filter"
                self._rack_fail_streak = 0
        sent = False
        if fresh:
            self.last_fresh_pose_s = float(frame.stamp_s)
        if fresh and self._safety_view.send_poses and self.link is not None and not self._withhold_unverified(nav):
            from drivers.mavlink import PoseOut

            pose = PoseOut(
                stamp_s=float(nav.stamp_s),
                T_ned_body=np.asarray(nav.T_ned_body),
                pose_covariance=np.asarray(nav.pose_covariance),
                velocity_ned_m_s=np.asarray(nav.velocity_ned_m_s),
                velocity_covariance=np.asarray(nav.velocity_covariance),
                reset_counter=int(nav.reset_counter),
            )
            sent = bool(self.link.send_pose(pose))
        if sent:
            self.counters.poses_sent += 1
            self.last_pose_sent_s = float(frame.stamp_s)
            self._latency_ms.append((self.clock.now() - float(frame.stamp_s)) * 1e3)
            if self.flight is not None:
                self.flight.tum.write(float(nav.stamp_s), np.asarray(nav.T_ned_body))
        else:
            self.counters.poses_withheld += 1
        if self._pending_photo is not None:
            self._take_photo_now(frame, nav)
        if self.record_frames and self.flight is not None:
            with contextlib.suppress(OSError):
                self.flight.save_frame(frame.image, int(frame.seq), float(frame.stamp_s))
        record = FrameRecord(
            seq=int(frame.seq), capture_s=float(frame.stamp_s), source_stamp_s=frame.source_stamp_s,
            process_s=m.process_s, nav=nav, sent=sent, sent_s=self.clock.now(), sent_perf_s=time.perf_counter(),
            measurement=m,
        )
        for obs in list(self.frame_observers):
            obs(record)
