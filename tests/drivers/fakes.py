"""Fakes for the driver tests: an OpenCV-like capture device and a clock that reports its sleepers."""

from __future__ import annotations

import asyncio
import queue
import threading
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from companion.clock import ManualClock

_UNPLUG = object()


class FakeCapture:
    """One opened capture of a `FakeDevice` (the `cv2.VideoCapture` surface the drivers use)."""

    def __init__(self, device: FakeDevice, opened: bool) -> None:
        self._device = device
        self._opened = opened
        self._queue: queue.Queue[Any] = queue.Queue()
        self.props: dict[int, float] = {}
        self.released = False

    def isOpened(self) -> bool:
        return self._opened

    def read(self) -> tuple[bool, Any]:
        self._device.note_read()
        item = self._queue.get()
        if item is _UNPLUG or self.released:
            return False, None
        return True, item

    def set(self, prop_id: int, value: float) -> bool:
        self.props[prop_id] = value
        return True

    def get(self, prop_id: int) -> float:
        if prop_id in self._device.reported:
            return self._device.reported[prop_id]
        return self.props.get(prop_id, 0.0)

    def release(self) -> None:
        self.released = True
        self._queue.put(_UNPLUG)


class FakeDevice:
    """A camera device that can be fed frames, unplugged and plugged back (thread-safe)."""

    def __init__(self, plugged: bool = True) -> None:
        self.plugged = plugged
        self.opens: list[tuple[Any, int]] = []
        self.captures: list[FakeCapture] = []
        self.reported: dict[int, float] = {}
        self._reads = 0
        self._cond = threading.Condition()

    def factory(self, device: Any, api_preference: int) -> FakeCapture:
        with self._cond:
            self.opens.append((device, api_preference))
            cap = FakeCapture(self, opened=self.plugged)
            if self.plugged:
                self.captures.append(cap)
            self._cond.notify_all()
            return cap

    @property
    def current(self) -> FakeCapture:
        return self.captures[-1]

    def feed(self, *images: np.ndarray[Any, Any]) -> None:
        for image in images:
            self.current._queue.put(image)

    def unplug(self) -> None:
        self.plugged = False
        if self.captures:
            self.current._queue.put(_UNPLUG)

    def note_read(self) -> None:
        with self._cond:
            self._reads += 1
            self._cond.notify_all()

    def wait_reads(self, count: int, timeout_s: float = 5.0) -> None:
        """Block until `read()` has been entered `count` times (the capture thread is waiting)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._reads >= count, timeout_s):
                raise TimeoutError(f"only {self._reads} reads, expected {count}")


def image(value: int, shape: tuple[int, ...] = (48, 64, 3)) -> np.ndarray[Any, Any]:
    return np.full(shape, value, dtype=np.uint8)


class RecordingClock(ManualClock):
    """A ManualClock that lets a test wait until some task sleeps for a given duration."""

    def __init__(self, start_s: float = 1000.0) -> None:
        super().__init__(start_s)
        self.sleeps: list[float] = []
        self._watchers: list[tuple[Callable[[float], bool], asyncio.Future[float]]] = []

    async def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        for match, fut in list(self._watchers):
            if not fut.done() and match(seconds):
                fut.set_result(seconds)
                self._watchers.remove((match, fut))
        await super().sleep(seconds)

    def expect_sleep(self, seconds: float) -> asyncio.Future[float]:
        """A future done when some task next starts sleeping `seconds` on this clock (register first)."""
        fut: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        self._watchers.append((lambda s: abs(s - seconds) < 1e-9, fut))
        return fut


async def wait_event(event: asyncio.Event, timeout_s: float = 5.0) -> None:
    """Await `event` with a real-time guard so a broken driver fails the test instead of hanging it."""
    await asyncio.wait_for(event.wait(), timeout_s)


def write_video(path: str, frames: int, size: tuple[int, int] = (64, 48), fps: float = 10.0) -> None:
    """A small MJPG AVI whose frame k is a flat gray of 20 k + 10."""
    writer = cv2.VideoWriter(path, cv2.VideoWriter.fourcc(*"MJPG"), fps, size)
    assert writer.isOpened()
    for k in range(frames):
        writer.write(np.full((size[1], size[0], 3), 20 * k + 10, dtype=np.uint8))
    writer.release()
