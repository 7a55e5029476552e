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
import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import TracebackType
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.checks import FloatArray
from companion.clock import Clock, SystemClock
from companion.errors import ConfigError, InputError
from companion.geometry import frames
from companion.sim.autopilot.battery import (
    BatteryParams,
    BatteryState,
    battery_current_a,
    initial_battery,
    step_battery,
)
from companion.sim.autopilot.faults import Fault, active_faults
from companion.sim.autopilot.flight import FlightLogic, FlightParams, Setpoint
from companion.sim.autopilot.profiles import Behaviour, ModeDef, Profile, profile_by_name
from companion.sim.autopilot.transport import PeerKey, ServerTransport, open_transport, parse_listen_url
from companion.sim.autopilot.vehicle import (
    VehicleParams,
    VehicleState,
    initial_vehicle,
    step_vehicle,
)
from companion.sim.autopilot.wind import DrydenConfig, DrydenWind

__all__ = ["DEFAULT_RATES_HZ", "FakeAutopilot", "FakeAutopilotConfig", "ImuNoise", "ReceivedMessage", "Truth"]

EARTH_RADIUS_M = 6378137.0

# Telemetry streamed without being asked (per profile), Hz. SET_MESSAGE_INTERVAL changes them.
DEFAULT_RATES_HZ: dict[str, dict[str, float]] = {
    "ardupilot": {
        "SYS_STATUS": 1.0,
        "BATTERY_STATUS": 1.0,
        "EXTENDED_SYS_STATE": 1.0,
        "EKF_STATUS_REPORT": 1.0,
        "ATTITUDE": 10.0,
        "LOCAL_POSITION_NED": 10.0,
        "GLOBAL_POSITION_INT": 5.0,
        "DISTANCE_SENSOR": 10.0,
        "SIM_STATE": 10.0,
        "HIGHRES_IMU": 0.0,
        "ATTITUDE_QUATERNION": 0.0,
        "GPS_GLOBAL_ORIGIN": 0.0,
        "HOME_POSITION": 0.0,
    },
    "px4": {
        "SYS_STATUS": 1.0,
        "BATTERY_STATUS": 1.0,
        "EXTENDED_SYS_STATE": 2.0,
        "EKF_STATUS_REPORT": 1.0,
        "ATTITUDE": 10.0,
        "ATTITUDE_QUATERNION": 10.0,
        "LOCAL_POSITION_NED": 10.0,
        "GLOBAL_POSITION_INT": 5.0,
        "DISTANCE_SENSOR": 10.0,
        "SIM_STATE": 10.0,
        "HIGHRES_IMU": 0.0,
        "GPS_GLOBAL_ORIGIN": 0.0,
        "HOME_POSITION": 0.5,
    },
}

_MAX_RATE_HZ = 400.0
_MAX_PARSERS = 16  # per-peer frame parsers kept (one per UDP source address / TCP client)
_ACCEPTED: int = mavlink.MAV_RESULT_ACCEPTED
_FAILED: int = mavlink.MAV_RESULT_FAILED
_FORCE_MAGIC = 21196
_GCS_SYSID, _GCS_COMPID = 255, 190
_PARAMS: dict[str, dict[str, float]] = {
    "ardupilot": {
        "GUID_TIMEOUT": 3.0,
        "FS_EKF_ACTION": 1.0,
        "DISARM_DELAY": 10.0,
        "LAND_SPEED": 50.0,
        "SYSID_THISMAV": 1.0,
    },
    "px4": {
        "MIS_TAKEOFF_ALT": 2.5,
        "COM_OF_LOSS_T": 0.5,
        "COM_DISARM_PRFLT": 10.0,
        "MPC_LAND_SPEED": 0.5,
        "MAV_SYS_ID": 1.0,
    },
}
_REJECT_RESULTS = {
    "denied": mavlink.MAV_RESULT_DENIED,
    "failed": mavlink.MAV_RESULT_FAILED,
    "temporarily_rejected": mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
}


@dataclass(frozen=True)
class ImuNoise:
    """HIGHRES_IMU noise: white noise per sample (std) and constant biases drawn once (std); rad/s, m/s²."""

    gyro_noise_rad_s: float = 0.003
    accel_noise_m_s2: float = 0.03
    gyro_bias_rad_s: float = 0.002
    accel_bias_m_s2: float = 0.04


