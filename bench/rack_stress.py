"""Benchmark: the rack tracker on scenes it was not tuned on (issue #14). Prints ONE JSON object.

Frames come from the second appearance model, `companion.sim.rack_scene_field.FieldRackScene`
(F sparse spots in total, high-contrast grounds, pale shaded cladding, beams, shadows, gain
steps, motion blur, JPEG q70, lens distortion), at 720x480, f = 630, 25 Hz, noise 6 grey levels,
optical blur 0.7 px. The tracker is driven through its public API only (`reset` 1 cm / 0.5 deg
off the true first pose, then `track`). Trajectories: the MATLAB repository's tour (±1 m across,
±1 m along, yaw ±0.2 rad, then 0.5 m down; 0.5 m/s, 0.2 rad/s) with low-pass wind (2 cm,
0.7 deg), its fast variant (0.8 m/s, 0.4 rad/s) and a flight along the pipes.

The matrix (CELLS x SEEDS) and the split of the seeds into a tuning half and a held-back half
were frozen before any tuning; the held-back half is run once, at the end. Rows (tracker
configurations) run on the same frames: `vision` (default config, vision only), `edge_only`
(texture off), `prior` (vision + the gravity direction from an attitude with 0.3 deg white
noise per axis and frame). Per cell and row: RMS and max position / orientation errors, and the RMS
along the rack's axes (x across the pipes, y along them, z up; rotation about each), lost frames and
frames/s (OpenCV on one thread: `one_thread()`). Each (cell, seed) frame set is rendered once and
cached as the camera's JPEG bytes (`--cache-dir`), keyed by the scene and trajectory code, so reruns
time only the tracker.

Usage: python bench/rack_stress.py [--seeds tuning|heldback|all] [--quick] [--cells a,b] [--rows vision,edge_only]
       [--set name=value ...] (override RackTrackerConfig fields of every row, for trying changes)
       [--plain-allocator] (glibc's default heap thresholds; by default this process keeps freed memory for the
       next frame as the daemon's does, drivers/allocator.py: it changes the frames/s, not the estimates)
The tracker's compiled kernels (numba, companion/jit.py) are used when available; `COMPANION_JIT=0` in the
environment runs its numpy code instead (the same estimates, slower). The JSON names the kernel sets used.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import hashlib  # noqa: E402
import inspect  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from companion.camera import PinholeCamera  # noqa: E402
from companion.geometry import se3, so3  # noqa: E402
from companion.jit import compiled_names  # noqa: E402
from companion.sim import rack_scene_field, rack_scene_field_world  # noqa: E402
from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig, decode_frame  # noqa: E402
from companion.vision.rack import Pipe, RackModel, RackTracker, RackTrackerConfig  # noqa: E402
from drivers.allocator import keep_freed_memory  # noqa: E402

CAMERA = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
# Mild barrel distortion (about 5 px at the corners) and its calibration, given to the tracker too.
CAMERA_DIST = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0,
                            dist=(-0.04, 0.008, 0.0, 0.0))
RATE_HZ = 25.0
NOISE_STD = 6.0
BLUR_PX = 0.7
EXPOSURE_FRACTION = 0.2  # shutter open for 8 ms of the 40 ms frame period
START_OFF_M, START_OFF_RAD = 0.01, np.radians(0.5)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
PAPER_RADII = (0.15, 0.20, 0.15, 0.175)


def paper_s5_rack(gaps: tuple[float, float, float] = (0.1, 0.1, 0.1)) -> RackModel:
    """The paper's §V rack: 4 parallel pipes (15-20 cm, 10 cm gaps, 10 m) and one crossing on top at y = 5 m."""
    cross = Pipe(radius=0.15, start=(-0.5, 5.0, 2 * 0.20 + 0.15 + 0.02), direction=(1.0, 0.0, 0.0), length=2.8)
    return RackModel.parallel(radii=PAPER_RADII, gaps=list(gaps), length=10.0, extra=[cross])


def parallel_rack(n: int) -> RackModel:
    return RackModel.parallel(radii=(0.15, 0.20, 0.15, 0.175, 0.20)[:n], gaps=[0.1] * (n - 1), length=10.0)


