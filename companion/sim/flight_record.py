"""A simulated flight's record and report: frames and latencies, the autopilot's mode timeline, why a
mission failed, and the report files (``report.json``, ``trajectory.png``) of `companion sim`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from companion.sim.report import SimRecord, build_report, plot_trajectory

__all__ = ["AFTER_END_S", "close_record", "collect_frames", "failed_action", "finish_report", "flight_over",
           "note_autopilot_mode", "rack_outline"]


def finish_report(record: SimRecord, daemon: Any, config: Any, camera_model: Any, out_dir: Path, speed: float,
                  extra: dict[str, Any] | None = None) -> tuple[dict[str, Any], Path, Path | None]:
    """Build the report of a finished flight, write ``report.json`` and ``trajectory.png`` into `out_dir`."""
    report = build_report(record)
    nf = daemon.nav_filter
    if nf is not None:
        report["estimation"]["filter_counts"] = dict(nf.stats.counts)
        report["estimation"]["reset_counter"] = int(nf.stats.reset_counter)
    report["flight_folder"] = None if daemon.flight is None else str(daemon.flight.path)
    report["camera"] = {"width": camera_model.width, "height": camera_model.height, "fps": config.camera.fps}
    report["speed"] = speed
    if speed != 1.0:
        report["notes"].append(f"ran at {speed:g}x real time; rates are per simulated second, latencies in wall ms")
    report.update(extra or {})
    report_path = out_dir / "report.json"
    report_path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    plot_path: Path | None = out_dir / "trajectory.png"
    try:
        plot_trajectory(record, out_dir / "trajectory.png", rack_outline(config))
    except Exception as exc:
        record.notes.append(f"plot failed: {exc}")
        plot_path = None
    return report, report_path, plot_path


AFTER_END_S = 15.0  # how long a run goes on after a mission failed or was aborted with the vehicle in the air


def flight_over(ex: Any, armed: bool, now_s: float, ended: dict[str, float]) -> bool:
    """Whether the simulated flight is over: no mission, completed, or failed/aborted and either disarmed or
    `AFTER_END_S` later (what the safety manager and the autopilot did next is in the record by then).
    `ended` keeps the time the mission ended between calls."""
    from companion.mission import State

    if ex is None or ex.state is State.COMPLETED:
        return True
    if ex.state not in (State.FAILED, State.ABORTED):
        return False
    ended.setdefault("t", now_s)
    return not armed or now_s - ended["t"] >= AFTER_END_S


def close_record(record: SimRecord, daemon: Any, t0: float, now_s: float, timeout_s: float) -> None:
    """The end of a flight in the record: mission state, why it failed, timeout, safety events (since `t0`)."""
    from companion.mission import State
    from companion.sim.report import SafetyEventRecord

    ex = daemon.executor
    record.mission_state = "not-started" if ex is None else str(ex.state)
    record.mission_completed = ex is not None and ex.state is State.COMPLETED
    if ex is not None and ex.state not in (State.COMPLETED, State.FAILED, State.ABORTED):
        record.notes.append(f"timed out after {timeout_s:.0f} s")
    record.failed_action = failed_action(ex)
    record.end_s = now_s
    for ev in daemon._safety_view.events:
        record.safety_events.append(SafetyEventRecord(
            time_s=float(ev["time_s"]) - t0, kind=str(ev["kind"]), action=str(ev["action"]),
            detail=str(ev["message"])))


def note_autopilot_mode(record: SimRecord, elapsed_s: float, mode: str | None, armed: bool) -> None:
    """Append the autopilot's (mode, armed) to the record's timeline when it changed."""
    now = (str(mode), bool(armed))
    if not record.autopilot_modes or record.autopilot_modes[-1][1:] != now:
        record.autopilot_modes.append((round(elapsed_s, 2), *now))


def failed_action(ex: Any) -> str:
    """"action N KIND 'ID' RESULT: MESSAGE" of the first action that did not succeed, or ""."""
    for r in [] if ex is None else ex.results:
        if r.result != "succeeded":
            return f"action {r.index + 1} {r.action} '{r.action_id}' {r.result}: {r.message}"
    return ""


def collect_frames(frames_seen: list[Any], render: Any, vpe: list[Any], boot_s: float, record: SimRecord,
                    speed: float = 1.0, stamp_base: str = "autopilot") -> None:
    """Estimates, frame stamps and capture -> autopilot-socket latencies (wall ms) from the daemon's frames.

    A frame is "captured" when the renderer has finished the image (a real camera's frame exists once
    read out); the latency ends when the VISION_POSITION_ESTIMATE carrying its stamp was read from the
    autopilot's socket. Clock seconds are divided by `speed` to give wall time. `stamp_base` is the
    link's pose time base (`MavLink.pose_time_base`): "autopilot" stamps count from the fake
    autopilot's boot (`boot_s` on our clock), "local" ones are our clock's (PX4 by default).
    """
    sent_by_stamp: dict[int, Any] = {}
    for fr in frames_seen:
        record.frame_stamps_s.append(fr.capture_s)
        nav = fr.nav
        if bool(nav.ok):
            record.est_stamps_s.append(float(nav.stamp_s))
            record.est_positions_ned_m.append(np.asarray(nav.position_ned_m, dtype=np.float64).copy())
            record.est_rotations.append(np.asarray(nav.T_ned_body, dtype=np.float64)[:3, :3].copy())
            record.est_sources.append(str(nav.source))
        if fr.sent:
            sent_by_stamp[round(fr.capture_s * 1e3)] = fr
    done = render.done_clock_s
    for msg in vpe:
        record.pose_message_stamps_s.append(float(msg.time_s))
        usec = msg.fields["usec"] if "usec" in msg.fields else msg.fields["time_usec"]  # VISION_* or ODOMETRY
        stamp_s = float(usec) * 1e-6 + (boot_s if stamp_base == "autopilot" else 0.0)
        fr = sent_by_stamp.get(round(stamp_s * 1e3))
        if fr is None:
            for k in (-1, 1):
                fr = sent_by_stamp.get(round(stamp_s * 1e3) + k)
                if fr is not None:
                    break
        if fr is None:
            continue
        ready_s = done[fr.seq] if 0 <= fr.seq < len(done) else fr.capture_s
        record.latencies_ms.append((float(msg.time_s) - ready_s) * 1e3 / speed)


def rack_outline(config: Any) -> list[Any]:
    from companion.geometry import se3
    from companion.sim.render import paper_rack_model

    model = paper_rack_model()
    if config.rack.model:
        from companion.vision.rack import RackModel

        model = RackModel.load(config.rack.model)
    T = config.rack.T_ned_rack
    outlines = []
    for pipe in model.pipes():
        start = np.asarray(pipe.start_m)
        d = np.asarray(pipe.direction_unit)
        side = np.cross(d, [0.0, 0.0, 1.0])
        n = float(np.linalg.norm(side))
        side = side / n if n > 1e-9 else np.array([1.0, 0.0, 0.0])
        r = pipe.radius
        end = start + d * pipe.length
        corners = np.array([start - side * r, end - side * r, end + side * r, start + side * r])
        outlines.append(se3.act(T, corners)[:, :2])
    return outlines
