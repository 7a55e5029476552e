"""`companion sim`: fly a mission against the fake autopilot with the synthetic camera, write a report.

Everything runs in this process on one asyncio loop, on loopback, in real time by default:
the fake autopilot (Dryden wind, scripted faults) listens on 127.0.0.1, the daemon connects
to it like to a real flight controller, the synthetic camera renders the rack scene from the
vehicle's true pose (the fake's SIM_STATE), and the mission is started on the daemon. The
runner samples the truth, follows the mission and, at the end, writes ``DIR/report.json``
(`companion.sim.report.build_report`) and ``DIR/trajectory.png``. The daemon's flight folder
(log, tlog, TUM trajectory, photos) is under ``DIR/flights/``.

Faults (``KIND@SECONDS[:DURATION]``, seconds after the mission start): battery-sag,
battery-critical, gcs-loss, link-loss, ceiling go to the fake autopilot; vision-loss (the
camera delivers featureless frames) and camera-unplug (the renderer raises, the driver
reopens with backoff) are injected at the camera.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.clock import Clock, SystemClock
from companion.errors import CompanionError, InputError
from companion.sim.flight_record import (
    close_record,
    collect_frames,
    failed_action,
    finish_report,
    flight_over,
    note_autopilot_mode,
)
from companion.sim.report import ActionResult, SimRecord

__all__ = ["FAULT_KINDS", "FaultSpec", "SimOptions", "SimResult", "collect_frames", "failed_action", "finish_report",
           "note_autopilot_mode", "parse_fault_spec", "run_sim", "run_sim_cli", "sim_config"]

# every fault `companion fake-autopilot --fault` knows, plus the two injected at the camera
FAULT_KINDS = ("battery-sag", "battery-critical", "gcs-loss", "vision-loss", "link-loss", "camera-unplug", "ceiling",
               "message-loss", "latency", "corrupt", "command-reject", "vision-reject")
CAMERA_FAULTS = ("vision-loss", "camera-unplug")
# the example mission flies 1.3-1.5 m above the deck: an overhead structure 2.0 m above it leaves less than
# safety.ceiling_clearance_m (1 m), so the ceiling fault visibly pushes the vehicle down (the fake's default
# 3 m would change nothing)
SIM_FAULT_PARAMS: dict[str, dict[str, Any]] = {"ceiling": {"height_m": 2.0}}


@dataclass(frozen=True)
class FaultSpec:
    """A fault `kind` at `at_s` seconds after the mission start, lasting `duration_s` (None: to the end)."""

    kind: str
    at_s: float
    duration_s: float | None = None

    def text(self) -> str:
        return f"{self.kind}@{self.at_s:g}" + ("" if self.duration_s is None else f":{self.duration_s:g}")


def parse_fault_spec(spec: str) -> FaultSpec:
    """Parse ``KIND@SECONDS[:DURATION]`` (seconds may end in 's'); raises `InputError` naming the problem."""
    text = spec.strip()
    if "@" not in text:
        raise InputError(f"--fault {spec!r}: expected KIND@SECONDS[:DURATION], e.g. gcs-loss@20:10")
    kind, _, when = text.partition("@")
    kind = kind.strip()
    if kind not in FAULT_KINDS:
        raise InputError(f"--fault {spec!r}: unknown kind {kind!r}; one of {', '.join(FAULT_KINDS)}")
    at_text, _, dur_text = when.partition(":")

    def seconds(value: str, what: str) -> float:
        v = value.strip().removesuffix("s")
        try:
            x = float(v)
        except ValueError:
            raise InputError(f"--fault {spec!r}: {what} {value!r} is not a number of seconds") from None
        if not math.isfinite(x) or x < 0:
            raise InputError(f"--fault {spec!r}: {what} must be a finite number >= 0")
        return x

    at_s = seconds(at_text, "time")
    duration = seconds(dur_text, "duration") if dur_text else None
    if duration is not None and duration <= 0:
        raise InputError(f"--fault {spec!r}: duration must be > 0")
    return FaultSpec(kind, at_s, duration)


class ScaledClock:
    """Real time slowed down (or sped up) by `speed`: ``now = start + speed * (monotonic - m0)``.

    `companion sim --speed 0.5` runs the whole closed loop (autopilot physics, camera, daemon timers)
    at half real time, for machines too slow or too loaded to render and track in real time. Every
    timing the daemon applies (safety timeouts, rates) is in this clock's seconds.
    """

    def __init__(self, speed: float, start_s: float | None = None) -> None:
        if not (math.isfinite(speed) and speed > 0):
            raise InputError(f"--speed: must be a number > 0, got {speed}")
        self.speed = float(speed)
        self._m0 = time.monotonic()
        self._t0 = self._m0 if start_s is None else float(start_s)

    def now(self) -> float:
        return self._t0 + (time.monotonic() - self._m0) * self.speed

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds) / self.speed)


@dataclass(frozen=True)
class SimOptions:
    """Options of `companion sim` (see the CLI help)."""

    mission_path: Path | None = None
    autopilot: str = "ardupilot"
    faults: tuple[FaultSpec, ...] = ()
    headless: bool = True
    out_dir: Path = Path("sim-out")
    max_duration_s: float | None = None
    seed: int = 1
    wind: bool = True
    wind_m_s: float = 2.0
    speed: float = 1.0
    rack_along_pipe_std_m: float | None = None  # None: vision.rack_along_pipe_std_m of the config
    start_error: Any = None  # companion.sim.start_error.StartError: boot away from the configured start
    seed_true_pose: bool = False  # hand the daemon the true start pose (else the configured one)
    appearance: str = "default"  # the rack's rendering: "default" (RackScene) or "field" (FieldRackScene)
    config_overrides: dict[str, Any] = field(default_factory=dict)


@dataclass
class SimResult:
    record: SimRecord
    report: dict[str, Any]
    report_path: Path | None
    plot_path: Path | None
    frames: list[Any] = field(default_factory=list)


def sim_config(out_dir: Path, overrides: dict[str, Any] | None = None) -> Any:
    """The embedded simulator configuration (``companion/data/sim_default.toml``) rooted in `out_dir`."""
    import tomllib

    from companion.config import parse_config
    from companion.data import data_path

    data = tomllib.loads(data_path("sim_default.toml").read_text(encoding="utf-8"))
    rack = data.setdefault("rack", {})
    model = str(rack.get("model", ""))
    if model and not Path(model).is_absolute():  # a packaged rack, relative to companion/data
        rack["model"] = str(data_path(model))
    data.setdefault("logging", {})["flight_root"] = str(out_dir / "flights")
    data.setdefault("mission", {})["photo_folder"] = str(out_dir / "photos")
    data["mission"]["upload_folder"] = str(out_dir / "missions")
    from companion.sim.config_set import merge_overrides

    data = merge_overrides(data, overrides or {})
    return parse_config(data, source="<sim_default.toml>")


def _withheld_reason(daemon: Any) -> str:
    """Why the daemon held its rack poses back on the deck, for the report (empty when it did not)."""
    if daemon.counters.poses_withheld <= 0:
        return ""
    checker = None if daemon.pipeline is None else daemon.pipeline.hint_checker
    last = None if checker is None else checker.last
    why = "" if last is None else f"; last check: {last.outcome}, {last.status or 'no status'}"
    return (f"; {daemon.counters.poses_withheld} withheld: the rack lock from the configured start was not verified "
            f"against the image (vision.rack_verify_start = \"withhold\"{why})")


def _progress_line(elapsed_s: float, daemon: Any, truth: Any) -> str:
    ex = daemon.executor
    state = "idle" if ex is None else str(ex.state)
    nav = daemon.last_nav
    src = "none" if nav is None else str(nav.source)
    p = truth.position_ned_m
    err = float("nan")
    if nav is not None and bool(nav.ok):
        err = float(np.linalg.norm(np.asarray(nav.position_ned_m) - p)) * 100.0
    done = 0 if ex is None else len(ex.results)
    total = 0 if ex is None else len(ex.mission.actions)
    return (f"t={elapsed_s:6.1f}s mission {state} {done}/{total}  N={p[0]:+6.2f} E={p[1]:+6.2f} "
            f"h={-p[2]:5.2f}m  vision={src:6s} err={err:5.1f}cm  poses={daemon.counters.poses_sent}")


async def run_sim(options: SimOptions, clock: Clock | None = None, out: Any = None) -> SimResult:
    """Fly `options`' mission in the simulator; returns the record and the report (files written)."""
    from companion.config import mission_limits
    from companion.daemon.app import Daemon, DaemonOptions
    from companion.data import data_path
    from companion.mission import load_mission
    from companion.sim.autopilot import DrydenConfig, FakeAutopilot, FakeAutopilotConfig, Fault, FlightParams
    from companion.sim.render import FaultyRender, SceneRenderer
    from drivers.camera import load_camera_model

    if options.autopilot == "ardupilot-sitl":
        from companion.sim.run_sitl import run_sim_sitl

        return await run_sim_sitl(options, out if out is not None else sys.stdout)  # type: ignore[no-any-return]
    clock = clock or (SystemClock() if options.speed == 1.0 else ScaledClock(options.speed))
    speed = float(getattr(clock, "speed", 1.0))
    out = out if out is not None else sys.stdout
    out_dir = options.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    mission_path = options.mission_path or data_path("missions/paper_sweep.xml")
    config = sim_config(out_dir, options.config_overrides)
    mission = load_mission(mission_path, limits=mission_limits(config))  # the vehicle's ceiling and speed
    camera_model = load_camera_model(config.camera)
    record = SimRecord(mission_name=mission.name, autopilot=options.autopilot,
                       faults=[f.text() for f in options.faults])
    timeout_s = options.max_duration_s or (sum(a.timeout_s for a in mission.actions) + 30.0)

    wind = DrydenConfig(w20_m_s=options.wind_m_s if options.wind else 0.0, from_rad=math.radians(60.0),
                        turbulence=1.0 if options.wind else 0.0)
    from companion.sim.start_error import StartError, start_hint, start_pose

    start = start_pose(options.start_error or StartError(), options.seed)
    if options.start_error is not None:
        record.notes.append(f"start error {options.start_error.text()}: the vehicle boots at N {start.north_m:+.2f} "
                            f"E {start.east_m:+.2f} m, heading {math.degrees(start.yaw_rad):+.1f} deg")
    ap_cfg = FakeAutopilotConfig(profile=options.autopilot, listen="udpin:127.0.0.1:0", seed=options.seed,
                                 wind=wind, gcs_heartbeat=True, physics_rate_hz=200.0,
                                 flight=FlightParams(takeoff_speed_m_s=0.3), start_north_m=start.north_m,
                                 start_east_m=start.east_m, start_yaw_rad=start.yaw_rad)
    async with FakeAutopilot(ap_cfg, clock=clock) as ap:
        config = dataclasses.replace(config, mavlink=dataclasses.replace(config.mavlink, url=ap.url_for_client))
        base_render = SceneRenderer.from_config(config, camera_model, seed=options.seed, appearance=options.appearance)
        base_render(ap.truth.T_ned_body)  # warm the renderer's caches before the camera's clock runs
        render = FaultyRender(base_render, clock.now)
        daemon = Daemon(config, clock=clock, options=DaemonOptions(
            render=render, api=bool(config.api.enabled), sdnotify=False,
            initial_T_ned_body=start_hint(start, seed_true_pose=options.seed_true_pose),
            flight_root=out_dir / "flights", visual_ground_z_ned_m=_visual_ground_z(config, base_render),
            rack_along_pipe_std_m=options.rack_along_pipe_std_m,
        ))
        frames_seen: list[Any] = []
        daemon.frame_observers.append(frames_seen.append)
        async with daemon:
            link = daemon.link
            assert link is not None
            await link.wait_autopilot(10.0)
            from companion.sim.ground_station import announce

            announce(daemon, out)  # the status page and the video, when configured (companion sim does)
            # like an operator: wait until poses flow and the autopilot's EKF accepts them
            # (ArduCopter's EKF aligns on the vision poses for ~12 s before it may arm: the fake does the same)
            t_wait = clock.now() + 30.0
            while clock.now() < t_wait and not (daemon.counters.poses_sent >= 10 and ap.ekf_healthy
                                                and ap.ready_to_arm):
                await clock.sleep(0.1)
            ready = daemon.counters.poses_sent >= 10 and ap.ekf_healthy
            if not ready:
                record.notes.append(f"no healthy vision pose stream before the start ({daemon.counters.poses_sent} "
                                    "poses sent): the mission was not started" + _withheld_reason(daemon))
            t0 = clock.now()
            record.start_s = t0
            boot_s = clock.now() - ap.elapsed_s
            for f in options.faults:
                if f.kind in CAMERA_FAULTS:
                    end = math.inf if f.duration_s is None else t0 + f.at_s + f.duration_s
                    render.windows.append((f.kind, t0 + f.at_s, end))
                else:
                    ap.schedule(Fault(f.kind, at_s=(t0 - boot_s) + f.at_s, duration_s=f.duration_s,
                                      **SIM_FAULT_PARAMS.get(f.kind, {})))
            if ready:
                try:
                    await daemon.start_mission(mission, mission_path.stem)
                except CompanionError as exc:
                    record.notes.append(f"mission refused: {exc}")
            last_print = -1.0
            ended: dict[str, float] = {}
            while clock.now() - t0 < timeout_s:
                await clock.sleep(0.05)
                truth = ap.truth
                record.truth_stamps_s.append(float(truth.stamp_s))
                record.truth_positions_ned_m.append(np.asarray(truth.T_ned_body[:3, 3], dtype=np.float64).copy())
                record.truth_rotations.append(np.asarray(truth.T_ned_body[:3, :3], dtype=np.float64).copy())
                elapsed = clock.now() - t0
                if elapsed - last_print >= (1.0 if not options.headless else 5.0):
                    last_print = elapsed
                    line = _progress_line(elapsed, daemon, truth)
                    if options.headless:
                        print(line, file=out, flush=True)
                    else:
                        print("\r" + line, end="", file=out, flush=True)
                note_autopilot_mode(record, elapsed, ap.mode, bool(ap.armed))
                _collect_results(daemon, record, ap)
                if flight_over(daemon.executor, bool(ap.armed), clock.now(), ended):
                    break
            if not options.headless:
                print("", file=out)
            close_record(record, daemon, t0, clock.now(), timeout_s)
            _collect_results(daemon, record, ap)
            vpe = ap.received_of("VISION_POSITION_ESTIMATE") or ap.received_of("ODOMETRY")  # PX4: ODOMETRY
            collect_frames(frames_seen, render, vpe, boot_s, record, speed,
                            stamp_base=link.pose_time_base or "autopilot")
    report, report_path, plot_path = finish_report(record, daemon, config, camera_model, out_dir, speed)
    return SimResult(record=record, report=report, report_path=report_path, plot_path=plot_path, frames=frames_seen)



