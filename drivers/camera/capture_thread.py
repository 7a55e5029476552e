"""The capture thread of a camera source: reads frames (blocking), stamps them on the injected clock, puts
the newest in the slot of one, and lets the thread wait on the event loop (`_pace`, `_run_on_loop`)."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from companion.errors import CameraError
from drivers.camera.frames import EndOfStream, Frame, Image, convert_color
from drivers.camera.source_state import CameraSourceState, _log

__all__ = ["CaptureThread"]

_T = TypeVar("_T")


class _Stopped(Exception):
    """The source is being closed (raised inside the capture thread)."""


class CaptureThread(CameraSourceState):
    """The capture-thread side of a `CameraSource` (a mixin of `CameraSourceState`)."""

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
