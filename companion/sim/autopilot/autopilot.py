"""The fake autopilot: a real MAVLink 2 endpoint on a UDP/TCP socket, ArduCopter-like or PX4-like.

It steps the true vehicle (`vehicle.py`) at a fixed rate on an injected clock,
runs the flight logic (`flight.py`), answers commands, consumes vision poses and
setpoints, publishes telemetry at the requested rates, applies scripted faults
(`faults.py`) and records every message it receives.

Time: everything runs on the `Clock` given to the constructor. With a
`ManualClock` the physics advances in exact steps of ``1 / physics_rate_hz``
up to the clock's time whenever the clock wakes it or a message arrives, so a
test is deterministic and as fast as the CPU; with `SystemClock` it runs in real
time. Autopilot timestamps (`time_boot_ms`, `time_usec`, TIMESYNC) count from
the moment `start()` ran; fault times `at_s` count from there too.
"""

from __future__ import annotations

import asyncio
import contextlib
from types import TracebackType

import numpy as np

from companion.errors import ConfigError, InputError
from companion.sim.autopilot.commands import Commands
from companion.sim.autopilot.config import (
    DEFAULT_RATES_HZ,
    FakeAutopilotConfig,
    ImuNoise,
    ReceivedMessage,
    Stream,
    Truth,
)
from companion.sim.autopilot.faults import Fault
from companion.sim.autopilot.transport import open_transport

TIMESYNC_PERIOD_S = 10.0  # ArduCopter SITL: a TIMESYNC request every 10.0 s

__all__ = ["DEFAULT_RATES_HZ", "FakeAutopilot", "FakeAutopilotConfig", "ImuNoise", "ReceivedMessage", "Truth"]


