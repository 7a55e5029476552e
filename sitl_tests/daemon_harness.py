"""Shared setup of the daemon sitl tests: fake autopilot + deterministic synthetic camera + daemon.

Everything runs on one `ManualClock` over real loopback UDP sockets. The camera renders the
simulator's rack scene from the fake autopilot's true pose *on the event-loop thread* at each
tick of the manual clock (`InlineCamera`), and the daemon runs its vision inline
(`vision_inline=True`), so a test is deterministic and never waits on a thread. The camera keeps
the `drivers.camera.CameraSource` contract the daemon uses (next_frame, stats, state, on_lost,
on_recovered); "unplugging" it makes reads fail the way the real drivers report a vanished device.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.clock import ManualClock
from companion.daemon.app import Daemon, DaemonOptions
from companion.errors import CameraError
from companion.mission import Mission, parse_mission
from companion.sim.autopilot import DrydenConfig, FakeAutopilot, FakeAutopilotConfig, Fault, FlightParams
from companion.sim.render import SceneRenderer
from companion.sim.run import sim_config
from drivers.camera import CameraState, CameraStats, Frame, load_camera_model

VISUAL_GROUND_Z_NED_M = 4.0  # sim_default.toml: rack support plane 1 m below the deck, ground 3 m below that


class InlineCamera:
    """Deterministic synthetic camera: renders on the loop thread at every 1/fps of the manual clock."""

    def __init__(self, clock: ManualClock, render: Callable[[Any], Any], pose_source: Callable[[], Any],
                 fps: float = 10.0, lost_after_s: float = 0.5) -> None:
        self.clock = clock
        self.render = render
        self.pose_source = pose_source
        self.period_s = 1.0 / fps
        self.lost_after_s = lost_after_s
        self.unplugged = False
        self.featureless = False
        self.state = CameraState.CLOSED
        self._next_s = 0.0
        self._seq = 0
        self._captured = 0
        self._failures = 0
        self._lost_count = 0
        self._reopens = 0
        self._last_frame_s: float | None = None
        self._lost_cbs: list[Callable[[str], None]] = []
        self._recovered_cbs: list[Callable[[], None]] = []

    async def __aenter__(self) -> InlineCamera:
        self.state = CameraState.STARTING
        self._next_s = self.clock.now()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.state = CameraState.CLOSED

    def on_lost(self, callback: Callable[[str], None]) -> None:
        self._lost_cbs.append(callback)

    def on_recovered(self, callback: Callable[[], None]) -> None:
        self._recovered_cbs.append(callback)

    @property
    def healthy(self) -> bool:
        return self.state is CameraState.STREAMING

    @property
    def ended(self) -> bool:
        return False

    @property
    def stats(self) -> CameraStats:
        return CameraStats(captured=self._captured, delivered=self._captured, dropped_stale=0,
                           read_failures=self._failures, reopen_count=self._reopens, lost_count=self._lost_count,
                           lost=self.state is CameraState.LOST, state=self.state, last_frame_s=self._last_frame_s,
                           last_error=None)

    def _read(self) -> Any:
        if self.unplugged:
            raise CameraError("device vanished (test unplug)")
        sample = self.pose_source()
        image = self.render(np.asarray(sample))
        if self.featureless:
            image = np.full_like(image, 128)
        return image

    async def next_frame(self, timeout_s: float | None = None) -> Frame | None:
        now = self.clock.now()
        if self._next_s > now:
            wait = self._next_s - now
            if timeout_s is not None and wait > timeout_s:
                await self.clock.sleep(timeout_s)
                return None
            await self.clock.sleep(wait)
        stamp = self.clock.now()
        self._next_s = max(self._next_s + self.period_s, stamp + 1e-6)
        try:
            image = self._read()
        except CameraError as exc:
            self._failures += 1
            last = self._last_frame_s if self._last_frame_s is not None else stamp
            if self.state is not CameraState.LOST and stamp - last >= self.lost_after_s:
                self.state = CameraState.LOST
                self._lost_count += 1
                for cb in self._lost_cbs:
                    cb(str(exc))
            return None
        if self.state is CameraState.LOST:
            self._reopens += 1
            self.state = CameraState.STREAMING
            for rcb in self._recovered_cbs:
                rcb()
        self.state = CameraState.STREAMING
        frame = Frame(image=image, stamp_s=stamp, seq=self._seq, dropped_before=0, source_stamp_s=stamp)
        self._seq += 1
        self._captured += 1
        self._last_frame_s = stamp
        return frame


@dataclass
class Rig:
    clock: ManualClock
    ap: FakeAutopilot
    daemon: Daemon
    camera: InlineCamera
    tmp: Path
    config: Any = None
    notes: list[str] = field(default_factory=list)

    @property
    def start_s(self) -> float:
        """The fake autopilot's boot time on the clock (faults are scheduled relative to it)."""
        return self.clock.now() - self.ap.elapsed_s

    def schedule(self, kind: str, in_s: float, duration_s: float | None = None, **params: Any) -> None:
        """Schedule a fake-autopilot fault `in_s` seconds from now."""
        self.ap.schedule(Fault(kind, at_s=self.ap.elapsed_s + in_s, duration_s=duration_s, **params))

    async def advance(self, seconds: float, step_s: float = 0.02) -> None:
        await self.clock.advance(seconds, step_s=step_s)

    async def advance_until(self, cond: Callable[[], bool], max_s: float, step_s: float = 0.02) -> float:
        """Advance until `cond()`; returns the clock time it became true (AssertionError after max_s)."""
        t_end = self.clock.now() + max_s
        while not cond():
            if self.clock.now() >= t_end:
                raise AssertionError(f"condition not met within {max_s} s of clock time")
            await self.clock.advance(step_s, step_s=step_s)
        return self.clock.now()

    def received(self, msg_type: str, since_s: float | None = None) -> list[Any]:
        msgs = self.ap.received_of(msg_type)
        return [m for m in msgs if since_s is None or m.time_s >= since_s]

    def statustexts(self, since_s: float | None = None) -> list[str]:
        """The STATUSTEXTs the autopilot received (since `since_s`), chunks (same non-zero id) joined in order."""
        texts: dict[int, str] = {}
        for k, m in enumerate(self.received("STATUSTEXT", since_s)):
            key = int(m.fields.get("id", 0)) or -1 - k
            texts[key] = texts.get(key, "") + str(m.fields["text"])
        return list(texts.values())

    def logged(self, event: str) -> list[dict[str, Any]]:
        """The daemon's flight-log records of `event` (the log flushed first)."""
        assert self.daemon.flight is not None
        self.daemon.flight.flush()
        lines = (self.daemon.flight.path / "log.jsonl").read_text(encoding="utf-8").splitlines()
        return [rec for rec in map(json.loads, lines) if rec["event"] == event]

    def modes_commanded(self, since_s: float | None = None) -> list[float]:
        """param2 of every MAV_CMD_DO_SET_MODE (176) the autopilot received (custom mode numbers)."""
        return [float(m.fields["param2"]) for m in self.received("COMMAND_LONG", since_s)
                if int(m.fields["command"]) == 176]

    async def start_mission(self, mission: Mission) -> None:
        await self.daemon.start_mission(mission, mission.name)


