"""Clocks for the I/O layers: the real monotonic clock and a manual one for tests.

Pure modules never read a clock: time comes in as an argument. The daemon, the
MAVLink link, the camera drivers and the fake autopilot take a `Clock` so tests
can run them on a `ManualClock` whose time only moves when the test advances
it; nobody sleeps in a test to wait for something.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Monotonic time source with an awaitable sleep."""

    def now(self) -> float:
        """Monotonic time in seconds."""
        ...

    async def sleep(self, seconds: float) -> None:
        """Suspend the calling task for `seconds` of this clock's time."""
        ...


class SystemClock:
    """The real clock: `time.monotonic` and `asyncio.sleep`."""

    def now(self) -> float:
        return time.monotonic()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))


class ManualClock:
    """A clock whose time moves only through `advance`/`advance_to` (for tests).

    Sleepers wake in time order; between wake-ups the event loop runs a few
    idle iterations so that socket I/O on loopback (already in the kernel's
    buffers) is delivered before time moves on. `now()` is thread-safe.
    """

    def __init__(self, start_s: float = 1000.0, io_yields: int = 8) -> None:
        self._now = float(start_s)
        self._lock = threading.Lock()
        self._waiters: list[tuple[float, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        self._io_yields = io_yields

    def now(self) -> float:
        with self._lock:
            return self._now

    async def sleep(self, seconds: float) -> None:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        with self._lock:
            wake = self._now + max(0.0, seconds)
            heapq.heappush(self._waiters, (wake, next(self._seq), fut))
        await fut

    async def _settle(self) -> None:
        # Zero-timeout loop iterations: ready callbacks run and the selector
        # polls sockets without blocking, so loopback datagrams get through.
        for _ in range(self._io_yields):
            await asyncio.sleep(0)

    async def advance(self, seconds: float, step_s: float | None = None) -> None:
        """Move time forward by `seconds`, in steps of at most `step_s` if given."""
        await self.advance_to(self.now() + seconds, step_s)

    async def advance_to(self, target_s: float, step_s: float | None = None) -> None:
        """Move time forward to `target_s`, waking every sleeper due on the way."""
        await self._settle()
        while True:
            with self._lock:
                next_wake = self._waiters[0][0] if self._waiters else None
                if step_s is not None:
                    horizon = min(target_s, self._now + step_s)
                else:
                    horizon = target_s
                if next_wake is not None and next_wake <= horizon:
                    self._now = max(self._now, next_wake)
                    due = []
                    while self._waiters and self._waiters[0][0] <= self._now:
                        due.append(heapq.heappop(self._waiters)[2])
                else:
                    self._now = max(self._now, horizon)
                    due = []
                    if self._now >= target_s:
                        break
            for fut in due:
                if not fut.done():
                    fut.set_result(None)
            await self._settle()
        await self._settle()

    @property
    def pending(self) -> int:
        """Number of tasks sleeping on this clock."""
        with self._lock:
            return len(self._waiters)
