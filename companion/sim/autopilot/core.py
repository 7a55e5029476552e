"""The fake autopilot's core: state, scripted faults, the physics step and the (faulty) way out to the socket.

`AutopilotCore` is the base of `Telemetry` (telemetry.py), `Commands` (commands.py) and `FakeAutopilot`
(autopilot.py), which add the outgoing messages, the incoming ones and the lifecycle.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.clock import Clock, SystemClock
from companion.sim.autopilot.battery import (
    BatteryState,
    battery_current_a,
    initial_battery,
    step_battery,
)
from companion.sim.autopilot.config import (
    GCS_COMPID,
    GCS_SYSID,
    MAX_RATE_HZ,
    PARAMS,
    FakeAutopilotConfig,
    ReceivedMessage,
    Stream,
)
from companion.sim.autopilot.faults import Fault, active_faults
from companion.sim.autopilot.flight import FlightLogic
from companion.sim.autopilot.profiles import Profile, profile_by_name
from companion.sim.autopilot.transport import PeerKey, ServerTransport
from companion.sim.autopilot.vehicle import (
    VehicleState,
    initial_vehicle,
    step_vehicle,
)
from companion.sim.autopilot.wind import DrydenWind


class AutopilotCore:
    """State shared by the fake's parts (see the module docstring)."""

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
        self._params = dict(PARAMS[self.profile.name])
        self._mav = mavlink.MAVLink(None, srcSystem=cfg.system_id, srcComponent=cfg.component_id)
        self._gcs_mav = mavlink.MAVLink(None, srcSystem=GCS_SYSID, srcComponent=GCS_COMPID)
        self._parsers: dict[PeerKey, mavlink.MAVLink] = {}
        self._transport: ServerTransport | None = None
        self._task: asyncio.Task[None] | None = None
        self._pending: set[asyncio.Task[None]] = set()
        self._boot_s = 0.0
        self._phys_t = 0.0
        self._started = False
        self._origin: tuple[float, float, float] | None = cfg.origin_lla
        self._timesync_next_s = 0.0
        self._announced_mode = self._flight.mode  # ArduPilot sends its own TIMESYNC request every 10 s
        self._streams: dict[str, Stream] = {}
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

    @staticmethod
    def _interval(rate_hz: float) -> float:
        return 0.0 if rate_hz <= 0.0 else 1.0 / min(rate_hz, MAX_RATE_HZ)

    # ----- sending ---------------------------------------------------------------------------

    def _heartbeat(self) -> Any:
        raise NotImplementedError  # telemetry.py

    def _flush_events(self) -> None:
        events, self._flight.events = self._flight.events, []
        for severity, text in events:
            self._send(self._mav.statustext_encode(severity, text[:50].encode()))
        if self._flight.mode != self._announced_mode:
            self._announced_mode = self._flight.mode
            if self.profile.name == "ardupilot" and self._started:
                self._send(self._heartbeat())  # ArduCopter sends a HEARTBEAT at once on a mode change

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
