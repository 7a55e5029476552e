"""`companion sim --autopilot ardupilot-sitl`: the embedded simulation against the real ArduCopter SITL.

Same world, mission, daemon and report as `companion sim` with the fake autopilot, but the flight
controller is ArduPilot's own firmware (`companion.sim.ardupilot_sitl`, real time only): the SITL's
home is the config's EKF origin with heading 0 (north = the rack's +y), the synthetic camera
renders from ArduPilot's SIM_STATE, and the truth of the report is SIM_STATE as seen by a second
MAVLink client that also plays the GCS. The daemon starts from the configured nominal pose (the
origin, facing north), not from the simulator's truth.

Faults: vision-loss and camera-unplug at the camera; battery-sag / battery-critical through
SIM_BATT_VOLTAGE; gcs-loss by stopping the GCS heartbeats. link-loss and ceiling have no SITL
counterpart here and are refused with one line.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from types import SimpleNamespace
from typing import Any, TextIO

import numpy as np

from companion.clock import SystemClock
from companion.errors import CompanionError, InputError
from companion.sim.report import SimRecord

__all__ = ["SITL_FAULTS", "run_sim_sitl"]

SITL_FAULTS = ("battery-sag", "battery-critical", "gcs-loss", "vision-loss", "camera-unplug")
_VOLTS_3S = {"battery-sag": 10.8, "battery-critical": 10.2}  # the SITL's battery is a 3S pack (12.6 V full)


def _fault_actions(options: Any, rig: Any, t0: float) -> list[tuple[float, str, Any]]:
    """(time, what, argument) steps of the scheduled faults, on the monotonic clock."""
    steps: list[tuple[float, str, Any]] = []
    for f in options.faults:
        if f.kind not in SITL_FAULTS:
            raise InputError(f"--fault {f.text()}: not available with --autopilot ardupilot-sitl "
                             f"(one of {', '.join(SITL_FAULTS)})")
        start = t0 + f.at_s
        end = math.inf if f.duration_s is None else start + f.duration_s
        if f.kind in ("vision-loss", "camera-unplug"):
            rig.render.windows.append((f.kind, start, end))
        elif f.kind == "gcs-loss":
            steps += [(start, "gcs", False)] + ([(end, "gcs", True)] if math.isfinite(end) else [])
        else:
            steps += [(start, "volts", _VOLTS_3S[f.kind])] + ([(end, "volts", 12.6)] if math.isfinite(end) else [])
    return sorted(steps, key=lambda s: s[0])


async def run_sim_sitl(options: Any, out: TextIO) -> Any:
    """Fly `options`' mission on the ArduCopter SITL; returns a `companion.sim.run.SimResult`."""
    from companion.config import mission_limits
    from companion.daemon.app import Daemon, DaemonOptions
    from companion.data import data_path
    from companion.mission import load_mission
    from companion.sim.ardupilot_sitl import ArduPilotSitl, SitlError, SitlObserver, sitl_binary
    from companion.sim.flight_record import close_record, finish_report, flight_over, note_autopilot_mode
    from companion.sim.render import FaultyRender, SceneRenderer
    from companion.sim.run import SimResult, _collect_results, _progress_line, sim_config
    from drivers.camera import load_camera_model

    binary = sitl_binary()
    if binary is None:
        raise SitlError("--autopilot ardupilot-sitl: no ArduCopter SITL binary (set COMPANION_ARDUPILOT_SITL or "
                        "put ../shared/ardupilot/arducopter beside the source tree)")
    if options.speed != 1.0:
        raise InputError("--speed: the ArduPilot SITL runs in real time only")
    clock = SystemClock()
    out_dir = options.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    mission_path = options.mission_path or data_path("missions/paper_sweep.xml")
    from companion.sim.config_set import merge_overrides

    config = sim_config(out_dir, merge_overrides({"safety": {"battery_low_v": 11.1, "battery_critical_v": 10.5}},
                                                 options.config_overrides))
    origin = (config.ekf_origin.lat_deg, config.ekf_origin.lon_deg, config.ekf_origin.alt_m)
    mission = load_mission(mission_path, limits=mission_limits(config))
    camera_model = load_camera_model(config.camera)
    record = SimRecord(mission_name=mission.name, autopilot="ardupilot-sitl", faults=[f.text() for f in options.faults])
    timeout_s = options.max_duration_s or (sum(a.timeout_s for a in mission.actions) + 60.0)
    # the fake's wind: `wind_m_s` from 60 deg with light turbulence; the Dryden intensity of light turbulence
    # at low altitude is ~0.1 x the wind speed, so SIM_WIND_TURB (m/s) gets that (1 m/s of turbulence in
    # a 2 m/s wind is a gale's gustiness, not the fake's)
    wind = {"SIM_WIND_SPD": options.wind_m_s if options.wind else 0.0, "SIM_WIND_DIR": 60.0,
            "SIM_WIND_TURB": 0.1 * options.wind_m_s if options.wind else 0.0}
    print(f"starting the ArduCopter SITL ({binary})", file=out, flush=True)
    from companion.sim.start_error import StartError, offset_lla, start_hint, start_pose

    start = start_pose(options.start_error or StartError(), options.seed)  # --start-error: boot away from it
    home = offset_lla(origin, start.north_m, start.east_m)
    heading_deg = math.degrees(start.yaw_rad) % 360.0
    with ArduPilotSitl(binary, home=f"{home[0]:.9f},{home[1]:.9f},{home[2]},{heading_deg:.2f}",
                       extra_params=wind) as sitl:
        config = dataclasses.replace(config, mavlink=dataclasses.replace(config.mavlink, url=sitl.url))
        base = SceneRenderer.from_config(config, camera_model, seed=options.seed)
        base(np.eye(4))  # warm the renderer's caches
        render = FaultyRender(base, clock.now)
        daemon = Daemon(config, clock=clock, options=DaemonOptions(
            render=render, api=False, sdnotify=False,
            initial_T_ned_body=start_hint(start, seed_true_pose=options.seed_true_pose),
            flight_root=out_dir / "flights", visual_ground_z_ned_m=None,
            rack_along_pipe_std_m=options.rack_along_pipe_std_m))
        frames_seen: list[Any] = []
        daemon.frame_observers.append(frames_seen.append)
        async with daemon:
            observer = SitlObserver(sitl.observer_url, origin)
            await asyncio.get_running_loop().run_in_executor(None, observer.start)
            try:
                t_wait = clock.now() + 30.0
                while clock.now() < t_wait and daemon.counters.poses_sent < 10:
                    await asyncio.sleep(0.1)
                t0 = clock.now()
                record.start_s = t0
                steps = _fault_actions(options, SimpleNamespace(render=render), t0)
                try:
                    await daemon.start_mission(mission, mission_path.stem)
                except CompanionError as exc:
                    record.notes.append(f"mission refused: {exc}")
                last_print = -math.inf
                ended: dict[str, float] = {}
                truth_view = SimpleNamespace(truth=SimpleNamespace(position_ned_m=np.zeros(3)))
                while clock.now() - t0 < timeout_s:
                    await asyncio.sleep(0.05)
                    while steps and steps[0][0] <= clock.now():
                        _, what, arg = steps.pop(0)
                        if what == "gcs":
                            observer.gcs_heartbeat = bool(arg)
                        else:
                            await asyncio.get_running_loop().run_in_executor(
                                None, observer.set_param, "SIM_BATT_VOLTAGE", float(arg))
                    T = observer.truth_T_ned_body()
                    if T is None:
                        continue
                    truth = SimpleNamespace(position_ned_m=T[:3, 3], height_m=-float(T[2, 3]))
                    truth_view.truth = truth
                    record.truth_stamps_s.append(clock.now())
                    record.truth_positions_ned_m.append(T[:3, 3].copy())
                    record.truth_rotations.append(T[:3, :3].copy())
                    if clock.now() - t0 - last_print >= 5.0:
                        last_print = clock.now() - t0
                        print(_progress_line(clock.now() - t0, daemon, truth), file=out, flush=True)
                    note_autopilot_mode(record, clock.now() - t0, observer.mode, observer.armed)
                    _collect_results(daemon, record, truth_view)
                    if flight_over(daemon.executor, observer.armed, clock.now(), ended):
                        break
                close_record(record, daemon, t0, clock.now(), timeout_s)
                _collect_results(daemon, record, truth_view)
                autopilot_texts = [t for t in observer.statustexts(t0) if not t.startswith(("companion", "SAFETY"))]
            finally:
                observer.stop()
        _collect_frames_sitl(frames_seen, render, record)
    extra = {"autopilot_texts": autopilot_texts[-40:],
             "sitl": {"binary": str(binary), "home": f"{origin[0]},{origin[1]},{origin[2]},0"}}
    report, report_path, plot_path = finish_report(record, daemon, config, camera_model, out_dir, 1.0, extra)
    return SimResult(record=record, report=report, report_path=report_path, plot_path=plot_path, frames=frames_seen)


def _collect_frames_sitl(frames_seen: list[Any], render: Any, record: SimRecord) -> None:
    """Estimates and capture -> socket latencies from the daemon's frames (ArduPilot has no receive log)."""
    done = render.done_clock_s
    for fr in frames_seen:
        record.frame_stamps_s.append(fr.capture_s)
        nav = fr.nav
        if bool(nav.ok):
            record.est_stamps_s.append(float(fr.source_stamp_s if fr.source_stamp_s is not None else nav.stamp_s))
            record.est_positions_ned_m.append(np.asarray(nav.position_ned_m, dtype=np.float64).copy())
            record.est_rotations.append(np.asarray(nav.T_ned_body, dtype=np.float64)[:3, :3].copy())
            record.est_sources.append(str(nav.source))
        if fr.sent:
            record.pose_message_stamps_s.append(float(fr.sent_s))
            ready_s = done[fr.seq] if 0 <= fr.seq < len(done) else fr.capture_s
            record.latencies_ms.append((float(fr.sent_s) - ready_s) * 1e3)
