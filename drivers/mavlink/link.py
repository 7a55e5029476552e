"""The MAVLink link: one async object that owns the transport and every task that talks on it.

Tasks (all started by ``async with MavLink(...)``, all on the injected clock):

- connection: opens the transport, re-opens it with exponential backoff when it dies or when
  the autopilot falls silent for ``autopilot_timeout_s``;
- writer: the only task that writes; drains a bounded priority queue (CONTROL > SETPOINT > POSE);
- heartbeat (1 Hz, MAV_TYPE_ONBOARD_CONTROLLER), timesync requests, EKF origin until confirmed,
  message-interval requests whenever the autopilot (re)appears, velocity setpoint stream;
- the reader is the transport's callback: bytes -> `FrameParser` -> `StateTracker` + callbacks.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import math
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType, TracebackType
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.clock import Clock, SystemClock
from companion.control.types import VelocityCommand
from companion.errors import CommandDenied, CommandTimeout, ConfigError, InputError, LinkError
from companion.geometry import frames
from drivers.mavlink.profiles import AutopilotProfile, profile_named
from drivers.mavlink.sendqueue import Priority, QueuedFrame, SendQueue
from drivers.mavlink.state import ImuSample, PoseOut, StateTracker, VehicleState
from drivers.mavlink.timesync import TimeSync
from drivers.mavlink.tlog import TlogWriter
from drivers.mavlink.transport import Transport, make_transport
from drivers.mavlink.url import parse_url
from drivers.mavlink.wire import Encoder, FrameParser, usec_from_s

__all__ = ["SEVERITY", "LinkConfig", "LinkHealth", "LinkStats", "MavLink"]

log = logging.getLogger(__name__)

SEVERITY: Mapping[str, int] = MappingProxyType(
    {
        "emergency": 0,
        "alert": 1,
        "critical": 2,
        "error": 3,
        "warning": 4,
        "notice": 5,
        "info": 6,
        "debug": 7,
    }
)

DEFAULT_MESSAGE_RATES_HZ: Mapping[str, float] = MappingProxyType(
    {
        "ATTITUDE": 50.0,
        "LOCAL_POSITION_NED": 30.0,
        "SYS_STATUS": 2.0,
        "BATTERY_STATUS": 2.0,
        "DISTANCE_SENSOR": 20.0,
        "HIGHRES_IMU": 100.0,
        "EKF_STATUS_REPORT": 2.0,
        "EXTENDED_SYS_STATE": 2.0,
    }
)

# If the autopilot refuses a stream, ask for these instead (same information, other message).
_INTERVAL_FALLBACKS: Mapping[str, tuple[str, ...]] = MappingProxyType({"HIGHRES_IMU": ("SCALED_IMU",)})

POSE_STAMP_BASES = ("auto", "autopilot", "local")

MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
FORCE_DISARM_MAGIC = 21196.0


@dataclass(frozen=True)
class LinkConfig:
    """Configuration of the link (times in seconds, rates in Hz).

    ``system_id`` None = use the autopilot's system id (the MAVLink rule for a companion);
    ``autopilot_profile`` None = detect ArduPilot/PX4 from the heartbeat. ``origin_*`` (degrees,
    metres AMSL) enable SET_GPS_GLOBAL_ORIGIN. ``pose_message`` is "vision" (VISION_POSITION_ESTIMATE
    + VISION_SPEED_ESTIMATE), "odometry", or "auto" (ODOMETRY for PX4,
    "vision" otherwise). ``message_rates_hz`` maps message names to requested
    rates; ``request_sim_state`` adds SIM_STATE (simulator truth). ``forward_urls``: GCS endpoints
    that get every autopilot frame and whose frames go to the autopilot.

    ``pose_stamp_base``: time base of the pose ``usec`` field. "autopilot": the capture time
    converted to the autopilot's clock once TIMESYNC converged (ours if it never answers).
    "local": always our monotonic capture time. "auto" (default): "local" when the autopilot is PX4,
    "autopilot" otherwise (ArduPilot, unknown), decided once the autopilot's profile is known (forced
    by ``autopilot_profile`` or detected from its heartbeat). PX4 wants "local": its receiver
    (``MavlinkReceiver::handle_message_vision_position_estimate``) passes ``usec`` through
    ``Timesync::sync_stamp``, which adds its *own* TIMESYNC offset (from the requests we answer) once
    converged and uses the arrival time before, so an already converted stamp is shifted twice.
    ArduPilot accepts either (it estimates the offset of the stamps itself).
    """

    url: str
    component_id: int = 197
    system_id: int | None = None
    autopilot_profile: str | None = None
    heartbeat_period_s: float = 1.0
    timesync_period_s: float = 1.0
    timesync_fallback_s: float = 3.0
    autopilot_timeout_s: float = 1.5
    reconnect_initial_s: float = 0.1
    reconnect_max_s: float = 2.0
    command_timeout_s: float = 1.0
    command_retries: int = 3
    message_rates_hz: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_MESSAGE_RATES_HZ))
    request_sim_state: bool = False
    sim_state_rate_hz: float = 50.0
    origin_lat_deg: float | None = None
    origin_lon_deg: float | None = None
    origin_alt_m: float | None = None
    origin_period_s: float = 1.0
    pose_message: str = "vision"
    send_vision_speed: bool = True
    pose_max_age_s: float = 0.5
    pose_stamp_base: str = "auto"
    setpoint_rate_hz: float = 20.0
    forward_urls: tuple[str, ...] = ()
    accept_mavlink1: bool = False

    def __post_init__(self) -> None:
        parse_url(self.url)
        for url in self.forward_urls:
            parse_url(url)
        if not 1 <= self.component_id <= 255:
            raise ConfigError(f"link.component_id must be in [1, 255], got {self.component_id}")
        if self.system_id is not None and not 1 <= self.system_id <= 255:
            raise ConfigError(f"link.system_id must be in [1, 255], got {self.system_id}")
        if self.autopilot_profile is not None:
            try:
                profile_named(self.autopilot_profile)
            except InputError as exc:
                raise ConfigError(f"link.autopilot_profile: {exc}") from None
        if self.pose_stamp_base not in POSE_STAMP_BASES:
            raise ConfigError(
                f"link.pose_stamp_base must be one of {', '.join(POSE_STAMP_BASES)}, got {self.pose_stamp_base!r}"
            )
        if self.pose_message not in ("vision", "odometry", "auto"):
            raise ConfigError(f"link.pose_message must be 'vision', 'odometry' or 'auto', got {self.pose_message!r}")
        if self.setpoint_rate_hz < 10.0:
            raise ConfigError(f"link.setpoint_rate_hz must be >= 10, got {self.setpoint_rate_hz}")
        for name in ("heartbeat_period_s", "autopilot_timeout_s", "command_timeout_s", "origin_period_s"):
            if not getattr(self, name) > 0.0:
                raise ConfigError(f"link.{name} must be > 0")
        if self.command_retries < 0:
            raise ConfigError("link.command_retries must be >= 0")
        origin = (self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m)
        if any(v is None for v in origin) and any(v is not None for v in origin):
            raise ConfigError("link.origin_lat_deg/origin_lon_deg/origin_alt_m must be given together")
        for name in self.message_rates_hz:
            if not hasattr(mavlink, f"MAVLINK_MSG_ID_{name}"):
                raise ConfigError(f"link.message_rates_hz: unknown message {name!r}")

    @property
    def origin(self) -> tuple[float, float, float] | None:
        if self.origin_lat_deg is None or self.origin_lon_deg is None or self.origin_alt_m is None:
            return None
        return (self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m)


class LinkHealth(enum.Enum):
    DISCONNECTED = "disconnected"  # transport not open
    CONNECTED = "connected"  # transport open, no autopilot heard yet
    AUTOPILOT_OK = "autopilot_ok"
    AUTOPILOT_LOST = "autopilot_lost"  # heard once, silent for longer than autopilot_timeout_s


@dataclass(frozen=True)
class LinkStats:
    """Counters of the link (cumulative since it was opened)."""

    bytes_in: int = 0
    bytes_out: int = 0
    messages_in: int = 0
    frames_out: int = 0
    garbage_bytes: int = 0
    bad_frames: int = 0
    unknown_messages: int = 0
    mavlink1_rejected: int = 0
    parser_errors: int = 0
    poses_sent: int = 0
    poses_rejected_stale: int = 0
    poses_held_for_timesync: int = 0
    frames_dropped_queue: int = 0
    frames_expired: int = 0
    write_failures: int = 0  # frames the transport could not take (closed, no peer yet, buffer full)
    transport_errors: int = 0  # socket errors reported by the transport (e.g. ICMP port unreachable)
    setpoints_sent: int = 0
    commands_sent: int = 0
    command_retries: int = 0
    command_timeouts: int = 0
    commands_denied: int = 0
    interval_requests_failed: int = 0
    origin_requests_sent: int = 0
    timesync_answered: int = 0
    timesync_samples: int = 0
    autopilot_lost: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    callback_errors: int = 0
    forwarded_to_gcs: int = 0
    forwarded_to_autopilot: int = 0
    tlog_records: int = 0


class MavLink:
    """Async MAVLink connection to one autopilot (see the module docstring)."""

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
    def state(self) -> VehicleState:
        """Frozen snapshot of the vehicle as last reported (SI units)."""
        return self._tracker.snapshot()

    @property
    def profile(self) -> AutopilotProfile | None:
        """The autopilot profile in use (forced by config or detected), None before detection."""
        return self._tracker.profile

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

    # ---------------------------------------------------------------- pose
    def send_pose(self, pose: PoseOut) -> bool:
        """Encode and enqueue a new pose (never blocks); returns whether it was queued.

        Refused (False, counted): not newer than the last pose sent, older than ``pose_max_age_s``, or
        while the stamp's time base is undecided (TIMESYNC converging, at most ``timesync_fallback_s``
        after the autopilot appeared). ``usec`` on the wire is the capture time in the autopilot's
        time base (TIMESYNC), or in ours if the autopilot does not answer TIMESYNC or the config
        says ``pose_stamp_base="local"``.
        """
        now = self._clock.now()
        if (self._last_pose_stamp_s is not None and pose.stamp_s <= self._last_pose_stamp_s) or (
            now - pose.stamp_s > self.config.pose_max_age_s
        ):
            self._counts["poses_rejected_stale"] += 1
            return False
        base = self._pose_time_base(now)
        if base is None:
            self._counts["poses_held_for_timesync"] += 1
            return False
        peer_s = self._timesync.to_peer_s(pose.stamp_s) if base == "autopilot" else pose.stamp_s
        if peer_s is None:  # the autopilot's clock jumped (reboot): wait for a new offset
            self._counts["poses_held_for_timesync"] += 1
            return False
        self._last_pose_stamp_s = pose.stamp_s
        usec = usec_from_s(peer_s)
        expires = pose.stamp_s + self.config.pose_max_age_s
        if self.pose_message == "odometry":
            self._enqueue(self._encoder.odometry(pose, usec), Priority.POSE, expires)
        else:
            self._enqueue(self._encoder.vision_position_estimate(pose, usec), Priority.POSE, expires)
            if self.config.send_vision_speed and pose.velocity_ned_m_s is not None:
                self._enqueue(self._encoder.vision_speed_estimate(pose, usec), Priority.POSE, expires)
        self._counts["poses_sent"] += 1
        return True

    def _pose_time_base(self, now: float) -> str | None:
        """ "autopilot" once TIMESYNC converged, "local" if it did not within ``timesync_fallback_s`` of the
        autopilot appearing (or is disabled), None while undecided. Decided once: the stamps never jump.
        With ``pose_stamp_base="auto"`` a PX4 gets "local" and anything else the TIMESYNC rule; undecided
        until the autopilot is known."""
        if self._pose_base is None:
            wanted = self.config.pose_stamp_base
            if wanted == "auto":
                profile = self.profile
                if profile is None and self.state.last_autopilot_heartbeat_s is None:
                    return None
                wanted = "local" if profile is not None and profile.name == "px4" else "autopilot"
            if wanted == "local":
                self._pose_base = "local"
            elif self._timesync.converged:
                self._pose_base = "autopilot"
            elif self.config.timesync_period_s <= 0.0 or (
                self._autopilot_since_s is not None and now - self._autopilot_since_s > self.config.timesync_fallback_s
            ):
                self._pose_base = "local"
                log.warning("no TIMESYNC answer from the autopilot: pose stamps stay in the companion's time base")
        return self._pose_base

    @property
    def pose_message(self) -> str:
        """What poses go out as: "odometry" or "vision"; "auto" is ODOMETRY for PX4 (which ignores
        VISION_SPEED_ESTIMATE), VISION_POSITION/SPEED_ESTIMATE for ArduPilot and unknown autopilots."""
        kind = self.config.pose_message
        if kind == "auto":
            profile = self.profile
            return "odometry" if profile is not None and profile.name == "px4" else "vision"
        return kind

    @property
    def pose_time_base(self) -> str | None:
        """Time base of outgoing pose stamps: "autopilot" (TIMESYNC), "local", or None (not decided yet)."""
        return self._pose_base

    # ---------------------------------------------------------------- setpoints
    def set_velocity_command(self, command: VelocityCommand | None) -> None:
        """Stream ``command`` at ``setpoint_rate_hz`` from now on (None stops the stream)."""
        if command is not None and not isinstance(command, VelocityCommand):
            raise InputError(f"set_velocity_command takes a VelocityCommand or None, got {type(command).__name__}")
        self._velocity_cmd = command
        if command is not None:
            self._setpoint_wake.set()
        else:  # a setpoint still waiting for the writer must not follow a hold/land command out
            self._queue.clear(Priority.SETPOINT)

    # ---------------------------------------------------------------- commands
    async def command_long(
        self,
        command: int,
        params: tuple[float, ...] = (),
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
        done_already: Callable[[], bool] | None = None,
    ) -> None:
        """Send COMMAND_LONG and wait for its COMMAND_ACK, resending with confirmation+1 on timeout.

        Raises `CommandDenied` on a non-accepted result, `CommandTimeout` after all retries,
        `LinkError` when no autopilot is known. ``done_already``: for commands that are not idempotent
        (takeoff), a denial of a *resent* command is accepted when this says the first attempt worked
        (its ACK was lost).
        """
        target = self._tracker.autopilot_address
        if target is None:
            raise LinkError(f"command {_command_name(command)}: no autopilot on the link")
        timeout = self.config.command_timeout_s if timeout_s is None else timeout_s
        attempts = 1 + (self.config.command_retries if retries is None else retries)
        lock = self._command_locks.setdefault(command, asyncio.Lock())
        async with lock:
            loop = asyncio.get_running_loop()
            for attempt in range(attempts):
                fut: asyncio.Future[int] = loop.create_future()
                self._pending_acks[command] = fut
                try:
                    self._enqueue(self._encoder.command_long(target, command, params, attempt), Priority.CONTROL)
                    self._counts["commands_sent"] += 1
                    if attempt:
                        self._counts["command_retries"] += 1
                    result = await self._await_ack(command, fut, timeout)
                finally:
                    if self._pending_acks.get(command) is fut:
                        del self._pending_acks[command]
                if result is None:
                    continue
                if result == MAV_RESULT_ACCEPTED:
                    return
                if attempt > 0 and done_already is not None and done_already():
                    log.info("%s denied on retry but already done (first ACK lost)", _command_name(command))
                    return
                self._counts["commands_denied"] += 1
                raise CommandDenied(f"{_command_name(command)} {params}: {_result_name(result)}")
            self._counts["command_timeouts"] += 1
            raise CommandTimeout(f"{_command_name(command)}: no COMMAND_ACK after {attempts} attempts of {timeout} s")

    async def _await_ack(self, command: int, fut: asyncio.Future[int], timeout_s: float) -> int | None:
        while True:
            if not await self._wait_future(fut, timeout_s):
                return None
            result = fut.result()
            if result != MAV_RESULT_IN_PROGRESS:
                return result
            fut = asyncio.get_running_loop().create_future()  # keep waiting for the final ACK
            self._pending_acks[command] = fut

    async def arm(self) -> None:
        await self.command_long(MAV_CMD_COMPONENT_ARM_DISARM, (1.0,))

    async def disarm(self, force: bool = False) -> None:
        await self.command_long(MAV_CMD_COMPONENT_ARM_DISARM, (0.0, FORCE_DISARM_MAGIC if force else 0.0))

    async def set_mode(self, name: str) -> None:
        """Change flight mode by name through the autopilot profile (e.g. "GUIDED", "AUTO.LAND")."""
        profile = self._require_profile()
        await self.command_long(MAV_CMD_DO_SET_MODE, profile.set_mode_params(name))

    async def hold(self) -> None:
        """Stop the setpoint stream and switch to the profile's hold mode (ArduPilot BRAKE, PX4 AUTO.LOITER)."""
        self.set_velocity_command(None)
        await self.set_mode(self._require_profile().hold_mode)

    async def land(self) -> None:
        """Stop the setpoint stream and switch to the profile's land mode."""
        self.set_velocity_command(None)
        await self.set_mode(self._require_profile().land_mode)

    async def takeoff(self, height_m: float) -> None:
        """Climb to ``height_m`` above the take-off point (ArduPilot: enters GUIDED first; vehicle must be armed)."""
        profile = self._require_profile()
        if profile.takeoff_mode is not None and self.state.mode != profile.takeoff_mode:
            await self.set_mode(profile.takeoff_mode)
        origin_alt = self.state.ekf_origin_alt_m
        if origin_alt is None and self.config.origin is not None:
            origin_alt = self.config.origin[2]
        param7 = profile.takeoff_param7(height_m, origin_alt)
        await self.command_long(
            MAV_CMD_NAV_TAKEOFF,
            (0.0, 0.0, 0.0, math.nan, math.nan, math.nan, param7),
            done_already=lambda: self.state.landed_state in ("takeoff", "in_air"),
        )

    async def set_message_interval(self, message_name: str, rate_hz: float) -> None:
        """Ask the autopilot to stream ``message_name`` at ``rate_hz`` (0 stops it)."""
        msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{message_name}", None)
        if msg_id is None:
            raise InputError(f"unknown MAVLink message {message_name!r}")
        interval_us = -1.0 if rate_hz <= 0.0 else 1e6 / rate_hz
        await self.command_long(MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), interval_us))

    # ---------------------------------------------------------------- ground station
    def statustext(self, text: str, severity: int | str = "info") -> None:
        """Send a STATUSTEXT (chunked with id/chunk_seq when longer than 50 bytes)."""
        if isinstance(severity, str):
            if severity.lower() not in SEVERITY:
                raise InputError(f"unknown severity {severity!r}; one of {', '.join(SEVERITY)}")
            severity = SEVERITY[severity.lower()]
        if not 0 <= int(severity) <= 7:
            raise InputError(f"severity must be in [0, 7], got {severity}")
        self._statustext_id = self._statustext_id % 65535 + 1
        for frame in self._encoder.statustext(text, int(severity), self._statustext_id):
            self._enqueue(frame, Priority.CONTROL, to_gcs=True)

    def send_as(self, component_id: int, build: Callable[[Any], Any]) -> None:
        """Send one message as another component of our system (e.g. MAV_COMP_ID_CAMERA), to the autopilot and
        the GCS forwards. `build(mav)` returns the pymavlink message (``mav.heartbeat_encode(...)``)."""
        enc = self._component_encoders.get(component_id)
        if enc is None:
            enc = self._component_encoders[component_id] = Encoder(self._encoder.system_id, component_id)
        enc.system_id = self._encoder.system_id  # follows the autopilot's system id once heard
        self._enqueue(enc.pack(build(enc.mav)), Priority.CONTROL, to_gcs=True)

    def named_value_float(self, name: str, value: float) -> None:
        """Send NAMED_VALUE_FLOAT (name cut to 10 ASCII characters)."""
        self._enqueue(self._encoder.named_value_float(self._boot_ms(), name, value), Priority.CONTROL, to_gcs=True)

    def camera_image_captured(
        self,
        image_index: int,
        file_url: str = "",
        *,
        success: bool = True,
        time_utc_s: float | None = None,
        R_ned_cam: Any = None,
        lat_deg: float | None = None,
        lon_deg: float | None = None,
        alt_m: float | None = None,
        relative_alt_m: float | None = None,
    ) -> None:
        """Announce a photo (CAMERA_IMAGE_CAPTURED); orientation/position are optional (zeros/identity if unknown)."""
        q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        if R_ned_cam is not None:
            w, x, y, z = (float(v) for v in frames.quaternion_wxyz_from_rotation(R_ned_cam))
            q = (w, x, y, z)
        frame = self._encoder.camera_image_captured(
            self._boot_ms(),
            usec_from_s(self._wall_time_s() if time_utc_s is None else time_utc_s),
            int(image_index),
            file_url,
            success,
            q,
            round((lat_deg or 0.0) * 1e7),
            round((lon_deg or 0.0) * 1e7),
            round((alt_m or 0.0) * 1e3),
            round((relative_alt_m or 0.0) * 1e3),
        )
        self._enqueue(frame, Priority.CONTROL, to_gcs=True)

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

    # ---------------------------------------------------------------- connection
    async def _open_transport(self) -> None:
        self._lost.clear()
        await self._transport.open(self._receive, self._on_lost)

    def _on_lost(self, exc: BaseException | None) -> None:
        if exc is not None:
            log.warning("mavlink transport %s lost: %s", self.config.url, exc)
        self._lost.set()

    async def _connection_loop(self) -> None:
        backoff = self.config.reconnect_initial_s
        while True:
            if not self._transport.is_open:
                try:
                    await self._open_transport()
                    backoff = self.config.reconnect_initial_s
                except (LinkError, OSError) as exc:
                    self._counts["connect_failures"] += 1
                    log.debug("mavlink connect %s failed: %s", self.config.url, exc)
                    await self._clock.sleep(backoff)
                    backoff = min(2.0 * backoff, self.config.reconnect_max_s)
                    continue
            await self._lost.wait()
            self._lost.clear()
            await self._transport.close()
            self._counts["reconnects"] += 1
            self._last_reconnect_s = self._clock.now()
            self._queue.clear(Priority.POSE)
            self._queue.clear(Priority.SETPOINT)
            await self._clock.sleep(backoff)
            backoff = min(2.0 * backoff, self.config.reconnect_max_s)

    async def _watchdog_loop(self) -> None:
        period = min(0.25, self.config.autopilot_timeout_s / 4.0)
        while True:
            await self._clock.sleep(period)
            last = self._last_autopilot_rx_s  # any message counts: a lost heartbeat or two is not silence
            if last is None:
                continue
            now = self._clock.now()
            if self._autopilot_present and now - last > self.config.autopilot_timeout_s:
                self._autopilot_present = False
                self._counts["autopilot_lost"] += 1
                log.warning("autopilot silent for %.2f s on %s: reconnecting", now - last, self.config.url)
                self._silent_reconnects = 0
                self._lost.set()
            elif not self._autopilot_present:
                factor = 2.0 ** min(self._silent_reconnects + 1, 3)
                if now - max(last, self._last_reconnect_s) > factor * self.config.autopilot_timeout_s:
                    self._silent_reconnects += 1
                    self._lost.set()

    # ---------------------------------------------------------------- writer
    async def _writer_loop(self) -> None:
        queue = self._queue
        while True:
            await queue.wait()
            while (item := queue.pop()) is not None:
                if item.expires_s is not None and self._clock.now() > item.expires_s:
                    self._counts["frames_expired"] += 1
                    continue
                try:
                    self._write_now(item.data, item.to_gcs)
                except Exception:  # the only writer: one bad write must not silence the link for good
                    self._counts["write_failures"] += 1
                    log.exception("mavlink writer: writing a frame failed")

    def _write_now(self, data: bytes, to_gcs: bool) -> None:
        if self._transport.write(data):
            self._counts["frames_out"] += 1
        else:
            self._counts["write_failures"] += 1
        if to_gcs:
            for t, _ in self._forwards:
                t.write(data)
        if self._tlog is not None:
            self._tlog.write(data)

    # ---------------------------------------------------------------- periodic senders
    async def _heartbeat_loop(self) -> None:
        while True:
            self._enqueue(self._encoder.heartbeat(), Priority.CONTROL, to_gcs=True)
            await self._clock.sleep(self.config.heartbeat_period_s)

    async def _timesync_loop(self) -> None:
        if self.config.timesync_period_s <= 0.0:
            return
        while True:
            if self._autopilot_present:
                ts1 = self._timesync.request_ns(self._clock.now())
                self._enqueue(self._encoder.timesync(0, ts1), Priority.CONTROL)
            # Fast requests until converged, so poses can start in the autopilot's time base quickly.
            fast = not self._timesync.converged
            await self._clock.sleep(min(0.1, self.config.timesync_period_s) if fast else self.config.timesync_period_s)

    async def _origin_loop(self) -> None:
        origin = self.config.origin
        if origin is None:
            return
        while True:
            address = self._tracker.autopilot_address
            if self._autopilot_present and address is not None and not self.state.ekf_origin_set:
                self._enqueue(self._encoder.set_gps_global_origin(address[0], *origin), Priority.CONTROL)
                self._counts["origin_requests_sent"] += 1
            await self._clock.sleep(self.config.origin_period_s)

    async def _setpoint_loop(self) -> None:
        period = 1.0 / self.config.setpoint_rate_hz
        while True:
            cmd = self._velocity_cmd
            target = self._tracker.autopilot_address
            if cmd is None or target is None or not self._autopilot_present:
                # Nothing to fly, or the autopilot went silent: never stream blind (resumes on its heartbeat).
                self._setpoint_wake.clear()
                await self._setpoint_wake.wait()
                continue
            frame = self._encoder.velocity_setpoint(
                target,
                self._boot_ms(),
                cmd.vx_m_s,
                cmd.vy_m_s,
                cmd.vz_m_s,
                cmd.yaw_rate_rad_s,
                body_frame=getattr(cmd, "frame", "ned") == "body",
            )
            self._enqueue(frame, Priority.SETPOINT, self._clock.now() + period)
            self._counts["setpoints_sent"] += 1
            await self._clock.sleep(period)

    async def _request_intervals(self) -> None:
        rates = dict(self.config.message_rates_hz)
        if self.config.request_sim_state:
            rates["SIM_STATE"] = self.config.sim_state_rate_hz
        for name, rate_hz in rates.items():
            for candidate in (name, *_INTERVAL_FALLBACKS.get(name, ())):
                try:
                    await self.set_message_interval(candidate, rate_hz)
                    break
                except LinkError as exc:
                    self._counts["interval_requests_failed"] += 1
                    log.info("message interval %s @ %.1f Hz not set: %s", candidate, rate_hz, exc)

    # ---------------------------------------------------------------- reader
    def _receive(self, data: bytes) -> None:
        now = self._clock.now()
        msgs = self._parser.feed(data, datagram=self._transport.datagram)
        if not self._warned_mavlink1 and self._parser.counters.mavlink1_rejected:
            self._warned_mavlink1 = True  # a misconfigured port looks like a dead link otherwise
            log.warning(
                "MAVLink 1 frames on %s are ignored: configure the autopilot port for MAVLink 2 "
                "(ArduPilot SERIALn_PROTOCOL=2) or set accept_mavlink1",
                self.config.url,
            )
        from_autopilot = False
        for msg in msgs:
            if self._tlog is not None:
                self._tlog.write(bytes(msg.get_msgbuf()))
            if self._forwards:
                frame = bytes(msg.get_msgbuf())
                for t, _ in self._forwards:
                    if t.write(frame):
                        self._counts["forwarded_to_gcs"] += 1
            self._handle(msg, now)
            from_autopilot = from_autopilot or self._tracker.autopilot_address == (
                msg.get_srcSystem(),
                msg.get_srcComponent(),
            )
        if from_autopilot:  # udpin answers the autopilot's address; another sender cannot take the link
            self._transport.accept_last_source()

    def _forward_receiver(self, transport: Transport, parser: FrameParser) -> Callable[[bytes], None]:
        def receive(data: bytes) -> None:
            now = self._clock.now()
            msgs = parser.feed(data, datagram=transport.datagram)
            if msgs:
                transport.accept_last_source()
            for msg in msgs:
                frame = bytes(msg.get_msgbuf())
                self._enqueue(frame, Priority.CONTROL)
                self._counts["forwarded_to_autopilot"] += 1
                if msg.get_type() == "HEARTBEAT":
                    self._tracker.apply(msg, now)
                elif msg.get_type() == "COMMAND_LONG":  # may be for one of our components (camera discovery)
                    for mcb in list(self._message_callbacks):
                        self._call(mcb, msg)

        return receive

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        address = self._tracker.autopilot_address
        if address is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == address:
            self._last_autopilot_rx_s = now
        try:
            imu = self._tracker.apply(msg, now)
        except Exception:  # a decoder bug must not kill the reader; count and go on
            self._counts["callback_errors"] += 1
            n = self._counts["callback_errors"]
            if n <= 10 or n % 1000 == 0:
                log.exception("decoding %s failed (%d callback errors so far)", kind, n)
            imu = None
        if kind == "HEARTBEAT":
            new_address = self._tracker.autopilot_address
            if (
                new_address is not None
                and self.state.last_autopilot_heartbeat_s == now
                and (new_address[0] == msg.get_srcSystem() and new_address[1] == msg.get_srcComponent())
            ):
                self._last_autopilot_rx_s = now
                self._autopilot_heartbeat(new_address)
        elif kind == "TIMESYNC":
            self._handle_timesync(msg, now)
        elif (
            kind == "COMMAND_ACK"
            and address is not None
            and (msg.get_srcSystem(), msg.get_srcComponent()) == address
            and self._ack_is_for_us(msg)
        ):
            fut = self._pending_acks.get(int(msg.command))
            if fut is not None and not fut.done():
                fut.set_result(int(msg.result))
        if imu is not None:
            for cb in list(self._imu_callbacks):
                self._call(cb, imu)
        for mcb in list(self._message_callbacks):
            self._call(mcb, msg)

    def _ack_is_for_us(self, msg: Any) -> bool:
        """COMMAND_ACK target ids: ArduPilot and PX4 address the sender of the command; 0 = not filled in
        (older firmware). An ACK of the same command sent by a GCS (e.g. through our forwarding) is not ours."""
        target_system = int(getattr(msg, "target_system", 0) or 0)
        target_component = int(getattr(msg, "target_component", 0) or 0)
        return target_system in (0, self._encoder.system_id) and target_component in (0, self._encoder.component_id)

    def _autopilot_heartbeat(self, address: tuple[int, int]) -> None:
        if self.config.system_id is None and self._encoder.system_id != address[0]:
            self._encoder.system_id = address[0]
        self._silent_reconnects = 0
        if not self._autopilot_present:
            self._autopilot_present = True
            if self._autopilot_since_s is None:
                self._autopilot_since_s = self._clock.now()
            self._autopilot_seen.set()
            if self._interval_task is None or self._interval_task.done():
                self._interval_task = asyncio.get_running_loop().create_task(
                    self._request_intervals(), name="mavlink-intervals"
                )
            if self._velocity_cmd is not None:
                self._setpoint_wake.set()

    def _handle_timesync(self, msg: Any, now: float) -> None:
        if msg.tc1 == 0:
            self._enqueue(self._encoder.timesync(max(1, round(now * 1e9)), msg.ts1), Priority.CONTROL)
            self._counts["timesync_answered"] += 1
        elif (msg.get_srcSystem(), msg.get_srcComponent()) == self._tracker.autopilot_address:
            self._timesync.add_response(int(msg.tc1), int(msg.ts1), now)

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


def _command_name(command: int) -> str:
    entry = mavlink.enums.get("MAV_CMD", {}).get(command)
    return entry.name if entry is not None else f"MAV_CMD({command})"


def _result_name(result: int) -> str:
    entry = mavlink.enums.get("MAV_RESULT", {}).get(result)
    return entry.name if entry is not None else f"MAV_RESULT({result})"