@dataclass(frozen=True)
class FakeAutopilotConfig:
    """Settings of the fake autopilot.

    ``profile``: "ardupilot" (ArduCopter-like, default) or "px4".
    ``listen``: ``udpin:HOST:PORT`` (UDP server, port 0 = ephemeral), ``tcpin:HOST:PORT`` or ``udpout:HOST:PORT``.
    ``require_vision``: non-GPS configuration; the EKF is healthy only with a vision pose < 300 ms old.
    ``physics_rate_hz``: fixed physics step rate. ``seed``: all randomness (wind, IMU noise, faults).
    ``start_north_m, start_east_m, start_yaw_rad``: where the vehicle rests at boot (on z = 0).
    ``rates_hz``: overrides of the unrequested stream rates (message name -> Hz, 0 = off).
    ``origin_lla``: EKF origin already set at boot (lat deg, lon deg, alt m), e.g. a GPS configuration.
    ``reference_lla``: where SIM_STATE's lat/lon are computed from while no origin is set.
    ``gcs_heartbeat``: also emit GCS heartbeats (sysid 255, MAV_TYPE_GCS) at 1 Hz on the same link.
    ``max_records``: keep at most this many received-message records (oldest dropped in batches of
    1/16 of it; None = all). About 0.5 kB per record: the default holds ~100 MB in a long real-time run.
    ``ekf_position_noise_m`` / ``ekf_attitude_noise_rad``: noise on the reported (EKF) position/attitude.
    """

    profile: str = "ardupilot"
    listen: str = "udpin:127.0.0.1:0"
    system_id: int = 1
    component_id: int = 1
    require_vision: bool = True
    physics_rate_hz: float = 400.0
    seed: int = 0
    start_north_m: float = 0.0
    start_east_m: float = 0.0
    start_yaw_rad: float = 0.0
    wind: DrydenConfig = field(default_factory=DrydenConfig)
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    flight: FlightParams = field(default_factory=FlightParams)
    battery: BatteryParams = field(default_factory=BatteryParams)
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    faults: tuple[Fault, ...] = ()
    rates_hz: Mapping[str, float] | None = None
    origin_lla: tuple[float, float, float] | None = None
    reference_lla: tuple[float, float, float] = (47.397742, 8.545594, 488.0)
    gcs_heartbeat: bool = False
    rangefinder_max_m: float = 40.0
    rangefinder_noise_m: float = 0.01
    ekf_position_noise_m: float = 0.01
    ekf_attitude_noise_rad: float = 0.002
    max_records: int | None = 200_000

    def __post_init__(self) -> None:
        profile_by_name(self.profile)
        parse_listen_url(self.listen)
        if not 1 <= self.system_id <= 255 or not 0 <= self.component_id <= 255:
            raise ConfigError(f"system_id/component_id out of range: {self.system_id}/{self.component_id}")
        if not 50.0 <= self.physics_rate_hz <= 2000.0:
            raise ConfigError(f"physics_rate_hz must be in [50, 2000], got {self.physics_rate_hz}")
        if self.max_records is not None and self.max_records < 1:
            raise ConfigError(f"max_records must be >= 1 or None, got {self.max_records}")
        for name in self.rates_hz or {}:
            if name not in DEFAULT_RATES_HZ["ardupilot"]:
                raise ConfigError(f"rates_hz: cannot stream {name!r}; known: {sorted(DEFAULT_RATES_HZ['ardupilot'])}")


@dataclass(frozen=True)
class ReceivedMessage:
    """One message the fake received: clock time (s), type name, decoded fields, raw frame bytes, sender ids."""

    time_s: float
    type: str
    fields: dict[str, Any]
    raw: bytes
    src_system: int
    src_component: int


@dataclass(frozen=True)
class Truth:
    """The true vehicle state at `stamp_s` (clock time, s): pose in NED, velocity, rates, wind, battery."""

    stamp_s: float
    T_ned_body: FloatArray
    velocity_ned_m_s: FloatArray
    accel_ned_m_s2: FloatArray
    rates_body_rad_s: FloatArray
    wind_ned_m_s: FloatArray
    on_ground: bool
    battery_voltage_v: float
    battery_remaining_pct: float
    battery_current_a: float

    @property
    def position_ned_m(self) -> FloatArray:
        """Body origin in NED (m)."""
        return np.asarray(self.T_ned_body[:3, 3].copy())

    @property
    def height_m(self) -> float:
        """Height above the ground plane (m)."""
        return float(-self.T_ned_body[2, 3])


@dataclass
class _Stream:
    interval_s: float  # 0 = off
    next_due_s: float


def _msg_fields(msg: Any) -> dict[str, Any]:
    fields: dict[str, Any] = msg.to_dict()
    fields.pop("mavpackettype", None)
    return fields


