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
import concurrent.futures
import contextlib
import enum
import logging
import threading
from collections.abc import AsyncIterator, Callable, Coroutine
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self, TypeVar

import cv2
import numpy as np

from companion.clock import Clock
from companion.errors import CameraError

_log = logging.getLogger(__name__)

Image = np.ndarray[Any, np.dtype[Any]]  # uint8 (H, W) or (H, W, 3)
_T = TypeVar("_T")


@dataclass(frozen=True)
class Frame:
    """One captured image.

    `image`: (H, W) uint8 gray or (H, W, 3) uint8 BGR. `stamp_s`: the injected
    clock's monotonic time at capture (s). `seq`: capture counter from 0 over
    the source's life (gaps = frames dropped). `dropped_before`: frames that
    were captured after the previously delivered one and replaced before being
    delivered. `source_stamp_s`: the recording's own time of the frame (s;
    folder timestamps file, video position, synthetic pose stamp) or None.
    """

    image: Image
    stamp_s: float
    seq: int
    dropped_before: int
    source_stamp_s: float | None = None


class CameraState(enum.Enum):
    """Life cycle of a source."""

    STARTING = "starting"  # entered, no frame yet
    STREAMING = "streaming"  # frames arriving
    LOST = "lost"  # read/open failure or no frame for lost_after_s; reopening with backoff
    ENDED = "ended"  # a finite source (video, folder) is exhausted
    CLOSED = "closed"  # not entered, or exited


@dataclass(frozen=True)
class CameraStats:
    """Counters of a source (a snapshot)."""

    captured: int  # frames read from the device
    delivered: int  # frames handed to the consumer
    dropped_stale: int  # frames replaced by a newer one before delivery
    read_failures: int  # failed reads or opens
    reopen_count: int  # successful reopens after a failure
    lost_count: int  # times the source became LOST
    lost: bool
    state: CameraState
    last_frame_s: float | None  # clock time of the newest captured frame
    last_error: str | None


@dataclass(frozen=True)
class Capture:
    """What `_read` returns for one frame: the image and optional stamps (s)."""

    image: Image
    stamp_s: float | None = None  # None: the base stamps clock.now() after the read
    source_stamp_s: float | None = None


class EndOfStream(Exception):
    """Raised by `_read` when a finite source has no more frames."""


class _Stopped(Exception):
    """The source is being closed (raised inside the capture thread)."""


def convert_color(image: Any, color: str) -> Image:
    """`image` as (H, W) uint8 gray (color="gray") or (H, W, 3) uint8 BGR (color="bgr")."""
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        raise CameraError(f"image: expected uint8 pixels, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 2:
        return arr if color == "gray" else cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        if color == "gray":
            code = cv2.COLOR_BGR2GRAY if arr.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            return cv2.cvtColor(arr, code)
        return arr if arr.shape[2] == 3 else cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR)
    raise CameraError(f"image: expected (H, W) or (H, W, 3) pixels, got shape {arr.shape}")


