"""`companion sim` results: the report.json figures and the trajectory plot.

`SimRecord` is what the simulator run collects while flying; `build_report`
turns it into the JSON document of DESIGN.md ("report.json has at least ...")
and `plot_trajectory` draws DIR/trajectory.png with matplotlib's Agg backend.
Positions are NED metres, stamps seconds on the run's monotonic clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.geometry import so3

__all__ = [
    "ActionResult",
    "SafetyEventRecord",
    "SimRecord",
    "build_report",
    "interpolate_positions",
    "plot_trajectory",
    "rotation_error_deg",
]


@dataclass(frozen=True)
class ActionResult:
    """One finished mission action: its name, ``result`` ("success" | "failed" | "timeout" | "aborted"), duration."""

    index: int
    name: str
    result: str
    seconds: float
    goal_ned_m: tuple[float, float, float] | None = None
    true_error_m: float | None = None


@dataclass(frozen=True)
class SafetyEventRecord:
    """A safety decision: run time (s since start), kind and the action taken."""

    time_s: float
    kind: str
    action: str
    detail: str = ""


@dataclass
class SimRecord:
    """Everything a simulated flight collects (mutable accumulator owned by the sim runner)."""

    start_s: float = 0.0
    end_s: float = 0.0
    truth_stamps_s: list[float] = field(default_factory=list)
    truth_positions_ned_m: list[FloatArray] = field(default_factory=list)
    truth_rotations: list[FloatArray] = field(default_factory=list)
    est_stamps_s: list[float] = field(default_factory=list)
    est_positions_ned_m: list[FloatArray] = field(default_factory=list)
    est_rotations: list[FloatArray] = field(default_factory=list)
    est_sources: list[str] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    pose_message_stamps_s: list[float] = field(default_factory=list)
    frame_stamps_s: list[float] = field(default_factory=list)
    goals_ned_m: list[tuple[float, float, float]] = field(default_factory=list)
    actions: list[ActionResult] = field(default_factory=list)
    safety_events: list[SafetyEventRecord] = field(default_factory=list)
    mission_completed: bool = False
    mission_name: str = ""
    mission_state: str = ""
    autopilot: str = ""
    faults: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    # what the autopilot did, from its own reports: (seconds since the mission start, mode, armed)
    autopilot_modes: list[tuple[float, str, bool]] = field(default_factory=list)
    failed_action: str = ""  # "action 9 servo 'p3-start' aborted: safety: land" when the mission did not complete


def interpolate_positions(stamps_s: FloatArray, positions: FloatArray, query_s: FloatArray) -> FloatArray:
    """Linear interpolation of positions (N, 3) sampled at increasing `stamps_s` at `query_s` (M,) -> (M, 3)."""
    out = np.empty((query_s.shape[0], 3))
    for k in range(3):
        out[:, k] = np.interp(query_s, stamps_s, positions[:, k])
    return out


def rotation_error_deg(R_true: FloatArray, R_est: FloatArray) -> FloatArray:
    """Angle (deg) of R_true^T R_est for stacks (N, 3, 3)."""
    R_err = np.einsum("nji,njk->nik", R_true, R_est)
    out: FloatArray = np.degrees(np.linalg.norm(so3.log(R_err), axis=-1))
    return out


def _nearest_index(stamps_s: FloatArray, query_s: FloatArray) -> Any:
    idx = np.searchsorted(stamps_s, query_s).clip(1, max(1, stamps_s.shape[0] - 1))
    left = stamps_s[idx - 1]
    right = stamps_s[np.minimum(idx, stamps_s.shape[0] - 1)]
    return np.where(np.abs(query_s - left) <= np.abs(right - query_s), idx - 1, idx).clip(0, stamps_s.shape[0] - 1)


def estimation_errors(record: SimRecord) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-estimate (stamps_s, position error m, orientation error deg) against interpolated truth."""
    if not record.truth_stamps_s or not record.est_stamps_s:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    t_true = np.asarray(record.truth_stamps_s)
    p_true = np.asarray(record.truth_positions_ned_m)
    t_est = np.asarray(record.est_stamps_s)
    inside = (t_est >= t_true[0]) & (t_est <= t_true[-1])
    t_est = t_est[inside]
    p_est = np.asarray(record.est_positions_ned_m)[inside]
    pos_err = np.linalg.norm(interpolate_positions(t_true, p_true, t_est) - p_est, axis=1)
    R_true = np.asarray(record.truth_rotations)[_nearest_index(t_true, t_est)]
    R_est = np.asarray(record.est_rotations)[inside]
    rot_err = rotation_error_deg(R_true, R_est) if t_est.size else np.zeros(0)
    return t_est, pos_err, rot_err