class FakeAutopilot:
    """A simulated ArduCopter/PX4 behind a real MAVLink socket (async context manager)."""

    def __init__(self, config: FakeAutopilotConfig | None = None, clock: Clock | None = None) -> None:
        self.config = config if config is not None else FakeAutopilotConfig()
        self.clock: Clock = clock if clock is not None else SystemClock()
        cfg = self.config
        self.profile: Profile = profile_by_name(cfg.profile)
        self._rng = np.random.default_rng(cfg.seed)
        self._fault_rng = np.random.default_rng([cfg.seed, 1])
        self._noise_rng = np.random.default_rng([cfg.seed, 2])
        self._wind = DrydenWind(cfg.wind, np.random.default_rng([cfg.seed, 3]))
        self._flight = FlightLogic(
            self.profile, replace(cfg.flight, require_vision=cfg.require_vision), (cfg.start_north_m, cfg.start_east_m)
        )
        self._vehicle: VehicleState = initial_vehicle(cfg.start_north_m, cfg.start_east_m, cfg.start_yaw_rad)
        self._battery: BatteryState = initial_battery(cfg.battery)
        self._wind_ned: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._dt_s = 1.0 / cfg.physics_rate_hz
        self._faults: list[Fault] = list(cfg.faults)
        self._params = dict(_PARAMS[self.profile.name])
        self._mav = mavlink.MAVLink(None, srcSystem=cfg.system_id, srcComponent=cfg.component_id)
        self._gcs_mav = mavlink.MAVLink(None, srcSystem=_GCS_SYSID, srcComponent=_GCS_COMPID)
        self._parsers: dict[PeerKey, mavlink.MAVLink] = {}
        self._transport: ServerTransport | None = None
        self._task: asyncio.Task[None] | None = None
        self._pending: set[asyncio.Task[None]] = set()
        self._boot_s = 0.0
        self._phys_t = 0.0
        self._started = False
        self._origin: tuple[float, float, float] | None = cfg.origin_lla
        self._home_set = cfg.origin_lla is not None
        self._streams: dict[str, _Stream] = {}
        self._gcs_next_s = 0.0
        self._imu_f_sum = [0.0, 0.0, 0.0]
        self._imu_w_sum = [0.0, 0.0, 0.0]
        self._imu_n = 0
        s = cfg.imu_noise
        self._gyro_bias = self._noise_rng.normal(0.0, s.gyro_bias_rad_s, 3) if s.gyro_bias_rad_s > 0 else np.zeros(3)
        self._accel_bias = self._noise_rng.normal(0.0, s.accel_bias_m_s2, 3) if s.accel_bias_m_s2 > 0 else np.zeros(3)
        self._records: list[ReceivedMessage] = []
        self._record_event = asyncio.Event()
        self._wake = asyncio.Event()
        self.stats: dict[str, int] = {
            "sent": 0,
            "dropped_out": 0,
            "corrupted_out": 0,
            "received": 0,
            "dropped_in": 0,
            "parse_errors": 0,
        }

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
        self._streams = {name: _Stream(self._interval(hz), self._boot_s) for name, hz in rates.items()}
        self._streams["HEARTBEAT"] = _Stream(1.0, self._boot_s)
        self._gcs_next_s = self._boot_s
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
    def origin_lla(self) -> tuple[float, float, float] | None:
        """The EKF origin (lat deg, lon deg, alt m) once set."""
        return self._origin

    @property
    def landed_state(self) -> int:
        """MAV_LANDED_STATE now."""
        return self._flight.landed_state(self._vehicle)

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

    # ----- fault helpers ---------------------------------------------------------------------

    def _active(self, kind: str, now_s: float | None = None) -> list[Fault]:
        t = self.clock.now() if now_s is None else now_s
        return active_faults(self._faults, t - self._boot_s, kind)

    def _battery_voltage(self, now_s: float | None = None) -> float:
        voltage = self._battery.voltage_v
        cells = self.config.battery.cells
        for f in self._active("battery-sag", now_s):
            voltage = min(voltage, f.params["voltage_v"] if f.params["voltage_v"] is not None else 3.4 * cells)
        for f in self._active("battery-critical", now_s):
            voltage = min(voltage, f.params["voltage_v"] if f.params["voltage_v"] is not None else 3.3 * cells)
        return float(voltage)

    def _battery_remaining_pct(self, now_s: float | None = None) -> float:
        remaining = self._battery.remaining_pct
        for f in self._active("battery-critical", now_s):
            remaining = min(remaining, float(f.params["remaining_pct"]))
        return float(remaining)

    def _ceiling_m(self, now_s: float) -> float | None:
        found = self._active("ceiling", now_s)
        return min(float(f.params["height_m"]) for f in found) if found else None

    # ----- physics ---------------------------------------------------------------------------

    def _advance_physics(self, now_s: float) -> None:
        dt = self._dt_s
        cfg = self.config
        while self._phys_t + dt <= now_s + 1e-9:
            t = self._phys_t + dt
            self._flight.battery_critical = self._battery_remaining_pct(t) <= cfg.battery.critical_remaining_pct
            command = self._flight.update(t, self._vehicle)
            v = self._vehicle
            if not v.on_ground:
                self._wind_ned = self._wind.step(v.height_m, v.velocity_ned_m_s, dt)
            else:
                self._wind_ned = (0.0, 0.0, 0.0)
            new = step_vehicle(v, command, self._wind_ned, cfg.vehicle, dt)
            ceiling = self._ceiling_m(t)
            if ceiling is not None and new.height_m > ceiling - 0.1 and new.velocity_ned_m_s[2] < 0.0:
                pos = new.position_ned_m
                vel = new.velocity_ned_m_s
                new = replace(
                    new, position_ned_m=(pos[0], pos[1], -(ceiling - 0.1)), velocity_ned_m_s=(vel[0], vel[1], 0.0)
                )
            self._vehicle = new
            current = battery_current_a(cfg.battery, self._flight.armed, not new.on_ground, new.thrust_ratio)
            self._battery = step_battery(self._battery, cfg.battery, current, dt)
            f, w = new.specific_force_body_m_s2, new.rates_body_rad_s
            for i in range(3):
                self._imu_f_sum[i] += f[i]
                self._imu_w_sum[i] += w[i]
            self._imu_n += 1
            self._phys_t = t

    # ----- the main loop ---------------------------------------------------------------------

    @staticmethod
    def _interval(rate_hz: float) -> float:
        return 0.0 if rate_hz <= 0.0 else 1.0 / min(rate_hz, _MAX_RATE_HZ)

    async def _run(self) -> None:
        while True:
            now = self.clock.now()
            self._advance_physics(now)
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

    def _flush_events(self) -> None:
        events, self._flight.events = self._flight.events, []
        for severity, text in events:
            self._send(self._mav.statustext_encode(severity, text[:50].encode()))

    # ----- sending ---------------------------------------------------------------------------

    def _send(self, msg: Any, mav: mavlink.MAVLink | None = None) -> None:
        encoder = self._mav if mav is None else mav
        buf = msg.pack(encoder)
        encoder.seq = (encoder.seq + 1) % 256
        self._emit(bytes(buf))

    def _emit(self, buf: bytes) -> None:
        now = self.clock.now()
        if self._transport is None or self._active("link-loss", now):
            self.stats["dropped_out"] += 1
            return
        for f in self._active("message-loss", now):
            if f.params["direction"] in ("both", "out") and self._fault_rng.random() * 100.0 < float(
                f.params["percent"]
            ):
                self.stats["dropped_out"] += 1
                return
        for f in self._active("corrupt", now):
            if self._fault_rng.random() * 100.0 < float(f.params["percent"]):
                data = bytearray(buf)
                pos = int(self._fault_rng.integers(1, len(data)))
                data[pos] ^= int(self._fault_rng.integers(1, 256))
                buf = bytes(data)
                self.stats["corrupted_out"] += 1
        delay_s = sum(
            float(f.params["ms"]) / 1000.0
            for f in self._active("latency", now)
            if f.params["direction"] in ("both", "out")
        )
        if delay_s > 0.0:
            self._later(delay_s, self._transmit, buf)
        else:
            self._transmit(buf)

    def _transmit(self, buf: bytes) -> None:
        if self._transport is not None:
            self._transport.send(buf)
            self.stats["sent"] += 1

    def _later(self, delay_s: float, fn: Any, *args: Any) -> None:
        async def run() -> None:
            await self.clock.sleep(delay_s)
            fn(*args)

        task = asyncio.create_task(run())
        self._pending.add(task)
        task.add_done_callback(self._pending.discard)

    # ----- telemetry builders ----------------------------------------------------------------

    def _time_boot_ms(self, now_s: float) -> int:
        return round((now_s - self._boot_s) * 1000.0) & 0xFFFFFFFF

    def _time_usec(self, now_s: float) -> int:
        return round((now_s - self._boot_s) * 1e6)

    def _heartbeat(self) -> Any:
        flight = self._flight
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if flight.mode.behaviour in (
            Behaviour.GUIDED,
            Behaviour.OFFBOARD,
            Behaviour.TAKEOFF,
            Behaviour.RTL,
            Behaviour.LAND,
        ):
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if flight.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self._battery_remaining_pct() <= self.config.battery.critical_remaining_pct:
            status = mavlink.MAV_STATE_CRITICAL
        elif flight.armed:
            status = mavlink.MAV_STATE_ACTIVE
        else:
            status = mavlink.MAV_STATE_STANDBY
        return self._mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, self.profile.autopilot, base, flight.mode.custom_mode, status, 3
        )

    def _send_gcs_heartbeat(self) -> None:
        msg = self._gcs_mav.heartbeat_encode(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
        )
        self._send(msg, self._gcs_mav)

    def _llh(
        self, position_ned_m: tuple[float, float, float], origin: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        lat0, lon0, alt0 = origin
        lat = lat0 + math.degrees(position_ned_m[0] / EARTH_RADIUS_M)
        lon = lon0 + math.degrees(position_ned_m[1] / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return lat, lon, alt0 - position_ned_m[2]

    def _ekf_position(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        sigma = self.config.ekf_position_noise_m
        p = self._vehicle.position_ned_m
        n = self._noise_rng.normal(0.0, sigma, 3) if sigma > 0 else np.zeros(3)
        return (p[0] + n[0], p[1] + n[1], p[2] + n[2]), self._vehicle.velocity_ned_m_s

    def _send_stream(self, name: str, now_s: float) -> None:
        msg = self._build(name, now_s)
        if msg is not None:
            self._send(msg)
        if name == "DISTANCE_SENSOR":
            up = self._distance_up(now_s)
            if up is not None:
                self._send(up)

    def _build(self, name: str, now_s: float) -> Any:
        v = self._vehicle
        mav = self._mav
        t_ms = self._time_boot_ms(now_s)
        cfg = self.config
        healthy = self._flight.ekf_healthy(now_s)
        if name == "HEARTBEAT":
            return self._heartbeat()
        if name == "ATTITUDE":
            s = cfg.ekf_attitude_noise_rad
            n = self._noise_rng.normal(0.0, s, 3) if s > 0 else np.zeros(3)
            r = v.rates_body_rad_s
            yaw = math.atan2(math.sin(v.yaw_rad + n[2]), math.cos(v.yaw_rad + n[2]))
            return mav.attitude_encode(t_ms, v.roll_rad + n[0], v.pitch_rad + n[1], yaw, r[0], r[1], r[2])
        if name == "ATTITUDE_QUATERNION":
            q = frames.quaternion_wxyz_from_rotation(v.R_ned_body())
            r = v.rates_body_rad_s
            return mav.attitude_quaternion_encode(t_ms, *(float(x) for x in q), r[0], r[1], r[2], [0.0] * 4)
        if name == "LOCAL_POSITION_NED":
            if self.config.require_vision and self._flight.last_vision_s is None:
                return None  # no position source yet: ArduPilot/PX4 do not publish a local position
            p, vel = self._ekf_position()
            return mav.local_position_ned_encode(t_ms, p[0], p[1], p[2], vel[0], vel[1], vel[2])
        if name == "GLOBAL_POSITION_INT":
            if self._origin is None:
                return None
            p, vel = self._ekf_position()
            lat, lon, alt = self._llh(p, self._origin)
            hdg = int(math.degrees(v.yaw_rad) % 360.0 * 100.0)
            return mav.global_position_int_encode(
                t_ms,
                int(lat * 1e7),
                int(lon * 1e7),
                int(alt * 1000),
                int(-p[2] * 1000),
                int(vel[0] * 100),
                int(vel[1] * 100),
                int(vel[2] * 100),
                hdg,
            )
        if name == "SYS_STATUS":
            sensors = (
                mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
                | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
                | mavlink.MAV_SYS_STATUS_SENSOR_LASER_POSITION
                | mavlink.MAV_SYS_STATUS_AHRS
                | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
                | mavlink.MAV_SYS_STATUS_PREARM_CHECK
                | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            )
            if cfg.require_vision:
                sensors |= mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION
            health = sensors
            if not healthy:
                health &= ~(mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION | mavlink.MAV_SYS_STATUS_PREARM_CHECK)
            if self._battery_remaining_pct() <= cfg.battery.critical_remaining_pct:
                health &= ~mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
            return mav.sys_status_encode(
                sensors,
                sensors,
                health,
                200,
                int(self._battery_voltage() * 1000),
                int(self._battery.current_a * 100),
                int(self._battery_remaining_pct()),
                0,
                self.stats["parse_errors"] & 0xFFFF,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            )
        if name == "BATTERY_STATUS":
            voltage = self._battery_voltage()
            cells = cfg.battery.cells
            cell_mv = int(voltage / cells * 1000)
            # cells 1..10 in `voltages` (UINT16_MAX = no cell), 11..14 in `voltages_ext` (0 = no cell)
            voltages = [cell_mv] * min(cells, 10) + [65535] * max(0, 10 - cells)
            voltages_ext = [cell_mv] * max(0, cells - 10) + [0] * (4 - max(0, cells - 10))
            remaining = self._battery_remaining_pct()
            if remaining <= cfg.battery.critical_remaining_pct:
                charge_state = mavlink.MAV_BATTERY_CHARGE_STATE_CRITICAL
            elif remaining <= cfg.battery.low_remaining_pct:
                charge_state = mavlink.MAV_BATTERY_CHARGE_STATE_LOW
            else:
                charge_state = mavlink.MAV_BATTERY_CHARGE_STATE_OK
            current = self._battery.current_a
            time_remaining = (
                int(3.6 * (cfg.battery.capacity_mah - self._battery.consumed_mah) / current) if current > 0 else 0
            )
            return mav.battery_status_encode(
                0,
                mavlink.MAV_BATTERY_FUNCTION_ALL,
                mavlink.MAV_BATTERY_TYPE_LIPO,
                2500,
                voltages,
                int(current * 100),
                int(self._battery.consumed_mah),
                int(self._battery.consumed_energy_j / 100.0),
                int(remaining),
                max(0, time_remaining),
                charge_state,
                voltages_ext,
                0,
                0,
            )
        if name == "EXTENDED_SYS_STATE":
            return mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, self._flight.landed_state(v))
        if name == "EKF_STATUS_REPORT":
            if healthy:
                flags = (
                    mavlink.EKF_ATTITUDE
                    | mavlink.EKF_VELOCITY_HORIZ
                    | mavlink.EKF_VELOCITY_VERT
                    | mavlink.EKF_POS_HORIZ_REL
                    | mavlink.EKF_POS_VERT_ABS
                    | mavlink.EKF_POS_VERT_AGL
                    | mavlink.EKF_PRED_POS_HORIZ_REL
                )
                if self._origin is not None:
                    flags |= mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_PRED_POS_HORIZ_ABS
                var = 0.05
            else:
                flags = (
                    mavlink.EKF_ATTITUDE
                    | mavlink.EKF_VELOCITY_VERT
                    | mavlink.EKF_POS_VERT_ABS
                    | mavlink.EKF_CONST_POS_MODE
                )
                var = 1.2
            return mav.ekf_status_report_encode(flags, var, var, 0.05, 0.05, 0.0, 0.0)
        if name == "DISTANCE_SENSOR":
            return self._distance_down(t_ms)
        if name == "HIGHRES_IMU":
            return self._highres_imu(now_s)
        if name == "SIM_STATE":
            return self._sim_state()
        if name == "GPS_GLOBAL_ORIGIN":
            if self._origin is None:
                return None
            lat, lon, alt = self._origin
            return mav.gps_global_origin_encode(
                round(lat * 1e7), round(lon * 1e7), round(alt * 1000), self._time_usec(now_s)
            )
        if name == "HOME_POSITION":
            if self._origin is None:
                return None
            home = (self._flight.home_ne_m[0], self._flight.home_ne_m[1], 0.0)
            lat, lon, alt = self._llh(home, self._origin)
            return mav.home_position_encode(
                int(lat * 1e7),
                int(lon * 1e7),
                int(alt * 1000),
                home[0],
                home[1],
                home[2],
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
                self._time_usec(now_s),
            )
        if name == "AUTOPILOT_VERSION":
            caps = (
                mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
            )
            version = (
                (4 << 24) | (5 << 16) | (0 << 8) | 255
                if self.profile.name == "ardupilot"
                else (1 << 24) | (15 << 16) | 255
            )
            return mav.autopilot_version_encode(
                caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x5EED0000 + cfg.system_id, [0] * 18
            )
        return None

    def _distance_down(self, t_ms: int) -> Any:
        v = self._vehicle
        cfg = self.config
        tilt_cos = max(math.cos(v.roll_rad) * math.cos(v.pitch_rad), 0.2)
        slant = max(v.height_m, 0.0) / tilt_cos + float(self._noise_rng.normal(0.0, cfg.rangefinder_noise_m))
        min_m, max_m = 0.2, cfg.rangefinder_max_m
        distance = min(max(slant, min_m), max_m + 0.01)
        return self._mav.distance_sensor_encode(
            t_ms,
            int(min_m * 100),
            int(max_m * 100),
            round(distance * 100),
            mavlink.MAV_DISTANCE_SENSOR_LASER,
            0,
            mavlink.MAV_SENSOR_ROTATION_PITCH_270,
            1,
            0.0,
            0.0,
            [0.0] * 4,
            100,
        )

    def _distance_up(self, now_s: float) -> Any:
        ceiling = self._ceiling_m(now_s)
        if ceiling is None:
            return None
        clearance = max(ceiling - self._vehicle.height_m, 0.2)
        return self._mav.distance_sensor_encode(
            self._time_boot_ms(now_s),
            20,
            int(self.config.rangefinder_max_m * 100),
            round(clearance * 100),
            mavlink.MAV_DISTANCE_SENSOR_LASER,
            1,
            mavlink.MAV_SENSOR_ROTATION_PITCH_90,
            1,
            0.0,
            0.0,
            [0.0] * 4,
            100,
        )

    def _highres_imu(self, now_s: float) -> Any:
        n = max(self._imu_n, 1)
        if self._imu_n == 0:
            f = self._vehicle.specific_force_body_m_s2
            w = self._vehicle.rates_body_rad_s
        else:
            f = (self._imu_f_sum[0] / n, self._imu_f_sum[1] / n, self._imu_f_sum[2] / n)
            w = (self._imu_w_sum[0] / n, self._imu_w_sum[1] / n, self._imu_w_sum[2] / n)
        self._imu_f_sum = [0.0, 0.0, 0.0]
        self._imu_w_sum = [0.0, 0.0, 0.0]
        self._imu_n = 0
        s = self.config.imu_noise
        na = self._noise_rng.normal(0.0, s.accel_noise_m_s2, 3) if s.accel_noise_m_s2 > 0 else np.zeros(3)
        ng = self._noise_rng.normal(0.0, s.gyro_noise_rad_s, 3) if s.gyro_noise_rad_s > 0 else np.zeros(3)
        acc = [f[i] + self._accel_bias[i] + na[i] for i in range(3)]
        gyro = [w[i] + self._gyro_bias[i] + ng[i] for i in range(3)]
        pressure_alt = self.config.reference_lla[2] + self._vehicle.height_m
        pressure_hpa = 1013.25 * (1.0 - 2.25577e-5 * pressure_alt) ** 5.25588
        return self._mav.highres_imu_encode(
            self._time_usec(now_s),
            acc[0],
            acc[1],
            acc[2],
            gyro[0],
            gyro[1],
            gyro[2],
            0.21,
            0.0,
            0.42,
            pressure_hpa,
            0.0,
            pressure_alt,
            25.0,
            0b1_1111_1111_1111,
            0,
        )

    def _sim_state(self) -> Any:
        v = self._vehicle
        R = v.R_ned_body()
        q = frames.quaternion_wxyz_from_rotation(R)
        origin = self._origin if self._origin is not None else self.config.reference_lla
        lat, lon, alt = self._llh(v.position_ned_m, origin)
        f, w = v.specific_force_body_m_s2, v.rates_body_rad_s
        vel = v.velocity_ned_m_s
        return self._mav.sim_state_encode(
            float(q[0]),
            float(q[1]),
            float(q[2]),
            float(q[3]),
            v.roll_rad,
            v.pitch_rad,
            v.yaw_rad,
            f[0],
            f[1],
            f[2],
            w[0],
            w[1],
            w[2],
            lat,
            lon,
            alt,
            0.0,
            0.0,
            vel[0],
            vel[1],
            vel[2],
            round(lat * 1e7),
            round(lon * 1e7),
        )

    # ----- receiving -------------------------------------------------------------------------

    def _on_bytes(self, data: bytes, peer: PeerKey) -> None:
        now = self.clock.now()
        if self._active("link-loss", now):
            self.stats["dropped_in"] += 1
            return
        parser = self._parsers.get(peer)
        if parser is None:
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = True
            self._parsers[peer] = parser
            while len(self._parsers) > _MAX_PARSERS:  # UDP senders come and go: forget the oldest
                del self._parsers[next(iter(self._parsers))]
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:
            self.stats["parse_errors"] += 1
            return
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.stats["parse_errors"] += 1
                continue
            self._incoming(msg, now)

    def _incoming(self, msg: Any, now_s: float) -> None:
        for f in self._active("message-loss", now_s):
            if f.params["direction"] in ("both", "in") and self._fault_rng.random() * 100.0 < float(
                f.params["percent"]
            ):
                self.stats["dropped_in"] += 1
                return
        delay_s = sum(
            float(f.params["ms"]) / 1000.0
            for f in self._active("latency", now_s)
            if f.params["direction"] in ("both", "in")
        )
        if delay_s > 0.0:
            self._later(delay_s, self._handle, msg)
        else:
            self._handle(msg)

    def _handle(self, msg: Any) -> None:
        now = self.clock.now()
        if self._started:
            self._advance_physics(now)
        msg_type = msg.get_type()
        record = ReceivedMessage(
            now, msg_type, _msg_fields(msg), bytes(msg.get_msgbuf()), msg.get_srcSystem(), msg.get_srcComponent()
        )
        self._records.append(record)
        limit = self.config.max_records
        if limit is not None and len(self._records) > limit:
            # Trim in batches: deleting one record per message from the front of a 200k list is
            # O(n) each time. Between trims the list holds 15/16 .. 1 times `limit` records.
            del self._records[: len(self._records) - limit + limit // 16]
        self.stats["received"] += 1
        self._record_event.set()
        handler = getattr(self, "_on_" + msg_type.lower(), None)
        if handler is not None:
            try:
                handler(msg, now)
            except (ValueError, TypeError, OverflowError, AttributeError):
                # A malformed but CRC-valid message (NaN where an integer belongs, ...) is ignored.
                self.stats["parse_errors"] += 1
        self._flush_events()

    def _for_me(self, msg: Any) -> bool:
        target_system = getattr(msg, "target_system", 0)
        target_component = getattr(msg, "target_component", 0)
        return target_system in (0, self.config.system_id) and target_component in (0, self.config.component_id)

    def _ack(self, command: int, result: int, msg: Any) -> None:
        self._send(self._mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_command_long(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._command(msg, int(msg.command), tuple(float(x) for x in params), now_s)

    def _on_command_int(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x / 1e7, msg.y / 1e7, msg.z)
        self._command(msg, int(msg.command), params, now_s)

    def _rejection(self, command: int, now_s: float) -> int | None:
        """The scripted answer to `command` (None = no fault; -1 = do not answer)."""
        for f in self._active("command-reject", now_s):
            commands = f.params["commands"]
            if commands is None or command in commands:
                result = f.params["result"]
                return -1 if result == "timeout" else int(_REJECT_RESULTS[result])
        return None

    def _command(self, msg: Any, command: int, p: tuple[float, ...], now_s: float) -> None:
        rejection = self._rejection(command, now_s)
        if rejection is not None:
            if rejection >= 0:
                self._ack(command, rejection, msg)
            return
        flight, vehicle = self._flight, self._vehicle
        result: int
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = math.isfinite(p[1]) and round(p[1]) == _FORCE_MAGIC
            if p[0] >= 0.5:
                result, _ = flight.arm(now_s, vehicle, force)
            else:
                result, _ = flight.disarm(now_s, vehicle, force)
        elif command == mavlink.MAV_CMD_DO_SET_MODE:
            mode = self.profile.mode_from_do_set_mode(p[0], p[1], p[2])
            result = mavlink.MAV_RESULT_FAILED if mode is None else flight.set_mode(mode, now_s, vehicle)[0]
        elif command == mavlink.MAV_CMD_NAV_TAKEOFF:
            result, _ = flight.takeoff(self._takeoff_height(p[6]), now_s, vehicle)
        elif command == mavlink.MAV_CMD_NAV_LAND:
            result, _ = flight.land(now_s, vehicle)
        elif command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            result, _ = flight.set_mode(self.profile.mode(self.profile.rtl_mode), now_s, vehicle)
        elif command == mavlink.MAV_CMD_NAV_LOITER_UNLIM:
            result, _ = flight.set_mode(self.profile.mode(self.profile.hold_mode), now_s, vehicle)
        elif command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(int(p[0]), p[1], now_s)
        elif command == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            result = self._get_interval(int(p[0]))
        elif command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            result = self._request_message(int(p[0]), now_s)
        elif command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result = self._request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, now_s)
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        self._ack(command, result, msg)

    def _takeoff_height(self, param7: float) -> float:
        if not math.isfinite(param7):
            return float(self._params.get("MIS_TAKEOFF_ALT", self._flight.params.default_takeoff_height_m))
        if self.profile.name == "px4" and self._origin is not None:
            return param7 - self._origin[2]  # PX4 takes an AMSL altitude
        return param7

    def _message_name(self, msg_id: int) -> str | None:
        cls = mavlink.mavlink_map.get(msg_id)
        return None if cls is None else str(cls.msgname)

    def _set_interval(self, msg_id: int, interval_us: float, now_s: float) -> int:
        name = self._message_name(msg_id)
        if name is None or (name not in self._streams):
            return _FAILED
        stream = self._streams[name]
        if interval_us < 0:
            stream.interval_s = 0.0
        elif interval_us == 0:
            rates = dict(DEFAULT_RATES_HZ[self.profile.name])
            rates.update(self.config.rates_hz or {})
            stream.interval_s = self._interval(rates.get(name, 1.0))
        else:
            stream.interval_s = max(interval_us / 1e6, 1.0 / _MAX_RATE_HZ)
        stream.next_due_s = now_s
        self._wake.set()
        return _ACCEPTED

    def _get_interval(self, msg_id: int) -> int:
        name = self._message_name(msg_id)
        if name is None or name not in self._streams:
            return _FAILED
        stream = self._streams[name]
        interval_us = -1 if stream.interval_s <= 0.0 else int(stream.interval_s * 1e6)
        self._send(self._mav.message_interval_encode(msg_id, interval_us))
        return _ACCEPTED

    def _request_message(self, msg_id: int, now_s: float) -> int:
        name = self._message_name(msg_id)
        if name is None:
            return _FAILED
        out = self._build(name, now_s)
        if out is None:
            return _FAILED
        self._send(out)
        return _ACCEPTED

    def _on_set_mode(self, msg: Any, now_s: float) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        rejection = self._rejection(mavlink.MAVLINK_MSG_ID_SET_MODE, now_s)
        ack_command = (
            mavlink.MAVLINK_MSG_ID_SET_MODE if self.profile.name == "ardupilot" else mavlink.MAV_CMD_DO_SET_MODE
        )
        if rejection is not None:
            if rejection >= 0:
                self._ack(ack_command, rejection, msg)
            return
        mode: ModeDef | None = None
        if msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            mode = self.profile.mode_from_custom(int(msg.custom_mode))
        if mode is None:
            self._ack(ack_command, mavlink.MAV_RESULT_FAILED, msg)
            return
        result, _ = self._flight.set_mode(mode, now_s, self._vehicle)
        self._ack(ack_command, result, msg)

    def _on_set_position_target_local_ned(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        mask = int(msg.type_mask)
        frame = int(msg.coordinate_frame)
        if frame not in (
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
            mavlink.MAV_FRAME_BODY_NED,
            mavlink.MAV_FRAME_BODY_OFFSET_NED,
        ):
            return
        vehicle = self._vehicle
        body = frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)
        offset = frame in (mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)
        c, s = math.cos(vehicle.yaw_rad), math.sin(vehicle.yaw_rad)

        def rotate(x: float, y: float) -> tuple[float, float]:
            return (c * x - s * y, s * x + c * y) if body else (x, y)

        velocity = None
        if not mask & 0b111000:
            vn, ve = rotate(msg.vx, msg.vy)
            velocity = (vn, ve, float(msg.vz))
        position = None
        if not mask & 0b111:
            pn, pe = rotate(msg.x, msg.y)
            if offset or body:
                p0 = vehicle.position_ned_m
                position = (p0[0] + pn, p0[1] + pe, p0[2] + float(msg.z))
            else:
                position = (pn, pe, float(msg.z))
        yaw = None if mask & 1024 else float(msg.yaw)
        yaw_rate = None if mask & 2048 else float(msg.yaw_rate)
        values = [
            *(velocity or ()),
            *(position or ()),
            *([yaw] if yaw is not None else []),
            *([yaw_rate] if yaw_rate is not None else []),
        ]
        if not all(math.isfinite(x) for x in values):
            return
        self._flight.on_setpoint(Setpoint(now_s, velocity, position, yaw, yaw_rate))

    def _vision(self, now_s: float) -> None:
        if not self._active("vision-reject", now_s):
            self._flight.on_vision(now_s)

    def _on_vision_position_estimate(self, msg: Any, now_s: float) -> None:
        if all(math.isfinite(x) for x in (msg.x, msg.y, msg.z)):
            self._vision(now_s)

    def _on_odometry(self, msg: Any, now_s: float) -> None:
        if all(math.isfinite(x) for x in (msg.x, msg.y, msg.z)):
            self._vision(now_s)

    def _on_att_pos_mocap(self, msg: Any, now_s: float) -> None:
        self._vision(now_s)

    def _on_set_gps_global_origin(self, msg: Any, now_s: float) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        if self._origin is None:
            self._origin = (msg.latitude / 1e7, msg.longitude / 1e7, msg.altitude / 1000.0)
            self._flight.events.append((mavlink.MAV_SEVERITY_INFO, "EKF origin set"))
        # Settable once: later requests only repeat the origin in use.
        self._send_stream("GPS_GLOBAL_ORIGIN", now_s)

    def _on_ping(self, msg: Any, now_s: float) -> None:
        if msg.target_system == 0 and msg.target_component == 0:
            self._send(self._mav.ping_encode(msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_timesync(self, msg: Any, now_s: float) -> None:
        if msg.tc1 == 0:
            self._send(self._mav.timesync_encode(round((now_s - self._boot_s) * 1e9), msg.ts1))

    def _on_param_request_read(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        names = sorted(self._params)
        name = (
            msg.param_id if msg.param_index < 0 else (names[msg.param_index] if msg.param_index < len(names) else None)
        )
        if isinstance(name, bytes):
            name = name.decode(errors="replace")
        if name in self._params:
            self._send_param(str(name))

    def _on_param_request_list(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        for name in sorted(self._params):
            self._send_param(name)

    def _on_param_set(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        name = msg.param_id.decode(errors="replace") if isinstance(msg.param_id, bytes) else str(msg.param_id)
        if name not in self._params or not math.isfinite(msg.param_value):
            return
        self._params[name] = float(msg.param_value)
        if name == "MIS_TAKEOFF_ALT":
            self._flight.params = dataclasses.replace(
                self._flight.params, default_takeoff_height_m=float(msg.param_value)
            )
        self._send_param(name)

    def _send_param(self, name: str) -> None:
        names = sorted(self._params)
        self._send(
            self._mav.param_value_encode(
                name.encode(), self._params[name], mavlink.MAV_PARAM_TYPE_REAL32, len(names), names.index(name)
            )
        )