def _visual_ground_z(config: Any, renderer: Any) -> float:
    """NED z (m) of the rendered ground plane (rack frame z = ground_z_m)."""
    from companion.geometry import se3

    p = se3.act(config.rack.T_ned_rack, np.array([0.0, 0.0, float(renderer.scene.config.ground_z_m)]))
    return float(p[2])


def _collect_results(daemon: Any, record: SimRecord, ap: Any) -> None:
    ex = daemon.executor
    if ex is None:
        return
    known = {a.index for a in record.actions}
    for r in ex.results:
        if r.index in known:
            continue
        goal = None
        err = None
        if r.T_ned_body_goal is not None and r.result == "succeeded" and r.action in (
                "gotoxy", "gotoz", "servo", "home", "takeoff"):
            g = np.asarray(r.T_ned_body_goal)[:3, 3]
            goal = (float(g[0]), float(g[1]), float(g[2]))
            err = float(np.linalg.norm(ap.truth.position_ned_m - g))
            record.goals_ned_m.append(goal)
        record.actions.append(ActionResult(index=r.index, name=f"{r.action}:{r.action_id}", result=r.result,
                                           seconds=float(r.seconds), goal_ned_m=goal, true_error_m=err))


def run_sim_cli(options: SimOptions) -> int:
    """`companion sim`: run, print the key figures, exit 0 only if the mission completed."""
    t_wall = time.monotonic()
    result = asyncio.run(run_sim(options))
    rep = result.report
    lat = rep["latency_ms"]
    est = rep["estimation"]
    print(f"mission {rep['mission']['name']}: {'COMPLETED' if rep['mission']['completed'] else 'NOT completed'} "
          f"({rep['mission']['state']}, {rep['mission']['duration_s']:.1f} s, wall {time.monotonic() - t_wall:.1f} s)")
    print(f"waypoint errors max {rep['waypoint_error_max_m']} m; estimation rms {est['rms_position_m']} m "
          f"max {est['max_position_m']} m, {est['rms_orientation_deg']} deg; "
          f"poses {rep['pose_messages']['rate_hz']} Hz; latency p50 {lat['p50']} ms p99 {lat['p99']} ms")
    for note in rep.get("notes", []):
        print(f"note: {note}")
    print(f"outcome: {rep['outcome']}")
    print(f"report: {result.report_path}" + (f", plot: {result.plot_path}" if result.plot_path else ""))
    return 0 if rep["mission"]["completed"] else 1