# ---------------------------------------------------------------- the frozen matrix
# name: rack, F, spot range, ground, overhead beams (y), distortion, gain steps, trajectory, tracker's gaps
CELLS: dict[str, dict[str, Any]] = {
    "p2_f10_concrete_tour": dict(rack="p2", F=10, ground="concrete", traj="tour"),
    "p3_f20_natural_fast": dict(rack="p3", F=20, ground="natural", traj="fast"),
    "p4_f40_grating_tour": dict(rack="p4", F=40, ground="grating", traj="tour"),
    "p5_f50_natural_tour_gain": dict(rack="p5", F=50, ground="natural", traj="tour", gain=True),
    "paper_s5_f100_concrete_tour": dict(rack="paper_s5", F=100, ground="concrete", traj="tour"),
    "paper_s5_wronggaps_grating_tour": dict(rack="paper_s5", F=40, ground="grating", traj="tour",
                                            model_gaps=(0.15, 0.20, 0.15)),
    "p4_f10_along_nospots_natural": dict(rack="p4", F=10, spots_y=(3.6, 10.0), ground="natural", traj="along"),
    "p5x_f50_concrete_fast_distort_beam_gain": dict(rack="paper_5pipe", F=50, ground="concrete", traj="fast",
                                                    distort=True, overhead=(6.9,), gain=True),
    "p4_f20_grating_tour_distort_beam_gain": dict(rack="p4", F=20, ground="grating", traj="tour", distort=True,
                                                  overhead=(5.3,), gain=True),
}
TUNING_SEEDS = (0, 1)
HELDBACK_SEEDS = (2, 3)
# More tuning seeds for diagnosing one cell (`--seeds extra --cells ...`); never reported as held back.
EXTRA_SEEDS = tuple(range(4, 20))


def build_rack(name: str) -> RackModel:
    if name == "paper_s5":
        return paper_s5_rack()
    if name == "paper_5pipe":
        return RackModel.load(ROOT / "missions" / "racks" / "paper_5pipe.toml")
    return parallel_rack(int(name[1:]))


def coloured(rng: np.random.Generator, n: int, dim: int, sigma: float, tau_s: float) -> np.ndarray:
    """Twice low-pass filtered white noise (a wind / AHRS error spectrum), std ~ sigma."""
    a = np.exp(-1.0 / (RATE_HZ * tau_s))
    m = n + 200
    w = rng.standard_normal((m, dim))
    x = np.zeros((m, dim))
    y = np.zeros((m, dim))
    for k in range(1, m):
        x[k] = a * x[k - 1] + np.sqrt(1 - a * a) * w[k]
        y[k] = a * y[k - 1] + np.sqrt(1 - a * a) * x[k]
    y = y[200:]
    return np.asarray(sigma * y / max(float(y.std()), 1e-9))


def _profile(distance: float, v_max: float, ramp_s: float) -> np.ndarray:
    """Fraction (0..1) covered per frame of a move at <= v_max with cosine velocity ramps (continuous acceleration)."""
    if distance <= 1e-9:
        return np.zeros(0)
    v = min(v_max, distance / ramp_s)
    total = distance / v + ramp_s
    t = np.arange(1, int(np.ceil(total * RATE_HZ)) + 1) / RATE_HZ
    fine = np.linspace(0.0, total, 4000)
    vel = np.where(fine < ramp_s, 0.5 * (1 - np.cos(np.pi * fine / ramp_s)), 1.0)
    vel = np.minimum(vel, np.where(fine > total - ramp_s, 0.5 * (1 - np.cos(np.pi * (total - fine) / ramp_s)), 1.0))
    s = np.concatenate([[0.0], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * np.diff(fine))])
    return np.asarray(np.interp(t, fine, s / s[-1]))


