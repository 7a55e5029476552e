"""Benchmark: the paper's Table I (Lippiello & Cacace) on rendered images, plus wrong gaps,
a 3 m flight along the pipes and throughput. Prints ONE JSON object.

Scenes: 2..5 parallel pipes (radii 15-20 cm, 10 cm gaps, 10 m long) over textured ground,
rendered by `companion.sim.rack_scene` at 720x480, f = 630, 25 Hz, Gaussian image noise. The
camera flies through 4 random waypoints 1.5-3 m above the pipes with a continuous-acceleration
profile capped at 0.5 m/s and 0.2 rad/s, plus Dryden-like (coloured-noise) vibration of position
and attitude. "Features" (10..50) is the paper's F: the number of texture spots in total over the
whole rack (10 m pipes; only a few are in view at a time), painted on otherwise plain pipes; the
tracker runs with its default configuration. The former meaning (densely rust-spotted paint, 30
spots per square metre) is kept as the named extra row "p<n>_dense". Each cell: 10 runs (seeds);
a run's trajectory and noise seed are shared by its cells. Errors are those of the camera pose in
the rack frame.

Usage: python bench/rack_table1.py [--quick] [--runs N] [--seconds S] [--cells p2_f10,p2_f20,p3_f10]
"""

from __future__ import annotations

import os

# Single-threaded measurement: BLAS thread pools would otherwise run next to track().
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from companion.camera import PinholeCamera  # noqa: E402
from companion.geometry import se3, so3  # noqa: E402
from companion.sim.rack_scene import RackScene, RackSceneConfig  # noqa: E402
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig  # noqa: E402

CAMERA = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
RATE_HZ = 25.0
RADII = (0.15, 0.20, 0.15, 0.175, 0.20)
# Camera looking straight down, image top towards rack +y: x_cam = x_rack, y_cam = -y_rack, z_cam = -z_rack.
R_RACK_CAM_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MAX_SPEED_M_S = 0.5
MAX_RATE_RAD_S = 0.2
NOISE_STD = 6.0  # grey levels

# The paper's Table I (mean ± std over 10 runs): position (m), orientation (deg); rows features, cols pipes.
PAPER_TABLE1 = {
    10: {2: ((0.145, 0.02), (1.9, 0.5)), 3: ((0.139, 0.02), (1.85, 0.6)), 4: ((0.13, 0.03), (1.2, 0.4)),
         5: ((0.12, 0.01), (1.0, 0.3))},
    20: {2: ((0.12, 0.01), (1.5, 0.3)), 3: ((0.124, 0.015), (1.55, 0.3)), 4: ((0.12, 0.02), (1.15, 0.4)),
         5: ((0.115, 0.005), (1.15, 0.3))},
    30: {2: ((0.11, 0.005), (1.2, 0.2)), 3: ((0.115, 0.001), (1.2, 0.2)), 4: ((0.11, 0.01), (0.9, 0.2)),
         5: ((0.112, 0.01), (0.8, 0.15))},
    40: {2: ((0.1, 0.01), (0.9, 0.1)), 3: ((0.12, 0.01), (0.8, 0.15)), 4: ((0.09, 0.05), (0.9, 0.25)),
         5: ((0.09, 0.01), (0.8, 0.1))},
    50: {2: ((0.09, 0.009), (0.8, 0.05)), 3: ((0.085, 0.015), (0.79, 0.1)), 4: ((0.07, 0.02), (0.6, 0.15)),
         5: ((0.08, 0.005), (0.5, 0.1))},
}


def rack(n_pipes: int, gaps_m: float = 0.10) -> RackModel:
    return RackModel.parallel(radii=RADII[:n_pipes], gaps=[gaps_m] * (n_pipes - 1), length=10.0)


def rack_width(model: RackModel) -> float:
    a = model.pipe_arrays()
    return float(a.starts[model.num_parallel - 1, 0] + a.radii[model.num_parallel - 1])


