"""`LinkCore`: what every part of `MavLink` shares, the state built in ``__init__`` and the helpers they
all use (vehicle snapshot, autopilot profile, the send queue, waits on the link's clock, callbacks)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from companion.clock import Clock, SystemClock
from companion.control.types import VelocityCommand
from companion.errors import InputError, LinkError
from drivers.mavlink.link_config import LinkConfig
from drivers.mavlink.link_status import LinkStats
from drivers.mavlink.profiles import AutopilotProfile, profile_named
from drivers.mavlink.sendqueue import Priority, QueuedFrame, SendQueue
from drivers.mavlink.state import ImuSample, StateTracker, VehicleState
from drivers.mavlink.timesync import TimeSync
from drivers.mavlink.tlog import TlogWriter
from drivers.mavlink.transport import Transport, make_transport
from drivers.mavlink.url import parse_url
from drivers.mavlink.wire import Encoder, FrameParser

__all__ = ["LinkCore", "log"]

# One logger for the whole link, whichever of its modules logs (the name the daemon's log shows).
log = logging.getLogger("drivers.mavlink.link")


class LinkCore:
    """Shared state and helpers of `MavLink`; its other parts are mixins built on this class."""

    def __init__(
        self,
        config: LinkConfig,
        clock: Clock | None = None,
        tlog_path: str | Path | None = None,
        wall_time_s: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self._clock: Clock = clock if clock is not None else SystemClock()
        self._start_s = self._clock.now()
        self._forced_profile = profile_named(config.autopilot_profile) if config.autopilot_profile else None
        self._timesync = TimeSync()
        self._tracker = StateTracker(
            system_id=config.system_id,
            origin_deg=config.origin,
            timesync=self._timesync,
            forced_profile=self._forced_profile,
        )
        self._encoder = Encoder(config.system_id or 1, config.component_id)
        self._component_encoders: dict[int, Encoder] = {}  # other components of ours (the camera, send_as)
        self._parser = FrameParser(accept_mavlink1=config.accept_mavlink1)
        self._transport: Transport = make_transport(parse_url(config.url))
        self._forwards: list[tuple[Transport, FrameParser]] = [
            (make_transport(parse_url(url)), FrameParser(config.accept_mavlink1)) for url in config.forward_urls
        ]
        self._queue = SendQueue()
        self._wall_time_s = wall_time_s
        self._tlog = TlogWriter(tlog_path, wall_time_s) if tlog_path is not None else None
        self._counts: dict[str, int] = {name: 0 for name in LinkStats.__dataclass_fields__}
        self._imu_callbacks: list[Callable[[ImuSample], object]] = []
        self._message_callbacks: list[Callable[[Any], object]] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._lost = asyncio.Event()
        self._autopilot_seen = asyncio.Event()
        self._setpoint_wake = asyncio.Event()
        self._autopilot_present = False
        self._last_reconnect_s = self._start_s
        self._silent_reconnects = 0
        self._pending_acks: dict[int, asyncio.Future[int]] = {}
        self._command_locks: dict[int, asyncio.Lock] = {}
        self._velocity_cmd: VelocityCommand | None = None
        self._last_pose_stamp_s: float | None = None
        self._pose_base: str | None = None
        self._autopilot_since_s: float | None = None
        self._last_autopilot_rx_s: float | None = None
        self._statustext_id = 0
        self._interval_task: asyncio.Task[None] | None = None
        self._warned_mavlink1 = False
        self._open = False

    @property
    def state(self) -> VehicleState:
        """Frozen snapshot of the vehicle as last reported (SI units)."""
        return self._tracker.snapshot()

    @property
    def profile(self) -> AutopilotProfile | None:
        """The autopilot profile in use (forced by config or detected), None before detection."""
        return self._tracker.profile

    # ================================================================ internals
    def _require_profile(self) -> AutopilotProfile:
        profile = self._tracker.profile
        if profile is None:
            raise LinkError("autopilot type unknown (no ArduPilot/PX4 heartbeat yet and no profile configured)")
        return profile

    def _boot_ms(self) -> int:
        return max(0, int((self._clock.now() - self._start_s) * 1000.0))

    def _enqueue(
        self, data: bytes, priority: Priority, expires_s: float | None = None, *, to_gcs: bool = False
    ) -> None:
        self._queue.put(QueuedFrame(data, priority, self._clock.now(), expires_s, True, to_gcs))

    async def _wait_future(self, fut: asyncio.Future[Any], timeout_s: float) -> bool:
        """True if ``fut`` completed within ``timeout_s`` of the link's clock."""
        if fut.done():
            return True
        sleeper = asyncio.ensure_future(self._clock.sleep(timeout_s))
        try:
            await asyncio.wait({fut, sleeper}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            sleeper.cancel()
        return fut.done() and not fut.cancelled()

    async def _wait_event(self, event: asyncio.Event, timeout_s: float) -> bool:
        waiter = asyncio.ensure_future(event.wait())
        try:
            return await self._wait_future(waiter, timeout_s)
        finally:
            waiter.cancel()

    def _call(self, callback: Callable[[Any], Any], arg: Any) -> None:
        try:
            result = callback(arg)
            if isinstance(result, Awaitable):
                raise InputError("link callbacks must be plain functions, not coroutines")
        except Exception:
            self._counts["callback_errors"] += 1
            n = self._counts["callback_errors"]
            if n <= 10 or n % 1000 == 0:  # rate-limited: the count is in `stats`
                log.exception("link callback %r failed (%d callback errors so far)", callback, n)