def make_trajectory(kind: str, model: RackModel, rng: np.random.Generator) -> list[np.ndarray]:
    """Camera poses T_rack_cam per frame: tour, fast tour or along the pipes, with wind."""
    arr = model.pipe_arrays()
    n_par = model.num_parallel
    centre_x = 0.5 * float(arr.starts[n_par - 1, 0] + arr.radii[n_par - 1])
    top = 2.0 * float(max(model.radii))
    h = top + float(rng.uniform(1.6, 2.4))
    y0 = float(rng.uniform(4.0, 4.6))
    start = np.array([centre_x, y0, h, 0.0])
    if kind == "along":
        moves = [np.array([0.0, 4.0, 0.0, 0.0])]
        start[1] = 1.0
        v, w, ramp = 0.5, 0.2, 0.8
    else:
        # +1 across, to -1 across, back across while going +1 along, to -1 along, back along with yaw
        # +0.2, yaw to -0.2, back to 0 while descending 0.5 m.
        moves = [np.array(m) for m in ([1, 0, 0, 0], [-2, 0, 0, 0], [1, 1, 0, 0], [0, -2, 0, 0], [0, 1, 0, 0.2],
                                       [0, 0, 0, -0.4], [0, 0, -0.5, 0.2])]
        v, w, ramp = (0.5, 0.2, 0.8) if kind == "tour" else (0.8, 0.4, 0.6)
    pts = [start]
    for mv in moves:
        d_lin, d_ang = float(np.linalg.norm(mv[:3])), abs(float(mv[3]))
        # One fraction profile per move, slow enough for both the linear and the angular limit.
        frac = _profile(1.0, min(v / max(d_lin, 1e-9), w / max(d_ang, 1e-9)), ramp)
        base = pts[-1].copy()
        pts.extend(base + f * mv for f in frac)
    P = np.array(pts)
    n = P.shape[0]
    wind_p = coloured(rng, n, 3, 0.02, 0.8)
    wind_a = coloured(rng, n, 3, 1.0, 0.6) * np.radians([0.7, 0.7, 0.35])
    return [se3.make(so3.exp(wind_a[k]) @ so3.exp([0.0, 0.0, P[k, 3]]) @ R_DOWN, P[k, :3] + wind_p[k])
            for k in range(n)]


def _source_key(cell: dict[str, Any], seed: int) -> str:
    """Cache key: the cell, the seed and the code that makes the frames."""
    h = hashlib.sha256()
    h.update(repr((sorted(cell.items()), seed)).encode())
    for module in (rack_scene_field, rack_scene_field_world):
        h.update(Path(module.__file__).read_bytes())
    for fn in (make_trajectory, _profile, coloured, render_run, build_rack, paper_s5_rack):
        h.update(inspect.getsource(fn).encode())
    return h.hexdigest()[:20]


def render_run(name: str, cell: dict[str, Any], seed: int, ground_albedo: np.ndarray | None = None,
               ground_texel_m: float | None = None) -> dict[str, Any]:
    """Poses, camera and JPEG frames of one (cell, seed); `ground_albedo` (and its texel, m) replaces the
    procedural ground with an image (`bench/rack_photo_ground.py`)."""
    cell_seed = int(hashlib.sha256(f"{name}/{seed}".encode()).hexdigest()[:8], 16)
    rng = np.random.default_rng(cell_seed)
    model = build_rack(cell["rack"])
    texel = {} if ground_texel_m is None else {"ground_texel_m": float(ground_texel_m)}
    cfg = FieldSceneConfig(num_spots=cell["F"], spots_y_m=cell.get("spots_y"), ground=cell["ground"],
                           overhead_beams_y_m=tuple(cell.get("overhead", ())), **texel)
    scene = FieldRackScene(model, seed=cell_seed, config=cfg, ground_albedo=ground_albedo)
    cam = CAMERA_DIST if cell.get("distort") else CAMERA
    poses = make_trajectory(cell["traj"], model, rng)
    gains = np.ones(len(poses))
    if cell.get("gain"):  # auto-exposure steps every 3 s
        for k0 in range(0, len(poses), 75):
            gains[k0:] = float(rng.choice([0.7, 0.85, 1.0, 1.15, 1.3]))
    frames = []
    for k, T in enumerate(poses):
        T_next = poses[min(k + 1, len(poses) - 1)]
        du, dv = scene.image_motion_px(T, T_next, cam)
        frames.append(scene.render_jpeg(T, cam, NOISE_STD, BLUR_PX, rng, gain=float(gains[k]),
                                        motion_blur_px=(EXPOSURE_FRACTION * du, EXPOSURE_FRACTION * dv)))
    return {"poses": poses, "frames": frames, "distort": bool(cell.get("distort")), "cell_seed": cell_seed}