def coloured_noise(rng: np.random.Generator, n: int, dim: int, sigma: float, tau_s: float) -> np.ndarray:
    """Twice low-pass filtered white noise (smooth, Dryden-like spectrum), std ~ sigma."""
    a = np.exp(-1.0 / (RATE_HZ * tau_s))
    x = np.zeros((n + 200, dim))
    y = np.zeros((n + 200, dim))
    w = rng.standard_normal((n + 200, dim))
    for k in range(1, n + 200):
        x[k] = a * x[k - 1] + np.sqrt(1 - a * a) * w[k]
        y[k] = a * y[k - 1] + np.sqrt(1 - a * a) * x[k]
    y = y[200:]
    return np.asarray(sigma * y / max(float(y.std()), 1e-9))


def min_jerk(s: np.ndarray) -> np.ndarray:
    return np.asarray(10 * s**3 - 15 * s**4 + 6 * s**5)


@dataclass
class Trajectory:
    poses: list[np.ndarray]  # T_rack_cam per frame


def make_trajectory(rng: np.random.Generator, model: RackModel, seconds: float) -> Trajectory:
    """Waypoints over the rack, min-jerk segments at <= 0.5 m/s and <= 0.2 rad/s, plus vibration."""
    width = rack_width(model)
    n = round(seconds * RATE_HZ)
    top = 2.0 * max(model.radii)
    wps = []
    for _ in range(5):
        wps.append(np.array([
            width / 2 + rng.uniform(-0.25, 0.25),
            rng.uniform(2.0, 8.0),
            top + rng.uniform(1.5, 3.0),
            rng.uniform(-0.35, 0.35),
        ]))
    # Segment durations from the speed limits (min-jerk peak speed = 1.875 * distance / T).
    pos = [wps[0]]
    for a, b in itertools.pairwise(wps):
        d = float(np.linalg.norm(b[:3] - a[:3]))
        dyaw = abs(float(b[3] - a[3]))
        T = max(1.875 * d / MAX_SPEED_M_S, 1.875 * dyaw / MAX_RATE_RAD_S, 1.0)
        k = max(int(T * RATE_HZ), 2)
        s = min_jerk(np.linspace(0, 1, k + 1)[1:])
        pos.extend(a + s[:, None] * (b - a))
        if len(pos) >= n:
            break
    while len(pos) < n:
        pos.append(pos[-1])
    P = np.array(pos[:n])
    vib_p = coloured_noise(rng, n, 3, 0.03, 0.6)
    vib_a = coloured_noise(rng, n, 2, np.radians(1.5), 0.4)
    poses = []
    for k in range(n):
        yaw = P[k, 3]
        R = so3.exp([vib_a[k, 0], vib_a[k, 1], 0.0]) @ so3.exp([0.0, 0.0, yaw]) @ R_RACK_CAM_DOWN
        poses.append(se3.make(R, P[k, :3] + vib_p[k]))
    return Trajectory(poses=poses)


def along_pipe_trajectory(
    rng: np.random.Generator, model: RackModel, length_m: float = 3.0, y0_m: float = 2.0, height_m: float = 2.0
) -> Trajectory:
    """Straight flight along +y over the rack's middle, `height_m` above the pipes, min-jerk, with vibration."""
    width = rack_width(model)
    top = 2.0 * max(model.radii)
    speed = 0.4
    n = round(length_m / speed * RATE_HZ) + 1
    s = min_jerk(np.linspace(0, 1, n))
    vib_p = coloured_noise(rng, n, 3, 0.02, 0.6)
    vib_a = coloured_noise(rng, n, 2, np.radians(1.0), 0.4)
    poses = []
    for k in range(n):
        p = np.array([width / 2, y0_m + length_m * s[k], top + height_m]) + vib_p[k]
        R = so3.exp([vib_a[k, 0], vib_a[k, 1], 0.0]) @ R_RACK_CAM_DOWN
        poses.append(se3.make(R, p))
    return Trajectory(poses=poses)


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    dp = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    dR = T_est[:3, :3].T @ T_true[:3, :3]
    ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    return dp, ang