async def stop_daemon(daemon: Daemon, clock: ManualClock) -> None:
    """Stop the daemon, advancing the manual clock while it shuts down (hold command, link close)."""
    stop = asyncio.ensure_future(daemon.stop("test end"))
    for _ in range(500):
        if stop.done():
            break
        await clock.advance(0.02)
    await stop


def mission(xml_body: str, name: str = "test", frame: str = "rack", timeout_s: float = 40.0) -> Mission:
    """A small mission over the paper rack (rack frame) with `xml_body` as its actions."""
    text = f"""<?xml version="1.0" encoding="UTF-8"?>
<mission version="1" name="{name}" frame="{frame}" timeout="{timeout_s:g}" speed="0.5" threshold="0.1"
         yaw-threshold="5" settle="0.3">
  <rack length="10.0">
    <pipe radius="0.15" gap="0.10"/><pipe radius="0.20" gap="0.10"/><pipe radius="0.15" gap="0.20"/>
    <pipe radius="0.18" gap="0.30"/><pipe radius="0.15"/>
  </rack>
{xml_body}
</mission>"""
    return parse_mission(text.encode(), source_name=f"{name}.xml")


@contextlib.asynccontextmanager
async def rig(
    tmp_path: Path,
    *,
    profile: str = "ardupilot",
    vision: str = "rack",
    fps: float = 10.0,
    overrides: dict[str, Any] | None = None,
    api: bool = False,
    gcs_heartbeat: bool = True,
    start_flight: bool = True,
    flight: FlightParams | None = None,
    max_records: int | None = 200_000,
    record_frames: bool | None = None,
    start_hint: Callable[[Any], Any] | None = None,
    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> AsyncIterator[Rig]:
    """Fake autopilot + inline camera + daemon on a ManualClock; waits until poses flow (EKF healthy).

    `start`: where the vehicle boots (north m, east m, yaw rad); `start_hint` maps its true pose to the
    daemon's start hint (default: the true pose).
    The deck/ground offset of the simulated world comes in as ``camera.sim_ground_z_ned_m``;
    `record_frames` None keeps ``logging.record_frames`` of the config (overrides)."""
    clock = ManualClock(1000.0)
    ov: dict[str, Any] = {"vision": {"source": vision}, "camera": {"fps": fps, "width": 240, "height": 160,
                                                                   "sim_ground_z_ned_m": VISUAL_GROUND_Z_NED_M}}
    for k, v in (overrides or {}).items():
        ov.setdefault(k, {}).update(v)
    if api:
        ov.setdefault("api", {}).update({"enabled": True, "port": 0, "bind": "127.0.0.1"})
    config = sim_config(tmp_path, ov)
    flight = flight or FlightParams(takeoff_speed_m_s=0.5)
    if flight.ekf_alignment_s is None:
        # The fake's EKF needs 11.8 s of vision before it may arm, like ArduCopter's; these tests fly at once.
        flight = dataclasses.replace(flight, ekf_alignment_s=0.5)
    ap_cfg = FakeAutopilotConfig(profile=profile, listen="udpin:127.0.0.1:0", seed=3, gcs_heartbeat=gcs_heartbeat,
                                 wind=DrydenConfig(w20_m_s=0.0), physics_rate_hz=100.0,
                                 flight=flight, max_records=max_records, start_north_m=start[0],
                                 start_east_m=start[1], start_yaw_rad=start[2])
    async with FakeAutopilot(ap_cfg, clock=clock) as ap:
        config = dataclasses.replace(config, mavlink=dataclasses.replace(config.mavlink, url=ap.url_for_client))
        camera_model = load_camera_model(config.camera)
        render = SceneRenderer.from_config(config, camera_model, seed=5)
        camera = InlineCamera(clock, render, lambda: ap.truth.T_ned_body, fps=fps)
        await camera.__aenter__()
        daemon = Daemon(config, clock=clock, options=DaemonOptions(
            vision_inline=True, camera_source=camera, api=api, sdnotify=False,
            initial_T_ned_body=ap.truth.T_ned_body if start_hint is None else start_hint(ap.truth.T_ned_body),
            flight_root=tmp_path / "flights", record_frames=record_frames,
        ))
        await daemon.start()
        r = Rig(clock=clock, ap=ap, daemon=daemon, camera=camera, tmp=tmp_path, config=config)
        try:
            if start_flight:
                await r.advance_until(lambda: daemon.counters.poses_sent >= 10 and ap.ekf_healthy, max_s=10.0)
            yield r
        finally:
            await stop_daemon(daemon, clock)
            await camera.__aexit__(None, None, None)