def cached_pickle(path: Path | None, make: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """The dict pickled at `path`, or `make()` stored there (written whole, then renamed: an interrupted run
    leaves no half file); `path` None: `make()`, not stored."""
    if path is not None and path.exists():
        with path.open("rb") as f:
            data: dict[str, Any] = pickle.load(f)
        return data
    run = make()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        with tmp.open("wb") as f:
            pickle.dump(run, f)
        tmp.replace(path)
    return run


def load_run(name: str, cell: dict[str, Any], seed: int, cache: Path | None) -> dict[str, Any]:
    path = None if cache is None else cache / f"{name}_s{seed}_{_source_key(cell, seed)}.pkl"
    return cached_pickle(path, lambda: render_run(name, cell, seed))


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    dR = T_est[:3, :3].T @ T_true[:3, :3]
    ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), ang


def start_offset(rng: np.random.Generator) -> np.ndarray:
    """The start pose's offset from the true first pose (twist, 6): START_OFF_M and START_OFF_RAD in random
    directions (two draws of 3 from `rng`)."""
    dp = rng.standard_normal(3)
    dw = rng.standard_normal(3)
    return np.concatenate([START_OFF_M * dp / np.linalg.norm(dp), START_OFF_RAD * dw / np.linalg.norm(dw)])


def track_run(name: str, cell: dict[str, Any], seed: int, run: dict[str, Any], row: str, overrides: dict[str, Any],
              n_frames: int | None) -> dict[str, Any]:
    """One tracker over one run's frames: per-frame errors, lost frames, time inside track()."""
    true_model = build_rack(cell["rack"])
    model = true_model
    kw: dict[str, Any] = dict(overrides)
    if "model_gaps" in cell:
        model = paper_s5_rack(cell["model_gaps"])
        kw["estimate_gaps"] = True
    if row == "edge_only":
        kw["max_texture_points"] = 0
    cam = CAMERA_DIST if run["distort"] else CAMERA
    tracker = RackTracker(model, cam, RackTrackerConfig(**kw))
    rng = np.random.default_rng(run["cell_seed"] + 1)  # start offset (and attitude error) per run, not per row
    poses = run["poses"][:n_frames]
    tracker.reset(poses[0] @ se3.exp(start_offset(rng)))
    att_err = np.radians(0.3) * rng.standard_normal((len(poses), 3))  # white, 0.3 deg per axis
    perr, aerr, t_ms = [], [], []
    axes_err: list[np.ndarray] = []  # per frame: position (3, m) and rotation (3, rad) errors along the rack's axes
    lost = 0
    gaps_100 = None
    for k, T_true in enumerate(poses):
        img = decode_frame(run["frames"][k])
        extra: dict[str, Any] = {}
        if row == "prior":
            extra = {"R_prior": so3.exp(att_err[k]) @ T_true[:3, :3], "R_prior_std_rad": np.radians(0.3)}
        t0 = time.perf_counter()
        est = tracker.track(img, k / RATE_HZ, **extra)
        t_ms.append(1000.0 * (time.perf_counter() - t0))
        p, a = pose_errors(est.T_rack_cam, T_true)
        axes_err.append(np.concatenate([est.T_rack_cam[:3, 3] - T_true[:3, 3],
                                        so3.log(est.T_rack_cam[:3, :3] @ T_true[:3, :3].T)]))
        perr.append(p)
        aerr.append(a)
        lost += 0 if est.ok else 1
        if k == 100 and "model_gaps" in cell:
            gaps_100 = np.asarray(est.gaps) - true_model.cumulative_gaps
    return {"perr": perr, "aerr": aerr, "axes_err": axes_err, "lost": lost, "t_ms": t_ms,
            "gap_err_100_cm": None if gaps_100 is None else float(100 * np.abs(gaps_100).max())}


