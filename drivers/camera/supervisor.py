"""The event-loop side of a camera source: opening the device, running one capture session at a time,
losing the source and reopening it with exponential backoff, recovering at the next frame, and the watchdog
that reports a source without frames as lost."""

from __future__ import annotations

import asyncio
import threading

from companion.errors import CameraError
from drivers.camera.frames import CameraState
from drivers.camera.source_state import CameraSourceState, _log

__all__ = ["CameraSupervisor"]


class CameraSupervisor(CameraSourceState):
    """The event-loop side of a `CameraSource`: loss, reopen and recovery (a mixin of `CameraSourceState`)."""

    # ------------------------------------------------------------------ event-loop side
    def _frame_arrived(self, stamp_s: float) -> None:
        self._last_progress_s = max(self._last_progress_s, self._clock.now())
        if self._frame_event is not None:
            self._frame_event.set()
        if self._state in (CameraState.STARTING, CameraState.LOST):
            recovered = self._state is CameraState.LOST
            self._state = CameraState.STREAMING
            if recovered:
                _log.info("%s: recovered", self.name)
                for callback in list(self._on_recovered):
                    callback()

    def _mark_lost(self, reason: str) -> None:
        self._last_error = reason
        if self._state is CameraState.LOST or self._stop.is_set():
            return
        self._state = CameraState.LOST
        self._lost_count += 1
        _log.warning("%s: camera lost: %s", self.name, reason)
        for callback in list(self._on_lost):
            callback(reason)

    def _session_finished(self, outcome: tuple[str, str]) -> None:
        self._session_outcome = outcome
        if self._session_done is not None:
            self._session_done.set()

    def _shutdown_session(self) -> None:
        """Join the capture thread and release the device (worker thread)."""
        thread = self._thread
        if thread is not None:
            thread.join(self._join_timeout_s)
            if thread.is_alive():
                # blocked in a read: releasing the device makes OpenCV return from it
                self._close_device()
                thread.join(2.0)
                if thread.is_alive():
                    _log.error("%s: capture thread did not stop", self.name)
            self._thread = None
        self._close_device()

    def _close_device(self) -> None:
        with self._cond:
            was_open, self._device_open = self._device_open, False
        if was_open:
            try:
                self._close()
            except Exception:
                _log.exception("%s: close failed", self.name)

    def _open_device(self) -> None:
        self._open()
        with self._cond:
            self._device_open = True

    async def _supervise(self) -> None:
        loop = asyncio.get_running_loop()
        backoff_s = self._backoff0_s
        had_failure = False
        while not self._stop.is_set():
            self._open_future = loop.run_in_executor(None, self._open_device)
            try:
                await self._open_future
                open_error = None
            except CameraError as exc:
                open_error = exc
            finally:
                self._open_future = None
            if open_error is not None:
                self._read_failures += 1
                self._mark_lost(f"open failed: {open_error}")
                had_failure = True
                await self._clock.sleep(backoff_s)
                backoff_s = min(2.0 * backoff_s, self._backoff_max_s)
                continue
            if had_failure:
                self._reopen_count += 1
            self._last_progress_s = max(self._last_progress_s, self._clock.now())
            captured_before = self.stats.captured
            self._session_done = asyncio.Event()
            self._thread = threading.Thread(target=self._capture_loop, name=f"{self.name}-capture", daemon=True)
            self._thread.start()
            await self._session_done.wait()
            kind, reason = self._session_outcome
            await asyncio.to_thread(self._shutdown_session)
            if kind == "stopped" or self._stop.is_set():
                return
            if kind == "ended":
                self._state = CameraState.ENDED
                if self._frame_event is not None:
                    self._frame_event.set()
                return
            if kind == "fatal":
                self._fatal = CameraError(f"{self.name}: {reason}")
                self._last_error = reason
                self._mark_lost(reason)
                if self._frame_event is not None:
                    self._frame_event.set()
                return
            self._read_failures += 1
            self._mark_lost(reason)
            had_failure = True
            if self.stats.captured > captured_before:
                backoff_s = self._backoff0_s
            await self._clock.sleep(backoff_s)
            backoff_s = min(2.0 * backoff_s, self._backoff_max_s)

    async def _watchdog(self) -> None:
        period_s = self._lost_after_s / 4.0
        while True:
            await self._clock.sleep(period_s)
            if self._state not in (CameraState.STARTING, CameraState.STREAMING):
                continue
            with self._cond:
                waiting_for_consumer = self._slot is not None
            if waiting_for_consumer:
                continue
            silent_s = self._clock.now() - self._last_progress_s
            if silent_s > self._lost_after_s:
                self._mark_lost(f"no frame for {silent_s:.2f} s")