def run_sequence(
    scene: RackScene, traj: Trajectory, trackers: list[RackTracker], rng: np.random.Generator,
    gaps_at: int | None = None,
) -> list[dict[str, Any]]:
    for tr in trackers:
        tr.reset(traj.poses[0])
    perr: list[list[float]] = [[] for _ in trackers]
    aerr: list[list[float]] = [[] for _ in trackers]
    lost = [0] * len(trackers)
    cpu_ms: list[list[float]] = [[] for _ in trackers]
    wall_ms: list[list[float]] = [[] for _ in trackers]
    gaps_hist: list[list[np.ndarray]] = [[] for _ in trackers]
    for k, T_true in enumerate(traj.poses):
        img = scene.render(T_true, CAMERA, noise_std=NOISE_STD, rng=rng)
        for i, tr in enumerate(trackers):
            c0, w0 = time.process_time(), time.perf_counter()
            est = tr.track(img, k / RATE_HZ)
            cpu_ms[i].append(1000 * (time.process_time() - c0))
            wall_ms[i].append(1000 * (time.perf_counter() - w0))
            dp, da = pose_errors(est.T_rack_cam, T_true)
            perr[i].append(dp)
            aerr[i].append(da)
            lost[i] += 0 if est.ok else 1
            gaps_hist[i].append(np.array(est.gaps))
    out = []
    for i in range(len(trackers)):
        p, a = np.array(perr[i]), np.array(aerr[i])
        r: dict[str, Any] = {
            "rms_position_m": float(np.sqrt(np.mean(p**2))), "max_position_m": float(p.max()),
            "rms_orientation_deg": float(np.sqrt(np.mean(a**2))), "max_orientation_deg": float(a.max()),
            "lost_frames": lost[i], "frames": len(p),
            "cpu_ms": cpu_ms[i], "wall_ms": wall_ms[i],
        }
        if gaps_at is not None:
            r["gaps_at"] = gaps_hist[i][min(gaps_at, len(gaps_hist[i]) - 1)].tolist()
            r["gaps_final"] = gaps_hist[i][-1].tolist()
        out.append(r)
    return out


