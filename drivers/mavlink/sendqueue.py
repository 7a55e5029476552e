"""Bounded priority send queue for the link's single writer task (no I/O).

Three classes, served strictly in order: CONTROL (commands, heartbeats, timesync, GCS text),
SETPOINT, POSE. Each class is bounded; when a class is full its *oldest* entry is dropped
(a stale pose is worthless, a newer one supersedes it) and counted. Entries carry their
enqueue time and an optional expiry so the writer can discard what went stale while waiting.
"""

from __future__ import annotations

import asyncio
import enum
from collections import deque
from dataclasses import dataclass

__all__ = ["Priority", "QueuedFrame", "SendQueue"]


class Priority(enum.IntEnum):
    CONTROL = 0
    SETPOINT = 1
    POSE = 2


@dataclass(frozen=True)
class QueuedFrame:
    """One encoded frame waiting for the writer; ``expires_s`` None = never (link clock, s)."""

    data: bytes
    priority: Priority
    enqueued_s: float
    expires_s: float | None = None
    to_autopilot: bool = True
    to_gcs: bool = True


class SendQueue:
    """Per-priority bounded FIFOs with drop-oldest overflow and an awaitable 'not empty'."""

    def __init__(self, limits: dict[Priority, int] | None = None) -> None:
        default = {Priority.CONTROL: 256, Priority.SETPOINT: 4, Priority.POSE: 8}
        if limits:
            default.update(limits)
        self._queues: dict[Priority, deque[QueuedFrame]] = {p: deque() for p in Priority}
        self._limits = default
        self._event = asyncio.Event()
        self.dropped: dict[Priority, int] = {p: 0 for p in Priority}

    def __len__(self) -> int:
        return sum(len(q) for q in self._queues.values())

    def put(self, frame: QueuedFrame) -> None:
        """Enqueue; drops the oldest frame of the same priority when that class is full."""
        q = self._queues[frame.priority]
        if len(q) >= self._limits[frame.priority]:
            q.popleft()
            self.dropped[frame.priority] += 1
        q.append(frame)
        self._event.set()

    def pop(self) -> QueuedFrame | None:
        """Highest-priority oldest frame, or None if empty."""
        for p in Priority:
            q = self._queues[p]
            if q:
                return q.popleft()
        self._event.clear()
        return None

    def clear(self, priority: Priority | None = None) -> int:
        """Drop everything (or one class); returns how many were dropped."""
        n = 0
        for p in Priority if priority is None else (priority,):
            n += len(self._queues[p])
            self._queues[p].clear()
        return n

    async def wait(self) -> None:
        """Return once the queue is (probably) non-empty."""
        if len(self):
            return
        self._event.clear()
        await self._event.wait()