def summarize(results: list[dict[str, Any]]) -> dict[str, Any]:
    p = 100.0 * np.concatenate([r["perr"] for r in results])
    a = np.concatenate([r["aerr"] for r in results])
    t = np.concatenate([r["t_ms"][1:] for r in results])
    out: dict[str, Any] = {
        "rms_position_cm": float(np.sqrt(np.mean(p**2))), "max_position_cm": float(p.max()),
        "rms_orientation_deg": float(np.sqrt(np.mean(a**2))), "max_orientation_deg": float(a.max()),
        "per_seed_rms_position_cm": [float(100 * np.sqrt(np.mean(np.square(r["perr"])))) for r in results],
        "per_seed_rms_orientation_deg": [float(np.sqrt(np.mean(np.square(r["aerr"])))) for r in results],
        "lost_frames": int(sum(r["lost"] for r in results)), "frames": int(p.size),
        "fps": float(1000.0 / np.mean(t)), "median_track_ms": float(np.median(t)),
    }
    # Which directions the error lies in (rack axes: x across the pipes, y along them, z up): the pairs that few
    # parallel pipes leave weak are slide (x) with roll (about y) and along (y) with pitch (about x).
    e = np.array([v for r in results for v in r["axes_err"]])
    out["rms_position_rack_xyz_cm"] = [float(v) for v in 100.0 * np.sqrt(np.mean(e[:, :3] ** 2, axis=0))]
    out["rms_rotation_rack_xyz_deg"] = [float(v) for v in np.degrees(np.sqrt(np.mean(e[:, 3:] ** 2, axis=0)))]
    g = [r["gap_err_100_cm"] for r in results if r["gap_err_100_cm"] is not None]
    if g:
        out["max_gap_error_after_100_frames_cm"] = float(max(g))
    return out


def row_summary(cells: dict[str, dict[str, Any]], row: str) -> dict[str, Any]:
    names = [n for n in cells if row in cells[n]["rows"]]
    pos = {n: cells[n]["rows"][row]["rms_position_cm"] for n in names}
    ori = {n: cells[n]["rows"][row]["rms_orientation_deg"] for n in names}
    if not names:
        return {}
    worst = max(names, key=lambda n: max(pos[n] / 2.0, ori[n] / 0.3))  # relative to the acceptance bar
    return {
        "worst_cell": worst, "worst_position_cm": max(pos.values()), "worst_orientation_deg": max(ori.values()),
        "worst_position_cell": max(pos, key=lambda n: pos[n]), "worst_orientation_cell": max(ori, key=lambda n: ori[n]),
        "median_position_cm": float(np.median(list(pos.values()))),
        "median_orientation_deg": float(np.median(list(ori.values()))),
        "lost_frames": int(sum(cells[n]["rows"][row]["lost_frames"] for n in names)),
        "fps_mean_over_cells": float(np.mean([cells[n]["rows"][row]["fps"] for n in names])),
    }


def acceptance(cells: dict[str, dict[str, Any]], summary: dict[str, Any]) -> dict[str, bool]:
    v = {n: c["rows"]["vision"] for n, c in cells.items() if "vision" in c["rows"]}
    out: dict[str, bool] = {}
    if v:
        out["every_cell_2cm_0.3deg_no_lost"] = all(
            r["rms_position_cm"] <= 2.0 and r["rms_orientation_deg"] <= 0.3 and r["lost_frames"] == 0
            for r in v.values())
        out["median_cell_1cm_0.15deg"] = bool(summary["vision"]["median_position_cm"] <= 1.0
                                              and summary["vision"]["median_orientation_deg"] <= 0.15)
        s5 = v.get("paper_s5_f100_concrete_tour")
        if s5:
            out["paper_s5_1.5cm_0.25deg"] = s5["rms_position_cm"] <= 1.5 and s5["rms_orientation_deg"] <= 0.25
        p2 = v.get("p2_f10_concrete_tour")
        if p2:
            out["p2_f10_2cm_0.3deg"] = p2["rms_position_cm"] <= 2.0 and p2["rms_orientation_deg"] <= 0.3
        wg = v.get("paper_s5_wronggaps_grating_tour")
        if wg and "max_gap_error_after_100_frames_cm" in wg:
            out["wrong_gaps_within_1cm_after_100"] = wg["max_gap_error_after_100_frames_cm"] <= 1.0
    e = {n: c["rows"]["edge_only"] for n, c in cells.items() if "edge_only" in c["rows"]}
    if v and e:
        out["orientation_not_worse_than_edge_only"] = all(
            v[n]["rms_orientation_deg"] <= e[n]["rms_orientation_deg"] for n in e if n in v)
    pr = [c["rows"]["prior"] for c in cells.values() if "prior" in c["rows"]]
    if pr:
        out["prior_0.15deg_every_cell"] = all(r["rms_orientation_deg"] <= 0.15 for r in pr)
    return out