def summarize(vals: list[float]) -> dict[str, float]:
    v = np.array(vals)
    return {"mean": float(v.mean()), "std": float(v.std()), "max": float(v.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="reduced set (< 1 min)")
    ap.add_argument("--runs", type=int, default=None)
    ap.add_argument("--seconds", type=float, default=None)
    ap.add_argument("--cells", default="", help="only these Table I cells, e.g. p2_f10,p2_f20,p3_f10,p2_dense")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t_start = time.perf_counter()
    if args.quick:
        pipes_list, feats_list, runs, seconds = [2, 5], [10, 50], 1, 2.0
    else:
        pipes_list, feats_list, runs, seconds = [2, 3, 4, 5], [10, 20, 30, 40, 50], 10, 8.0
    runs = args.runs or runs
    cells = {c.strip() for c in args.cells.split(",") if c.strip()}
    if cells:
        pipes_list, feats_list = [2, 3, 4, 5], [10, 20, 30, 40, 50]
    seconds = args.seconds or seconds
    all_feats = list(feats_list)
    table: dict[str, Any] = {}
    all_cpu: list[float] = []
    all_wall: list[float] = []
    for n_p in pipes_list:
        feats_list = [f for f in all_feats if not cells or f"p{n_p}_f{f}" in cells]
        dense = not cells or f"p{n_p}_dense" in cells
        if not feats_list and not dense:
            continue
        model = rack(n_p)
        names = [f"p{n_p}_f{f}" for f in feats_list] + ([f"p{n_p}_dense"] if dense else [])
        cell_runs: dict[str, list[dict[str, Any]]] = {c: [] for c in names}
        for run in range(runs):
            seed = 1000 * n_p + run
            traj = make_trajectory(np.random.default_rng(seed), model, seconds)
            for c in names:
                # F spots in total (the paper's features), or the dense paint of the extra row.
                f = None if c.endswith("_dense") else int(c.split("_f")[1])
                scene = RackScene(model, seed=seed, config=RackSceneConfig(total_spots=f))
                r = run_sequence(scene, traj, [RackTracker(model, CAMERA, RackTrackerConfig())],
                                 np.random.default_rng(seed + 7))[0]
                cell_runs[c].append(r)
                if n_p == max(pipes_list):
                    all_cpu.extend(r["cpu_ms"][1:])
                    all_wall.extend(r["wall_ms"][1:])
            print(f"{n_p} pipes, run {run + 1}/{runs}: rms orientation "
                  + ", ".join(f"{c} {cell_runs[c][-1]['rms_orientation_deg']:.3f} deg" for c in names),
                  file=sys.stderr, flush=True)
        for c in names:
            rs = cell_runs[c]
            f_spots = None if c.endswith("_dense") else int(c.split("_f")[1])
            table[c] = {
                "pipes": n_p, "features": f_spots if f_spots is not None else "dense paint (30 spots/m^2)",
                "runs": len(rs),
                "rms_position_m": summarize([r["rms_position_m"] for r in rs]),
                "max_position_m": float(max(r["max_position_m"] for r in rs)),
                "rms_orientation_deg": summarize([r["rms_orientation_deg"] for r in rs]),
                "max_orientation_deg": float(max(r["max_orientation_deg"] for r in rs)),
                "lost_frames": int(sum(r["lost_frames"] for r in rs)),
                "frames": int(sum(r["frames"] for r in rs)),
            }
            if f_spots is not None:
                table[c]["paper"] = {"position_m": PAPER_TABLE1[f_spots][n_p][0],
                                     "orientation_deg": PAPER_TABLE1[f_spots][n_p][1]}
    # Wrong-gap case: 4 pipes, true d̄ = 10/20/30 cm, model starts at 15/35/50 cm.
    true_model = rack(4)
    wrong_model = true_model.with_cumulative_gaps([0.15, 0.35, 0.50])
    wg_runs = []
    for run in range(1 if args.quick else 5):
        rng = np.random.default_rng(77 + run)
        scene = RackScene(true_model, seed=77 + run)
        traj = make_trajectory(rng, true_model, 101 / RATE_HZ if args.quick else 6.0)
        tr = RackTracker(wrong_model, CAMERA, RackTrackerConfig(estimate_gaps=True))
        wg_runs.append(run_sequence(scene, traj, [tr], rng, gaps_at=100)[0])
    truth = true_model.cumulative_gaps
    wrong_gap = {
        "true_cumulative_gaps_m": truth.tolist(),
        "initial_cumulative_gaps_m": [0.15, 0.35, 0.50],
        "gaps_after_100_frames_m": [r["gaps_at"] for r in wg_runs],
        "max_abs_error_after_100_frames_m": float(max(np.abs(np.array(r["gaps_at"]) - truth).max() for r in wg_runs)),
        "rms_position_m": summarize([r["rms_position_m"] for r in wg_runs]),
        "rms_orientation_deg": summarize([r["rms_orientation_deg"] for r in wg_runs]),
        "lost_frames": int(sum(r["lost_frames"] for r in wg_runs)),
    }
    # 3 m along the pipes on the paper's 5-pipe rack with the crossing pipe.
    paper_model = RackModel.load(os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                              "missions", "racks", "paper_5pipe.toml"))
    ap_runs = []
    along_m = 1.5 if args.quick else 3.0
    # Run 0 passes under the crossing pipe (y = 6 m); the others see only parallel pipes + texture.
    along_cases = [(4.5, 2.0), (1.0, 3.0), (2.0, 1.5)]
    for run in range(1 if args.quick else 3):
        rng = np.random.default_rng(500 + run)
        scene = RackScene(paper_model, seed=500 + run)
        y0, h = along_cases[run]
        traj = along_pipe_trajectory(rng, paper_model, along_m, y0 + (1.0 if args.quick else 0.0), h)
        tr = RackTracker(paper_model, CAMERA, RackTrackerConfig(max_texture_points=50))
        ap_runs.append(run_sequence(scene, traj, [tr], rng)[0])
        all_cpu.extend(ap_runs[-1]["cpu_ms"][1:])
        all_wall.extend(ap_runs[-1]["wall_ms"][1:])
    along = {
        "distance_m": along_m,
        "cases_start_y_m_height_m": along_cases[: len(ap_runs)],
        "max_position_m": float(max(r["max_position_m"] for r in ap_runs)),
        "rms_position_m": summarize([r["rms_position_m"] for r in ap_runs]),
        "max_orientation_deg": float(max(r["max_orientation_deg"] for r in ap_runs)),
        "lost_frames": int(sum(r["lost_frames"] for r in ap_runs)),
    }
    # Throughput of one tracker on its own (the table runs interleave five trackers per frame,
    # which thrashes caches): paper rack with the crossing pipe, 50 texture points, frames
    # rendered beforehand, only track() timed.
    rng = np.random.default_rng(900)
    scene = RackScene(paper_model, seed=900)
    traj = along_pipe_trajectory(rng, paper_model, 1.5 if args.quick else 3.0, 4.5, 2.0)
    frames = [scene.render(T, CAMERA, noise_std=NOISE_STD, rng=rng) for T in traj.poses]
    solo_cpu: list[float] = []
    solo_wall: list[float] = []
    for _rep in range(2 if args.quick else 3):
        tr = RackTracker(paper_model, CAMERA, RackTrackerConfig(max_texture_points=50))
        tr.reset(traj.poses[0])
        for k, img in enumerate(frames):
            c0, w0 = time.process_time(), time.perf_counter()
            tr.track(img, k / RATE_HZ)
            if k > 0:
                solo_cpu.append(1000 * (time.process_time() - c0))
                solo_wall.append(1000 * (time.perf_counter() - w0))
    cpu = np.array(all_cpu)
    wall = np.array(all_wall)
    scpu = np.array(solo_cpu)
    swall = np.array(solo_wall)
    out = {
        "benchmark": "rack_table1",
        "mode": "quick" if args.quick else "full",
        "camera": {"width": 720, "height": 480, "f_px": 630.0, "rate_hz": RATE_HZ},
        "image_noise_std_grey": NOISE_STD,
        "runs_per_cell": runs,
        "seconds_per_run": seconds,
        "table1": table,
        # The acceptance figure: each cell's mean over its runs (as the paper's Table I reports).
        "all_cell_means_pass": bool(all(
            c["rms_position_m"]["mean"] <= 0.02 and c["rms_orientation_deg"]["mean"] <= 0.2 and c["lost_frames"] == 0
            for c in table.values()
        )),
        # Stricter: every single run of every cell within the targets.
        "all_cells_pass": bool(all(
            c["rms_position_m"]["max"] <= 0.02 and c["rms_orientation_deg"]["max"] <= 0.2 and c["lost_frames"] == 0
            for c in table.values()
        )),
        "wrong_gap": wrong_gap,
        "along_pipes": along,
        "throughput": {
            "note": ("track() only, cv2.setNumThreads(1), BLAS 1 thread, 5-pipe scenes of the table (five trackers "
                     "interleaved per frame); shared, loaded machine"),
            "median_cpu_ms": float(np.median(cpu)), "p90_cpu_ms": float(np.percentile(cpu, 90)),
            "median_wall_ms": float(np.median(wall)), "p90_wall_ms": float(np.percentile(wall, 90)),
            "frames_per_s_cpu": float(1000.0 / np.mean(cpu)),
            "frames_per_s_wall_median": float(1000.0 / np.median(wall)),
            "samples": int(cpu.size),
            "single_tracker": {
                "scene": "paper_5pipe.toml (5 parallel + crossing pipe), 50 texture points, 720x480",
                "median_cpu_ms": float(np.median(scpu)), "p90_cpu_ms": float(np.percentile(scpu, 90)),
                "median_wall_ms": float(np.median(swall)), "p90_wall_ms": float(np.percentile(swall, 90)),
                "frames_per_s_cpu_median": float(1000.0 / np.median(scpu)),
                "frames_per_s_wall_median": float(1000.0 / np.median(swall)),
                "frames_per_s_wall_mean": float(1000.0 / np.mean(swall)),
                "samples": int(scpu.size),
            },
        },
        "python": platform.python_version(),
        "opencv": cv2.__version__,
        "elapsed_s": time.perf_counter() - t_start,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