def _stat(values: FloatArray, fn: str) -> float | None:
    if values.size == 0:
        return None
    if fn == "rms":
        return float(math.sqrt(float(np.mean(values**2))))
    if fn == "max":
        return float(np.max(values))
    if fn == "p50":
        return float(np.percentile(values, 50))
    if fn == "p99":
        return float(np.percentile(values, 99))
    if fn == "mean":
        return float(np.mean(values))
    raise ValueError(fn)


def _rate_hz(stamps_s: list[float]) -> float | None:
    if len(stamps_s) < 2:
        return None
    t = np.sort(np.asarray(stamps_s))
    span = float(t[-1] - t[0])
    return (t.size - 1) / span if span > 0 else None


def _round(value: float | None, ndigits: int) -> float | None:
    return None if value is None else round(value, ndigits)


def build_report(record: SimRecord) -> dict[str, Any]:
    """The report.json document of a simulated flight (DESIGN.md fields plus context)."""
    _, pos_err, rot_err = estimation_errors(record)
    lat = np.asarray(record.latencies_ms, dtype=np.float64)
    waypoint_errors = [a.true_error_m for a in record.actions if a.true_error_m is not None]
    return {
        "mission": {
            "name": record.mission_name,
            "completed": bool(record.mission_completed),
            "state": record.mission_state,
            "duration_s": round(record.end_s - record.start_s, 3),
            "actions": [
                {"index": a.index, "name": a.name, "result": a.result, "seconds": round(a.seconds, 3)}
                for a in record.actions
            ],
        },
        "autopilot": record.autopilot,
        "faults": list(record.faults),
        "waypoint_errors_m": [round(float(e), 4) for e in waypoint_errors],
        "waypoint_error_max_m": _round(max(waypoint_errors), 4) if waypoint_errors else None,
        "estimation": {
            "samples": int(pos_err.size),
            "rms_position_m": _round(_stat(pos_err, "rms"), 4),
            "max_position_m": _round(_stat(pos_err, "max"), 4),
            "rms_orientation_deg": _round(_stat(rot_err, "rms"), 3),
            "max_orientation_deg": _round(_stat(rot_err, "max"), 3),
        },
        "pose_messages": {
            "count": len(record.pose_message_stamps_s),
            "rate_hz": _round(_rate_hz(record.pose_message_stamps_s), 2),
            "camera_rate_hz": _round(_rate_hz(record.frame_stamps_s), 2),
        },
        "latency_ms": {
            "samples": int(lat.size),
            "p50": _round(_stat(lat, "p50"), 3),
            "p99": _round(_stat(lat, "p99"), 3),
            "max": _round(_stat(lat, "max"), 3),
        },
        "safety": {
            "events": [
                {"time_s": round(e.time_s, 3), "kind": e.kind, "action": e.action, "detail": e.detail}
                for e in record.safety_events
            ],
        },
        "autopilot_modes": [{"time_s": round(t, 2), "mode": m, "armed": a} for t, m, a in record.autopilot_modes],
        "outcome": outcome_line(record),
        "notes": list(record.notes),
    }