class CameraSource:
    """Base of every camera source (see the module docstring for the behaviour)."""

    def __init__(
        self,
        clock: Clock,
        *,
        name: str,
        color: str = "gray",
        lost_after_s: float = 0.5,
        reopen_backoff_s: float = 0.2,
        reopen_backoff_max_s: float = 5.0,
        drop_stale: bool = True,
        join_timeout_s: float = 0.5,
    ) -> None:
        if color not in ("gray", "bgr"):
            raise CameraError(f'color: must be "gray" or "bgr", got {color!r}')
        if lost_after_s <= 0 or reopen_backoff_s <= 0 or reopen_backoff_max_s < reopen_backoff_s:
            raise CameraError("lost_after_s/reopen_backoff_s: must be > 0 and backoff max >= backoff")
        self.name = name
        self._clock = clock
        self._color = color
        self._lost_after_s = float(lost_after_s)
        self._backoff0_s = float(reopen_backoff_s)
        self._backoff_max_s = float(reopen_backoff_max_s)
        self._drop_stale = drop_stale
        self._join_timeout_s = join_timeout_s
        # shared with the capture thread, guarded by _cond
        self._cond = threading.Condition()
        self._slot: Frame | None = None
        self._seq = 0
        self._pending_drops = 0
        self._captured = 0
        self._delivered = 0
        self._dropped = 0
        self._last_frame_s: float | None = None
        self._stop = threading.Event()
        self._thread_futures: set[concurrent.futures.Future[Any]] = set()
        # event-loop side
        self._state = CameraState.CLOSED
        self._read_failures = 0
        self._reopen_count = 0
        self._lost_count = 0
        self._last_error: str | None = None
        self._fatal: CameraError | None = None
        self._last_progress_s = 0.0
        self._on_lost: list[Callable[[str], None]] = []
        self._on_recovered: list[Callable[[], None]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._frame_event: asyncio.Event | None = None
        self._session_done: asyncio.Event | None = None
        self._session_outcome: tuple[str, str] = ("", "")
        self._tasks: list[asyncio.Task[None]] = []
        self._thread: threading.Thread | None = None
        self._open_future: asyncio.Future[None] | None = None
        self._device_open = False

    # ------------------------------------------------------------------ subclass hooks (worker threads)
    async def _check_available(self) -> None:
        """Raise `CameraError` if the source can never work (called in `__aenter__`)."""

    def _open(self) -> None:
        """Open the device; raise `CameraError` on failure."""
        raise NotImplementedError

    def _read(self) -> Capture | None:
        """Block for the next frame. None: no frame this time (try again). Raise `CameraError` on a
        failed read (the source reopens), `EndOfStream` when a finite source is exhausted."""
        raise NotImplementedError

    def _close(self) -> None:
        """Release the device (must not raise)."""

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

    # ------------------------------------------------------------------ capture thread
    def _post(self, callback: Callable[..., None], *args: Any) -> None:
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # loop closed during shutdown
            loop.call_soon_threadsafe(callback, *args)

    def _run_on_loop(self, coro: Coroutine[Any, Any, _T]) -> _T:
        """Run `coro` on the event loop from the capture thread and wait for it; `_Stopped` when closing."""
        loop = self._loop
        if loop is None or self._stop.is_set():
            coro.close()
            raise _Stopped
        fut = asyncio.run_coroutine_threadsafe(coro, loop)
        with self._cond:
            self._thread_futures.add(fut)
        try:
            if self._stop.is_set():
                fut.cancel()
            return fut.result()
        except concurrent.futures.CancelledError:
            raise _Stopped from None
        finally:
            with self._cond:
                self._thread_futures.discard(fut)

    def _pace(self, due_s: float) -> float:
        """From the capture thread: sleep on the clock until `due_s` (clock time); returns the clock time."""

        async def wait() -> float:
            delay = due_s - self._clock.now()
            if delay > 0:
                await self._clock.sleep(delay)
            return self._clock.now()

        return self._run_on_loop(wait())

    def _capture_loop(self) -> None:
        outcome = ("stopped", "")
        try:
            while not self._stop.is_set():
                try:
                    cap = self._read()
                except _Stopped:
                    break
                except EndOfStream:
                    outcome = ("ended", "end of stream")
                    break
                except CameraError as exc:
                    outcome = ("failed", str(exc) or type(exc).__name__)
                    break
                except Exception as exc:
                    _log.exception("%s: capture crashed", self.name)
                    outcome = ("fatal", f"{type(exc).__name__}: {exc}")
                    break
                if cap is None:
                    continue
                stamp_s = self._clock.now() if cap.stamp_s is None else cap.stamp_s
                try:
                    image = convert_color(cap.image, self._color)
                except CameraError as exc:
                    outcome = ("fatal", str(exc))
                    break
                self._deliver(image, stamp_s, cap.source_stamp_s)
                if not self._drop_stale:
                    with self._cond:
                        while self._slot is not None and not self._stop.is_set():
                            self._cond.wait()
        finally:
            if self._stop.is_set():
                outcome = ("stopped", "")
            self._post(self._session_finished, outcome)

    def _deliver(self, image: Image, stamp_s: float, source_stamp_s: float | None) -> None:
        with self._cond:
            if self._slot is not None:
                self._dropped += 1
                self._pending_drops += 1
            self._slot = Frame(image, stamp_s, self._seq, self._pending_drops, source_stamp_s)
            self._seq += 1
            self._captured += 1
            self._last_frame_s = stamp_s
        self._post(self._frame_arrived, stamp_s)

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