# The tracker as it was on main before 2026-11-26 (these options did not exist or had these values).
OLD_TRACKER = {"texture_min_corner_ratio": 0.0, "edge_profile_px": 0, "edge_tangent_px": 0.0, "ground_points": 0,
               "max_residual_px": 2.0, "init_search_range_m": 0.25, "texture_weight": 2.0, "relock_after_frames": 0,
               "gap_scan": False, "edge_silhouette_px": 0, "unobserved_velocity_tau_s": 0.0,
               "texture_refine_obs": 20,
               # added since (2026-11-26 night and 2026-11-27): off, so that "old" stays the old tracker
               "edge_distance_sigma_px": 0.0, "edge_innermost_ratio": 0.0, "edge_strength_weight": 0.0,
               "texture_check_deg": 0.0, "texture_weight_crossing": None, "edge_pitch_gain": 0.0,
               "texture_crossing_edge_fraction": 0.0, "along_scan_range_m": 0.0,
               "retry_refused": False}


@contextmanager
def one_thread() -> Iterator[None]:
    """OpenCV on one thread inside the block: its own pool (not OpenMP's, so not OMP_NUM_THREADS) would otherwise
    spread filters, eigenvalue maps and LK over every core, and the tracker's frames/s are claimed single-threaded.
    Rendering a frame set on a cache miss stays outside, on every core."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def throughput(overrides: dict[str, Any], cache: Path | None) -> dict[str, Any]:
    """Frames/s inside track() on the paper's 5 pipes + crossing pipe (first 150 frames of a cached
    tour run), one thread, median of 3 runs, for this tracker and the old one on the same frames."""
    name = "p5x_f50_concrete_fast_distort_beam_gain"
    cell = dict(CELLS[name], distort=False, traj="tour", overhead=(), gain=False)  # plain 720x480 pinhole
    run = load_run("throughput_p5x_tour", cell, 0, cache)
    frames = [decode_frame(b) for b in run["frames"][:150]]
    model = build_rack(cell["rack"])
    out: dict[str, Any] = {"scene": "paper_5pipe.toml (5 parallel + crossing pipe), field appearance, 720x480",
                           "frames": len(frames)}
    with one_thread():
        out["opencv_threads"] = cv2.getNumThreads()
        for label, kw in (("new", dict(overrides)), ("old", dict(OLD_TRACKER))):
            fps = []
            for _rep in range(3):
                tr = RackTracker(model, CAMERA, RackTrackerConfig(**kw))
                tr.reset(run["poses"][0])
                t_s = 0.0
                for k, img in enumerate(frames):
                    t0 = time.perf_counter()
                    tr.track(img, k / RATE_HZ)
                    if k:
                        t_s += time.perf_counter() - t0
                fps.append((len(frames) - 1) / t_s)
            out[f"{label}_frames_per_s_runs"] = fps
            out[f"{label}_frames_per_s_median"] = float(np.median(fps))
    out["ratio_new_to_old"] = out["new_frames_per_s_median"] / out["old_frames_per_s_median"]
    return out


def parse_set(items: list[str]) -> dict[str, Any]:
    """`--set name=value` items -> `RackTrackerConfig` overrides, each value of its field's type."""
    fields = {f.name: f for f in dataclasses.fields(RackTrackerConfig)}
    out: dict[str, Any] = {}
    for it in items:
        key, _, val = it.partition("=")
        if key not in fields:
            raise SystemExit(f"--set: unknown RackTrackerConfig field {key!r}")
        default = getattr(RackTrackerConfig(), key)
        if default is None or "None" in str(fields[key].type):  # an optional number: "none" unsets it
            out[key] = None if val.lower() == "none" else float(val)
        else:
            out[key] = (val.lower() in ("1", "true", "yes")) if isinstance(default, bool) else type(default)(val)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", choices=("tuning", "heldback", "all", "extra"), default="tuning")
    ap.add_argument("--seed-values", default="",
                    help="comma-separated seeds instead of --seeds' half, to diagnose one cell (never held back)")
    ap.add_argument("--quick", action="store_true", help="smoke: first seed of the half, first 100 frames")
    ap.add_argument("--cells", default="", help="comma-separated subset of the cells")
    ap.add_argument("--rows", default="vision,edge_only,prior")
    ap.add_argument("--set", action="append", default=[], help="RackTrackerConfig override, name=value")
    ap.add_argument("--cache-dir", default=os.environ.get("RACK_STRESS_CACHE", "/tmp/rack_stress_cache"))
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--throughput", action="store_true", help="only the throughput check (see throughput())")
    ap.add_argument("--plain-allocator", action="store_true",
                    help="leave glibc's heap thresholds as they are (default: as the daemon sets them, "
                         "drivers/allocator.py)")
    ap.add_argument("--render-only", action="store_true",
                    help="only fill the frame cache (no tracker is run, no result is printed but the counts)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    # The daemon's process keeps freed heap memory for the next frame (drivers/allocator.py); so does this one.
    allocator = "plain" if args.plain_allocator else \
        ("daemon's" if keep_freed_memory() else "plain (not glibc)")
    t_start = time.perf_counter()
    seeds = {"tuning": TUNING_SEEDS, "heldback": HELDBACK_SEEDS, "all": TUNING_SEEDS + HELDBACK_SEEDS,
             "extra": EXTRA_SEEDS}[args.seeds]
    if args.seed_values:
        try:
            seeds = tuple(int(v) for v in args.seed_values.split(",") if v.strip())
        except ValueError:
            raise SystemExit(f"--seed-values: integers separated by commas, got {args.seed_values!r}") from None
        if set(seeds) & set(HELDBACK_SEEDS):
            raise SystemExit(f"--seed-values: {sorted(set(seeds) & set(HELDBACK_SEEDS))} are held back; "
                             "run them with --seeds heldback")
    if args.quick:
        seeds = seeds[:1]
    n_frames = 100 if args.quick else None
    wanted = [c.strip() for c in args.cells.split(",") if c.strip()] or list(CELLS)
    for c in wanted:
        if c not in CELLS:
            raise SystemExit(f"--cells: unknown cell {c!r}")
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    overrides = parse_set(args.set)
    cache = None if args.no_cache else Path(args.cache_dir)
    if args.throughput:
        tp = throughput(overrides, cache)
        print(json.dumps({"benchmark": "rack_stress", "throughput": tp, "allocator": allocator,
                          "compiled_kernels": compiled_names(), "elapsed_s": time.perf_counter() - t_start}))
        return
    out_cells: dict[str, dict[str, Any]] = {}
    for name in wanted:
        cell = CELLS[name]
        per_row: dict[str, list[dict[str, Any]]] = {r: [] for r in rows}
        for seed in seeds:
            run = load_run(name, cell, seed, cache)
            if args.render_only:
                print(f"{name} seed {seed}: {len(run['frames'])} frames cached", file=sys.stderr, flush=True)
                continue
            for r in rows:
                with one_thread():
                    res = track_run(name, cell, seed, run, r, overrides, n_frames)
                per_row[r].append(res)
                print(f"{name} seed {seed} {r}: rms {100 * np.sqrt(np.mean(np.square(res['perr']))):.2f} cm "
                      f"{np.sqrt(np.mean(np.square(res['aerr']))):.3f} deg, lost {res['lost']}, "
                      f"{len(res['perr'])} frames", file=sys.stderr, flush=True)
        if not args.render_only:
            out_cells[name] = {"spec": cell, "seeds": list(seeds),
                               "rows": {r: summarize(v) for r, v in per_row.items()}}
    if args.render_only:
        print(json.dumps({"benchmark": "rack_stress", "render_only": True, "seeds": args.seeds, "cells": wanted,
                          "elapsed_s": time.perf_counter() - t_start}))
        return
    summary = {r: row_summary(out_cells, r) for r in rows}
    out = {
        "benchmark": "rack_stress", "seeds": args.seeds, "seed_values": list(seeds), "quick": args.quick,
        "overrides": overrides, "camera": {"width": 720, "height": 480, "f_px": 630.0, "rate_hz": RATE_HZ},
        "noise_std_grey": NOISE_STD, "blur_px": BLUR_PX, "start_offset": {"m": START_OFF_M, "deg": 0.5},
        "cells": out_cells, "summary": summary, "acceptance": acceptance(out_cells, summary), "allocator": allocator,
        "compiled_kernels": compiled_names(), "elapsed_s": time.perf_counter() - t_start,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
