"""The daemon against the real ArduCopter SITL: one fresh SITL, the daemon in-process, an observer.

Real time (the SITL cannot run on our clock). The world is the simulator's default placement
(`companion/data/sim_default.toml`: the paper's 5-pipe rack 1 m below the take-off deck), with
the SITL's home as the EKF origin and the home heading 0 deg (north = the rack's +y), so the
daemon's default start pose (the origin, facing north) is the surveyed start an integrator would
give. The synthetic camera renders from ArduPilot's own SIM_STATE, received on the daemon's link.
The observer (SERIAL1) records what ArduPilot reports and plays the GCS.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.clock import SystemClock
from companion.daemon.app import Daemon, DaemonOptions
from companion.sim.ardupilot_sitl import ArduPilotSitl, SitlObserver, sitl_binary
from companion.sim.render import FaultyRender, SceneRenderer
from companion.sim.run import sim_config
from drivers.camera import load_camera_model

FIGURES: list[str] = []  # printed at the end of the pytest run (conftest.py)


def report(line: str) -> None:
    """A measured figure for the test log: printed now and again in the run's terminal summary."""
    FIGURES.append(line)
    print(f"[ardupilot] {line}", flush=True)


HOME_LLA = (-35.363261, 149.165230, 584.0)  # ArduPilot's SITL default home (CMAC), heading set to 0
BATTERY_LOW_V = 11.1


@dataclass
class SitlRig:
    sitl: ArduPilotSitl
    observer: SitlObserver
    daemon: Daemon
    render: FaultyRender
    clock: SystemClock
    config: Any
    tmp: Path
    log: list[str] = field(default_factory=list)

    def say(self, line: str) -> None:
        """Print a figure into the test log (pytest -s or the captured output of a failure)."""
        self.log.append(line)
        report(line)

    async def wait_until(self, cond: Callable[[], bool], timeout_s: float, what: str, poll_s: float = 0.1) -> float:
        """Wait (real time) until `cond()`; returns the seconds it took; AssertionError naming `what`."""
        t0 = time.monotonic()
        while not cond():
            if time.monotonic() - t0 > timeout_s:
                raise AssertionError(f"{what}: not within {timeout_s:g} s (mode {self.observer.mode}, "
                                     f"armed {self.observer.armed}, texts {self.observer.statustexts()[-6:]})")
            await asyncio.sleep(poll_s)
        return time.monotonic() - t0

    def truth_position(self) -> np.ndarray[Any, Any]:
        T = self.observer.truth_T_ned_body()
        assert T is not None, "no SIM_STATE from the SITL"
        return np.asarray(T)[:3, 3]

    def truth_height_m(self) -> float:
        return float(-self.truth_position()[2])

    def vision_fault(self, kind: str, start_s: float, end_s: float = math.inf) -> None:
        """Camera fault on the daemon's clock: "vision-loss" (featureless frames) or "camera-unplug"."""
        self.render.windows.append((kind, start_s, end_s))


@contextlib.asynccontextmanager
async def sitl_rig(tmp_path: Path, *, extra_params: dict[str, float] | None = None,
                   overrides: dict[str, Any] | None = None, gcs_heartbeat: bool = True,
                   fps: float = 10.0, seed: int = 5) -> AsyncIterator[SitlRig]:
    """ArduCopter SITL + daemon (synthetic camera rendered in this process) in real time.

    10 frames/s, not 15: the renderer (40-46 ms a frame at 360x240), the tracker and the filter share this 2-core
    machine with the SITL, and with the host's CPU short (2026-12-03) 15 frames/s starved the camera: gaps of
    0.3-0.8 s, re-seeds, ArduCopter's EKF failsafe (LAND); docs/missions.md, "A starved companion computer".
    """
    binary = sitl_binary()
    assert binary is not None
    lat, lon, alt = HOME_LLA
    ov: dict[str, Any] = {"ekf_origin": {"enabled": True, "lat_deg": lat, "lon_deg": lon, "alt_m": alt},
                          "camera": {"fps": fps},
                          # the SITL's battery is a 3S pack (12.6 V full), not the fake's 4S
                          "safety": {"battery_low_v": BATTERY_LOW_V, "battery_critical_v": 10.5}}
    for k, v in (overrides or {}).items():
        ov.setdefault(k, {}).update(v)
    with ArduPilotSitl(binary, home=f"{lat},{lon},{alt},0", extra_params=dict(extra_params or {})) as sitl:
        config = sim_config(tmp_path, ov)
        config = dataclasses.replace(config, mavlink=dataclasses.replace(config.mavlink, url=sitl.url))
        clock = SystemClock()
        camera_model = load_camera_model(config.camera)
        base = SceneRenderer.from_config(config, camera_model, seed=seed)
        base(np.eye(4))  # warm the renderer's caches before the camera's clock runs
        render = FaultyRender(base, clock.now)
        daemon = Daemon(config, clock=clock, options=DaemonOptions(
            render=render, api=False, sdnotify=False, initial_T_ned_body=np.eye(4),
            flight_root=tmp_path / "flights"))
        async with daemon:
            observer = SitlObserver(sitl.observer_url, HOME_LLA, gcs_heartbeat=gcs_heartbeat)
            await asyncio.get_running_loop().run_in_executor(None, observer.start)
            rig = SitlRig(sitl=sitl, observer=observer, daemon=daemon, render=render, clock=clock,
                          config=config, tmp=tmp_path)
            try:
                yield rig
            finally:
                observer.stop()


def toml_text(data: dict[str, Any]) -> str:
    """A TOML file for `companion run` from plain tables of scalars and lists (test configs only)."""

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, int | float):
            return repr(v)
        if isinstance(v, list | tuple):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'

    lines: list[str] = []
    for section, table in data.items():
        lines.append(f"[{section}]")
        for key, v in table.items():
            if isinstance(v, dict):
                raise ValueError(f"{section}.{key}: nested tables are not supported here")
            lines.append(f"{key} = {value(v)}")
        lines.append("")
    return "\n".join(lines)


def run_config(tmp_path: Path, url: str, api_port: int, overrides: dict[str, Any] | None = None) -> Path:
    """The simulator's default config as a file for `companion run` against the SITL at `url`."""
    import tomllib

    from companion.data import data_path

    data = tomllib.loads(data_path("sim_default.toml").read_text(encoding="utf-8"))
    lat, lon, alt = HOME_LLA
    data["mavlink"]["url"] = url
    data["rack"]["model"] = str(data_path(str(data["rack"]["model"])))
    data["ekf_origin"].update({"enabled": True, "lat_deg": lat, "lon_deg": lon, "alt_m": alt})
    data["safety"].update({"battery_low_v": BATTERY_LOW_V, "battery_critical_v": 10.5})
    data["logging"]["flight_root"] = str(tmp_path / "flights")
    data["mission"].update({"photo_folder": str(tmp_path / "photos"), "upload_folder": str(tmp_path / "missions")})
    data["api"] = {"enabled": True, "bind": "127.0.0.1", "port": api_port}
    for k, v in (overrides or {}).items():
        data.setdefault(k, {}).update(v)
    path = tmp_path / "companion.toml"
    path.write_text(toml_text(data), encoding="utf-8")
    return path
