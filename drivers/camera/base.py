"""The common camera-source machinery: capture thread, newest-frame slot, loss and recovery.

A `CameraSource` is an async context manager. Entering it starts a supervisor
task on the event loop that opens the device (in a worker thread) and runs one
capture thread per open session. The capture thread reads frames (blocking),
stamps each with the injected clock's `now()` right after the read returns, and
puts it into a slot of one: a newer frame replaces an unconsumed one, which is
counted as dropped (`dropped_stale`), so the consumer always gets the newest
frame and latency never grows. With `drop_stale=False` (replay pacing) the
thread instead waits until the frame has been taken.

A failed read or open makes the source LOST (`on_lost` callbacks fire once);
the supervisor closes the device and reopens it with exponential backoff on
the injected clock. A watchdog also reports LOST when no frame arrived for
`lost_after_s`. The first frame after a loss makes it STREAMING again and
fires `on_recovered`. Callbacks run on the event-loop thread.

Subclasses implement `_open`, `_read` and `_close` (called from worker
threads) and may use `_pace(offset_s)` / `_run_on_loop(coro)` from the capture
thread to wait on the injected clock.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from types import TracebackType
from typing import Any, Self

from companion.errors import CameraError
from drivers.camera.capture_thread import CaptureThread
from drivers.camera.frames import CameraState, CameraStats, Capture, EndOfStream, Frame, Image, convert_color
from drivers.camera.supervisor import CameraSupervisor

__all__ = ["CameraSource", "CameraState", "CameraStats", "Capture", "EndOfStream", "Frame", "Image", "convert_color"]


class CameraSource(CaptureThread, CameraSupervisor):
    """Base of every camera source (see the module docstring for the behaviour)."""

    # ------------------------------------------------------------------ public surface
    @property
    def state(self) -> CameraState:
        return self._state

    @property
    def healthy(self) -> bool:
        """True while frames are streaming."""
        return self._state is CameraState.STREAMING

    @property
    def ended(self) -> bool:
        """True once a finite source (video, folder without loop) is exhausted."""
        return self._state is CameraState.ENDED

    @property
    def stats(self) -> CameraStats:
        with self._cond:
            captured, delivered, dropped, last = self._captured, self._delivered, self._dropped, self._last_frame_s
        return CameraStats(
            captured=captured,
            delivered=delivered,
            dropped_stale=dropped,
            read_failures=self._read_failures,
            reopen_count=self._reopen_count,
            lost_count=self._lost_count,
            lost=self._state is CameraState.LOST,
            state=self._state,
            last_frame_s=last,
            last_error=self._last_error,
        )

    def on_lost(self, callback: Callable[[str], None]) -> None:
        """Register `callback(reason)`, called (event-loop thread) each time the source becomes LOST."""
        self._on_lost.append(callback)

    def on_recovered(self, callback: Callable[[], None]) -> None:
        """Register `callback()`, called (event-loop thread) at the first frame after a loss."""
        self._on_recovered.append(callback)

    async def __aenter__(self) -> Self:
        if self._state is not CameraState.CLOSED or self._loop is not None:
            raise CameraError(f"{self.name}: already started")
        await self._check_available()
        self._loop = asyncio.get_running_loop()
        self._frame_event = asyncio.Event()
        self._stop.clear()
        self._state = CameraState.STARTING
        self._last_progress_s = self._clock.now()
        self._tasks = [
            asyncio.create_task(self._supervise(), name=f"{self.name}-supervisor"),
            asyncio.create_task(self._watchdog(), name=f"{self.name}-watchdog"),
        ]
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def close(self) -> None:
        """Stop the capture thread and release the device (idempotent)."""
        if self._loop is None:
            return
        self._stop.set()
        with self._cond:
            futures = list(self._thread_futures)
            self._cond.notify_all()
        for fut in futures:
            fut.cancel()
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks = []
        if self._open_future is not None:
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await asyncio.shield(self._open_future)
        await asyncio.to_thread(self._shutdown_session)
        self._state = CameraState.CLOSED
        self._loop = None
        if self._frame_event is not None:
            self._frame_event.set()

    async def next_frame(self, timeout_s: float | None = None) -> Frame | None:
        """The newest frame not yet delivered, waiting up to `timeout_s` of the clock (None = forever).

        Returns None on timeout, when the source has ended or is closed. Raises `CameraError` if the
        source failed for good (e.g. the synthetic renderer raised an unexpected exception).
        """
        if self._fatal is not None:
            raise self._fatal
        frame = self._take()
        if frame is not None or self._frame_event is None:
            return frame
        timer: asyncio.Future[None] | None = None
        if timeout_s is not None:
            if timeout_s <= 0:
                return None
            timer = asyncio.ensure_future(self._clock.sleep(timeout_s))
        try:
            while True:
                event = self._frame_event
                if self._state in (CameraState.ENDED, CameraState.CLOSED):
                    return self._take()
                event.clear()
                frame = self._take()
                if frame is not None:
                    return frame
                waiter = asyncio.ensure_future(event.wait())
                pending: set[asyncio.Future[Any]] = {waiter} if timer is None else {waiter, timer}
                try:
                    await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
                finally:
                    waiter.cancel()
                if self._fatal is not None:
                    raise self._fatal
                frame = self._take()
                if frame is not None:
                    return frame
                if timer is not None and timer.done():
                    return None
        finally:
            if timer is not None:
                timer.cancel()

    async def frames(self, timeout_s: float | None = None) -> AsyncIterator[Frame]:
        """Frames until the source ends or closes; waits at most `timeout_s` each (then stops)."""
        while True:
            frame = await self.next_frame(timeout_s)
            if frame is None:
                return
            yield frame

    # ------------------------------------------------------------------ consumer side
    def _take(self) -> Frame | None:
        with self._cond:
            frame = self._slot
            if frame is None:
                return None
            self._slot = None
            self._pending_drops = 0
            self._delivered += 1
            self._cond.notify_all()
        self._last_progress_s = max(self._last_progress_s, self._clock.now())
        return frame
