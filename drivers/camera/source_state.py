"""The state every part of a camera source shares (see `CameraSource`): the settings, the newest-frame slot
and counters guarded by a condition, the event-loop bookkeeping, and the subclass hooks `_open`, `_read`,
`_close` and `_check_available`. Base of the capture-thread and supervisor mixins."""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from companion.clock import Clock
from companion.errors import CameraError
from drivers.camera.frames import CameraState, CameraStats, Capture, Frame

__all__ = ["CameraSourceState"]

_log = logging.getLogger("drivers.camera.base")  # one logger for a whole source, named after CameraSource's module


class CameraSourceState:
    """State of a `CameraSource` (see `__init__`), shared by the capture-thread and supervisor mixins."""

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

    if TYPE_CHECKING:
        # Implemented by the mixins and `CameraSource` and called across them (at run time they exist on
        # `CameraSource` only); declared here so that mypy checks those calls.
        @property
        def stats(self) -> CameraStats: ...  # CameraSource
        def _capture_loop(self) -> None: ...  # CaptureThread
        def _frame_arrived(self, stamp_s: float) -> None: ...  # CameraSupervisor
        def _session_finished(self, outcome: tuple[str, str]) -> None: ...  # CameraSupervisor