class FakeAutopilot(Commands):
    """A simulated ArduCopter/PX4 behind a real MAVLink socket (async context manager)."""

    # ----- lifecycle -------------------------------------------------------------------------

    async def __aenter__(self) -> FakeAutopilot:
        await self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def start(self) -> None:
        """Bind the socket and start the simulation task."""
        if self._started:
            return
        self._record_event = asyncio.Event()
        self._wake = asyncio.Event()
        self._transport = open_transport(self.config.listen, self._on_bytes)
        await self._transport.start()
        self._boot_s = self.clock.now()
        self._phys_t = self._boot_s
        rates = dict(DEFAULT_RATES_HZ[self.profile.name])
        rates.update(self.config.rates_hz or {})
        self._streams = {name: Stream(self._interval(hz), self._boot_s) for name, hz in rates.items()}
        self._streams["HEARTBEAT"] = Stream(1.0, self._boot_s)
        self._gcs_next_s = self._boot_s
        self._timesync_next_s = self._boot_s + TIMESYNC_PERIOD_S
        self._started = True
        self._task = asyncio.create_task(self._run(), name="fake-autopilot")

    async def close(self) -> None:
        """Stop the simulation and close the socket."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        for task in list(self._pending):
            task.cancel()
        for task in list(self._pending):
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self._transport is not None:
            await self._transport.close()
            self._transport = None
        self._started = False

    # ----- public state ----------------------------------------------------------------------

    @property
    def url_for_client(self) -> str:
        """The URL a client connects with (``udpout:127.0.0.1:PORT`` or ``tcp:127.0.0.1:PORT``)."""
        if self._transport is None:
            raise ConfigError("FakeAutopilot is not started")
        return self._transport.url_for_client

    @property
    def mode(self) -> str:
        """Current flight-mode name (e.g. "GUIDED", "AUTO.LOITER")."""
        return self._flight.mode.name

    @property
    def armed(self) -> bool:
        return self._flight.armed

    @property
    def elapsed_s(self) -> float:
        """Seconds since `start()` (the autopilot's boot time), on its clock."""
        return self.clock.now() - self._boot_s

    @property
    def ekf_healthy(self) -> bool:
        """Whether the EKF has a usable position estimate now."""
        return self._flight.ekf_healthy(self.clock.now())

    @property
    def ready_to_arm(self) -> bool:
        """Whether the pre-arm checks pass now (what SYS_STATUS's PREARM_CHECK health bit reports): with
        `require_vision`, ArduPilot needs `ekf_alignment_s` of vision and a home (an origin)."""
        if self._started:
            self._advance_physics(self.clock.now())
        return not self._flight.prearm_failures(self.clock.now(), self._vehicle)

    @property
    def origin_lla(self) -> tuple[float, float, float] | None:
        """The EKF origin (lat deg, lon deg, alt m) once set."""
        return self._origin

    @property
    def landed_state(self) -> int:
        """MAV_LANDED_STATE now."""
        return self._flight.landed_state(self._vehicle, self.clock.now())

    @property
    def truth(self) -> Truth:
        """The true vehicle state (physics advanced to the clock's time)."""
        if self._started:
            self._advance_physics(self.clock.now())
        v = self._vehicle
        return Truth(
            stamp_s=self._phys_t,
            T_ned_body=v.T_ned_body(),
            velocity_ned_m_s=np.array(v.velocity_ned_m_s),
            accel_ned_m_s2=np.array(v.accel_ned_m_s2),
            rates_body_rad_s=np.array(v.rates_body_rad_s),
            wind_ned_m_s=np.array(self._wind_ned),
            on_ground=v.on_ground,
            battery_voltage_v=self._battery_voltage(),
            battery_remaining_pct=self._battery_remaining_pct(),
            battery_current_a=self._battery.current_a,
        )

    @property
    def received(self) -> list[ReceivedMessage]:
        """Every message received so far (after link faults), oldest first."""
        return self._records

    def received_of(self, *types: str) -> list[ReceivedMessage]:
        """The received messages of the given type names (e.g. "VISION_POSITION_ESTIMATE")."""
        wanted = {t.upper() for t in types}
        return [r for r in self._records if r.type in wanted]

    async def wait_received(self, msg_type: str, count: int = 1) -> ReceivedMessage:
        """Wait until at least `count` messages of `msg_type` were received; return the latest.

        Wrap in `asyncio.wait_for` for a timeout (with a ManualClock, advance the clock instead).
        """
        while True:
            found = self.received_of(msg_type)
            if len(found) >= count:
                return found[-1]
            self._record_event.clear()
            await self._record_event.wait()

    def schedule(self, fault: Fault) -> None:
        """Add a fault (its `at_s` counts from the autopilot's start)."""
        if not isinstance(fault, Fault):
            raise InputError(f"schedule() takes a Fault, got {type(fault).__name__}")
        self._faults.append(fault)

    @property
    def faults(self) -> tuple[Fault, ...]:
        return tuple(self._faults)

    def stream_rate_hz(self, msg_type: str) -> float:
        """Current stream rate of a telemetry message (0 = off)."""
        stream = self._streams.get(msg_type.upper())
        return 0.0 if stream is None or stream.interval_s <= 0.0 else 1.0 / stream.interval_s

    # ----- the main loop ---------------------------------------------------------------------

    async def _run(self) -> None:
        while True:
            now = self.clock.now()
            self._advance_physics(now)
            self._check_home(now)
            self._flush_events()
            next_wake = now + 0.05
            for name, stream in self._streams.items():
                if stream.interval_s <= 0.0:
                    continue
                if stream.next_due_s <= now + 1e-9:
                    self._send_stream(name, now)
                    stream.next_due_s += stream.interval_s
                    if stream.next_due_s <= now:
                        stream.next_due_s = now + stream.interval_s
                next_wake = min(next_wake, stream.next_due_s)
            if self.config.gcs_heartbeat:
                if self._gcs_next_s <= now + 1e-9:
                    if not self._active("gcs-loss", now):
                        self._send_gcs_heartbeat()
                    self._gcs_next_s += 1.0
                    if self._gcs_next_s <= now:
                        self._gcs_next_s = now + 1.0
                next_wake = min(next_wake, self._gcs_next_s)
            if self.profile.name == "ardupilot":
                if self._timesync_next_s <= now + 1e-9:
                    # ArduPilot's own time-sync requests (tc1 = 0, ts1 = its time in ns), every 10 s
                    self._send(self._mav.timesync_encode(0, round((now - self._boot_s) * 1e9)))
                    self._timesync_next_s = max(self._timesync_next_s + TIMESYNC_PERIOD_S, now)
                next_wake = min(next_wake, self._timesync_next_s)
            await self._sleep_or_wake(max(0.0, next_wake - now))

    async def _sleep_or_wake(self, seconds: float) -> None:
        """Sleep on the clock, but return early when a message changed the schedule."""
        if self._wake.is_set():
            self._wake.clear()
            return
        sleeper = asyncio.ensure_future(self.clock.sleep(seconds))
        waker = asyncio.ensure_future(self._wake.wait())
        try:
            await asyncio.wait((sleeper, waker), return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (sleeper, waker):
                if not task.done():
                    task.cancel()
            self._wake.clear()
