"""TIMESYNC offset estimation (MAVLink timesync protocol, nanoseconds on the wire).

We send ``TIMESYNC(tc1=0, ts1=our_ns)``; the peer answers ``TIMESYNC(tc1=its_ns, ts1=our_ns)``.
One round trip gives ``offset = tc1 - (ts1 + now) / 2`` (peer minus ours) with an error bounded
by half the round-trip time. The estimate is the offset of the fastest round trip among the
last ``window`` samples; it is `converged` after ``min_samples`` samples. A sample more than
``jump_s`` away from the estimate (with a short round trip) means the peer's clock jumped
(reboot): the history is dropped.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

__all__ = ["TimeSync", "TimeSyncConfig"]


@dataclass(frozen=True)
class TimeSyncConfig:
    """Tuning of the offset estimator (seconds)."""

    window: int = 10
    min_samples: int = 3
    max_rtt_s: float = 0.5
    jump_s: float = 1.0


class TimeSync:
    """Offset between the peer's clock and ours, from TIMESYNC round trips."""

    def __init__(self, config: TimeSyncConfig | None = None) -> None:
        self._config = config or TimeSyncConfig()
        self._samples: deque[tuple[float, float]] = deque(maxlen=self._config.window)  # (rtt_s, offset_s)
        self._pending: deque[int] = deque(maxlen=16)
        self.samples_total = 0
        self.resets = 0

    def request_ns(self, now_s: float) -> int:
        """ts1 for an outgoing request at local time ``now_s`` (remembered to match the answer)."""
        ts1 = max(1, round(now_s * 1e9))
        self._pending.append(ts1)
        return ts1

    def is_our_request(self, ts1_ns: int) -> bool:
        """True if ``ts1_ns`` is the stamp of one of our recent requests."""
        return ts1_ns in self._pending

    def add_response(self, tc1_ns: int, ts1_ns: int, now_s: float) -> bool:
        """Fold in the peer's answer to one of our requests; False if rejected."""
        if ts1_ns not in self._pending:
            return False
        self._pending.remove(ts1_ns)
        ts1_s = ts1_ns * 1e-9
        rtt_s = now_s - ts1_s
        if rtt_s < -1e-6 or rtt_s > self._config.max_rtt_s:  # tiny negatives: ns rounding of ts1
            return False
        rtt_s = max(rtt_s, 0.0)
        offset_s = tc1_ns * 1e-9 - 0.5 * (ts1_s + now_s)
        if self._samples and abs(offset_s - self._best()) > self._config.jump_s:
            self._samples.clear()
            self.resets += 1
        self._samples.append((rtt_s, offset_s))
        self.samples_total += 1
        return True

    def _best(self) -> float:
        return min(self._samples)[1]

    @property
    def converged(self) -> bool:
        """True once enough round trips are in the window."""
        return len(self._samples) >= self._config.min_samples

    @property
    def offset_s(self) -> float | None:
        """Peer time minus local time (s), None before the first sample."""
        return self._best() if self._samples else None

    @property
    def rtt_s(self) -> float | None:
        """Fastest round trip in the window (s)."""
        return min(self._samples)[0] if self._samples else None

    def to_peer_s(self, local_s: float) -> float | None:
        """A local time expressed in the peer's time base, None until converged."""
        off = self.offset_s
        return local_s + off if (off is not None and self.converged) else None

    def to_local_s(self, peer_s: float) -> float | None:
        """A peer time expressed in our time base, None until converged."""
        off = self.offset_s
        return peer_s - off if (off is not None and self.converged) else None