def outcome_line(record: SimRecord) -> str:
    """One line: how the mission ended and why, what the safety manager and the autopilot did, with times."""
    if record.mission_completed:
        head = "completed"
    else:
        why = record.failed_action or "; ".join(record.notes) or record.mission_state
        head = f"NOT completed ({record.mission_state}): {why}"
    actions = [f"{e.action} at {e.time_s:.1f} s ({e.detail.split('(')[-1].rstrip(')')})"
               for e in record.safety_events if e.kind == "action" and e.time_s >= 0.0]
    limits: dict[str, float] = {}  # first clamp of each limit (ceiling, clearance, geofence): not an action
    for e in record.safety_events:
        if e.kind in ("ceiling", "ceiling-clearance", "geofence") and e.time_s >= 0.0:
            limits.setdefault(e.kind, e.time_s)
    actions += [f"{kind} clamp from {t:.1f} s" for kind, t in limits.items()]
    modes = []
    for k, (t, mode, armed) in enumerate(record.autopilot_modes):
        if k and not armed and record.autopilot_modes[k - 1][2]:
            modes.append(f"disarmed at {t:.1f} s")
        elif not k or mode != record.autopilot_modes[k - 1][1]:
            modes.append(f"{mode} at {t:.1f} s")
    return (f"{head}; safety: {', '.join(actions) or 'no action'}; "
            f"autopilot: {', '.join(modes) or 'no report'}")


def plot_trajectory(record: SimRecord, path: Path, rack_outline_ned: list[FloatArray] | None = None) -> None:
    """Write the trajectory figure: top view (truth, estimate, commanded path, rack), side view, error over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 5.5))
    ax_top, ax_side, ax_err = axes
    if rack_outline_ned:
        for k, outline in enumerate(rack_outline_ned):
            ax_top.fill(outline[:, 1], outline[:, 0], color="0.85", edgecolor="0.5",
                        label="rack pipes" if k == 0 else None)
    t0 = record.start_s
    if record.truth_stamps_s:
        p = np.asarray(record.truth_positions_ned_m)
        ax_top.plot(p[:, 1], p[:, 0], "-", color="tab:blue", lw=1.5, label="true")
        ax_side.plot(np.asarray(record.truth_stamps_s) - t0, -p[:, 2], "-", color="tab:blue", lw=1.5, label="true")
    if record.est_stamps_s:
        p = np.asarray(record.est_positions_ned_m)
        ax_top.plot(p[:, 1], p[:, 0], "--", color="tab:orange", lw=1.0, label="estimated")
        ax_side.plot(np.asarray(record.est_stamps_s) - t0, -p[:, 2], "--", color="tab:orange", lw=1.0,
                     label="estimated")
    if record.goals_ned_m:
        g = np.asarray(record.goals_ned_m)
        ax_top.plot(g[:, 1], g[:, 0], ":o", color="tab:green", ms=4, lw=1.0, label="commanded")
    ax_top.set_xlabel("east (m)")
    ax_top.set_ylabel("north (m)")
    ax_top.set_title("top view (NED)")
    ax_top.axis("equal")
    ax_top.grid(True, alpha=0.3)
    if ax_top.get_legend_handles_labels()[0]:
        ax_top.legend(loc="best", fontsize=8)
    ax_side.set_xlabel("time (s)")
    ax_side.set_ylabel("height above origin (m)")
    ax_side.set_title("height")
    ax_side.grid(True, alpha=0.3)
    if ax_side.get_legend_handles_labels()[0]:
        ax_side.legend(loc="best", fontsize=8)
    t_est, pos_err, rot_err = estimation_errors(record)
    if t_est.size:
        ax_err.plot(t_est - t0, pos_err * 100.0, color="tab:red", lw=1.0, label="position (cm)")
        ax_err.plot(t_est - t0, rot_err, color="tab:purple", lw=1.0, label="orientation (deg)")
    for e in record.safety_events:
        ax_err.axvline(e.time_s, color="k", lw=0.8, ls=":")
    ax_err.set_xlabel("time (s)")
    ax_err.set_title("estimation error")
    ax_err.grid(True, alpha=0.3)
    if ax_err.get_legend_handles_labels()[0]:
        ax_err.legend(loc="best", fontsize=8)
    status = "completed" if record.mission_completed else "NOT completed"
    fig.suptitle(f"companion sim: {record.mission_name} ({record.autopilot}) - mission {status}")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
