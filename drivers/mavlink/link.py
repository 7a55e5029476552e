"""The MAVLink link: one async object that owns the transport and every task that talks on it.

Tasks (all started by ``async with MavLink(...)``, all on the injected clock):

- connection: opens the transport, re-opens it with exponential backoff when it dies or when
  the autopilot falls silent for ``autopilot_timeout_s``;
- writer: the only task that writes; drains a bounded priority queue (CONTROL > SETPOINT > POSE);
- heartbeat (1 Hz, MAV_TYPE_ONBOARD_CONTROLLER), timesync requests, EKF origin until confirmed,
  message-interval requests whenever the autopilot (re)appears, velocity setpoint stream;
- the reader is the transport's callback: bytes -> `FrameParser` -> `StateTracker` + callbacks.

The parts of `MavLink` are mixins, one concern each: `link_core` (shared state and helpers),
`link_outbound` (poses, velocity command, ground-station messages), `link_commands` (COMMAND_LONG and the
commands), `link_reader` (the receive path), `link_tasks` (the task bodies); `LinkConfig` is in
`link_config`, `LinkHealth` and `LinkStats` in `link_status`. This module keeps the lifecycle and the
public status surface, and re-exports what is imported from it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from types import TracebackType
from typing import Any

from companion.control.types import VelocityCommand
from companion.errors import LinkError
from drivers.mavlink.link_commands import CommandsMixin
from drivers.mavlink.link_config import LinkConfig
from drivers.mavlink.link_core import LinkCore
from drivers.mavlink.link_outbound import SEVERITY, OutboundMixin
from drivers.mavlink.link_reader import ReaderMixin
from drivers.mavlink.link_status import LinkHealth, LinkStats
from drivers.mavlink.link_tasks import TasksMixin
from drivers.mavlink.state import ImuSample, VehicleState

__all__ = ["SEVERITY", "LinkConfig", "LinkHealth", "LinkStats", "MavLink"]

log = logging.getLogger(__name__)


class MavLink(TasksMixin, ReaderMixin, CommandsMixin, OutboundMixin, LinkCore):
    """Async MAVLink connection to one autopilot (see the module docstring)."""

    # ================================================================ context manager
    async def __aenter__(self) -> MavLink:
        if self._open:
            raise LinkError("link already open")
        self._open = True
        try:
            await self._open_transport()
        except (LinkError, OSError) as exc:  # the connection task keeps trying, with backoff
            self._counts["connect_failures"] += 1
            log.info("mavlink connect %s failed: %s", self.config.url, exc)
        try:
            for t, parser in self._forwards:
                await t.open(self._forward_receiver(t, parser), lambda exc: None)
        except (LinkError, OSError) as exc:
            await self.close()
            raise LinkError(f"cannot open GCS forwarding endpoint: {exc}") from exc
        for name, coro in (
            ("connection", self._connection_loop()),
            ("writer", self._writer_loop()),
            ("heartbeat", self._heartbeat_loop()),
            ("timesync", self._timesync_loop()),
            ("origin", self._origin_loop()),
            ("setpoints", self._setpoint_loop()),
            ("watchdog", self._watchdog_loop()),
        ):
            self._tasks.append(asyncio.create_task(coro, name=f"mavlink-{name}"))
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def close(self) -> None:
        """Stop every task, close the transports and the tlog."""
        tasks = list(self._tasks)
        if self._interval_task is not None:
            tasks.append(self._interval_task)
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks.clear()
        self._interval_task = None
        for fut in self._pending_acks.values():
            if not fut.done():
                fut.cancel()
        await self._transport.close()
        for t, _ in self._forwards:
            await t.close()
        if self._tlog is not None:
            self._tlog.close()
        self._open = False

    # ================================================================ public surface
    @property
    def health(self) -> LinkHealth:
        if not self._transport.is_open:
            return LinkHealth.DISCONNECTED
        if self._autopilot_present:
            return LinkHealth.AUTOPILOT_OK
        return LinkHealth.AUTOPILOT_LOST if self.state.last_autopilot_heartbeat_s is not None else LinkHealth.CONNECTED

    @property
    def stats(self) -> LinkStats:
        c = dict(self._counts)
        p = self._parser.counters
        for parser in [p] + [fp.counters for _, fp in self._forwards]:
            c["garbage_bytes"] += parser.garbage_bytes
            c["bad_frames"] += parser.bad_frames
            c["unknown_messages"] += parser.unknown_messages
            c["mavlink1_rejected"] += parser.mavlink1_rejected
            c["parser_errors"] += parser.parser_errors
        c["bytes_in"] += p.bytes_in
        c["messages_in"] += p.messages
        c["frames_dropped_queue"] += sum(self._queue.dropped.values())
        c["bytes_out"] += self._transport.bytes_out
        c["transport_errors"] += self._transport.write_errors
        c["timesync_samples"] = self._timesync.samples_total
        c["tlog_records"] = 0 if self._tlog is None else self._tlog.records
        return LinkStats(**c)

    @property
    def time_offset_s(self) -> float | None:
        """Autopilot clock minus our clock (s) once TIMESYNC has converged, else None."""
        return self._timesync.offset_s if self._timesync.converged else None

    @property
    def local_address(self) -> tuple[str, int] | None:
        """Our socket address (useful with ``udpin:127.0.0.1:0``)."""
        return self._transport.local_address

    @property
    def velocity_command(self) -> VelocityCommand | None:
        return self._velocity_cmd

    def on_imu(self, callback: Callable[[ImuSample], object]) -> Callable[[], None]:
        """Call ``callback(sample)`` for every IMU message; returns a function that unsubscribes."""
        self._imu_callbacks.append(callback)
        return lambda: self._imu_callbacks.remove(callback) if callback in self._imu_callbacks else None

    def on_message(self, callback: Callable[[Any], object]) -> Callable[[], None]:
        """Call ``callback(msg)`` with every decoded pymavlink message; returns an unsubscribe function."""
        self._message_callbacks.append(callback)
        return lambda: self._message_callbacks.remove(callback) if callback in self._message_callbacks else None

    async def wait_autopilot(self, timeout_s: float = 10.0) -> VehicleState:
        """Wait (on the link's clock) until an autopilot heartbeat was heard; LinkError on timeout."""
        if not self._autopilot_present:
            self._autopilot_seen.clear()
            if not await self._wait_event(self._autopilot_seen, timeout_s):
                raise LinkError(f"no autopilot heartbeat on {self.config.url} within {timeout_s} s")
        return self.state
