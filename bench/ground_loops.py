"""Benchmark of the ground odometer on sFly-shaped flights (Ortiz et al., Tables 1-2).

Renders a textured floor (scikit-image's real gravel / grass / brick photos) along trajectories
shaped like the sFly sets (1, 2, 3 loops and hovering, ~6 m x 3 m at 1-1.5 m, 752x480) and runs,
on the same frames, every detector with GEN + LM + Kalman under perfect attitude and under
IMU-like roll/pitch noise plus rangefinder height noise; the planar baseline (GFTT + LK +
estimateAffinePartial2D, translation scaled by height, no attitude compensation) is measured in
the same run. Also: GEN vs SMA per-frame agreement after refinement, stage ablations, and the
single-threaded frame rate of ORB (time inside update()).

    python bench/ground_loops.py --quick     # < 1 min: ORB + baseline on a 1-loop flight and hovering
    python bench/ground_loops.py             # full table, every detector on DS1-DS4 (SIFT, AKAZE and
                                             # BRISK cost 0.1-0.2 s per frame: about an hour)
    python bench/ground_loops.py --detectors orb,fast-orb,gftt-orb            # ~15 min
    python bench/ground_loops.py --detectors sift,akaze,brisk --datasets DS1  # ~15 min

Prints exactly one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from companion.camera import PinholeCamera
from companion.sim.ground_scene import GroundScene, GroundTrajectory, loop_trajectory
from companion.vision.ground import GroundOdometer, GroundOdometerConfig, PlanarBaseline

DETECTORS = ("orb", "fast-orb", "gftt-orb", "sift", "akaze", "brisk")
# IMU-like attitude error: white noise plus a slowly wandering bias; rangefinder white noise.
IMU_WHITE_STD_RAD = math.radians(0.5)
IMU_BIAS_STD_RAD = math.radians(0.25)
IMU_BIAS_TAU_S = 20.0
RANGE_STD_M = 0.01
RATE_HZ = 20.0


@dataclass
class Runner:
    """One odometer under one attitude condition, with its error and timing accumulators."""

    name: str
    condition: str
    odo: Any
    errors: dict[str, list[list[float]]] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    failures: dict[str, int] = field(default_factory=dict)
    increments: dict[str, list[list[float]]] = field(default_factory=dict)
    bias_errors: dict[str, list[list[float]]] = field(default_factory=dict)


def camera() -> PinholeCamera:
    return PinholeCamera(width=752, height=480, fx=450.0, fy=450.0, cx=375.5, cy=239.5)


def datasets(quick: bool) -> list[tuple[str, GroundTrajectory, str]]:
    if quick:
        return [
            ("DS1", loop_trajectory(1, RATE_HZ, seconds_per_loop=20.0, hover_s=1.0, seed=1), "gravel"),
            ("DS4", loop_trajectory(0, RATE_HZ, seconds_per_loop=6.0, seed=4), "brick"),
        ]
    return [
        ("DS1", loop_trajectory(1, RATE_HZ, seconds_per_loop=30.0, seed=1), "gravel"),
        ("DS2", loop_trajectory(2, RATE_HZ, seconds_per_loop=30.0, seed=2), "grass"),
        ("DS3", loop_trajectory(3, RATE_HZ, seconds_per_loop=30.0, seed=3), "mixed"),
        ("DS4", loop_trajectory(0, RATE_HZ, seconds_per_loop=80.0, seed=4), "brick"),
    ]


def imu_noise(tr: GroundTrajectory, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Measured roll, pitch (true + white + Gauss-Markov bias), height (true + white), and the
    bias itself (n, 2) (roll, pitch; only to score the odometer's bias estimate)."""
    n = len(tr)
    dt = 1.0 / RATE_HZ
    phi = math.exp(-dt / IMU_BIAS_TAU_S)
    q = IMU_BIAS_STD_RAD * math.sqrt(1.0 - phi * phi)
    bias = np.zeros((n, 2))
    bias[0] = rng.standard_normal(2) * IMU_BIAS_STD_RAD
    w = rng.standard_normal((n, 2)) * q
    for k in range(1, n):
        bias[k] = phi * bias[k - 1] + w[k]
    white = rng.standard_normal((n, 2)) * IMU_WHITE_STD_RAD
    roll = tr.roll_rad + bias[:, 0] + white[:, 0]
    pitch = tr.pitch_rad + bias[:, 1] + white[:, 1]
    height = tr.height_m + rng.standard_normal(n) * RANGE_STD_M
    return roll, pitch, height, bias


def photometric(k: int, n: int, rng: np.random.Generator) -> dict[str, float]:
    """Exposure drift, sensor noise and occasional blur for frame k."""
    return {
        "gain": 1.0 + 0.12 * math.sin(2 * math.pi * k / max(n, 1) * 3.0),
        "offset": 6.0 * math.sin(2 * math.pi * k / 97.0),
        "noise_std": 2.0,
        "blur_sigma_px": 0.8 if rng.random() < 0.1 else 0.0,
    }


def summarize(rows: list[list[float]]) -> dict[str, float]:
    e = np.abs(np.asarray(rows))
    return {"x_m": float(e[:, 0].mean()), "y_m": float(e[:, 1].mean()), "yaw_deg": float(e[:, 2].mean())}


def run(quick: bool, detectors: tuple[str, ...], only: tuple[str, ...] = ()) -> dict[str, Any]:
    cv2.setNumThreads(1)
    cam = camera()
    conditions = ("perfect", "imu")
    runners: list[Runner] = []
    for cond in conditions:
        for det in detectors:
            runners.append(Runner(det, cond, GroundOdometer(cam, GroundOdometerConfig(detector=det))))
        runners.append(Runner("baseline", cond, PlanarBaseline(cam)))
    # GEN vs SMA agreement (kalman off to compare the refined increments themselves).
    agreement = [
        Runner("gen", "imu", GroundOdometer(cam, GroundOdometerConfig(solver="gen", kalman=False))),
        Runner("sma", "imu", GroundOdometer(cam, GroundOdometerConfig(solver="sma", kalman=False))),
        Runner(
            "gen-norefine", "imu", GroundOdometer(cam, GroundOdometerConfig(solver="gen", refine=False, kalman=False))
        ),
        Runner(
            "sma-norefine", "imu", GroundOdometer(cam, GroundOdometerConfig(solver="sma", refine=False, kalman=False))
        ),
    ]
    ablation = {"orb-no-kalman": agreement[0], "orb-sma-no-refine-no-kalman": agreement[3]}
    extra = {
        "orb-no-subpixel": GroundOdometerConfig(subpixel=False),
        "orb-no-tilt": GroundOdometerConfig(estimate_tilt=False),
        "orb-no-tilt-bias": GroundOdometerConfig(estimate_tilt_bias=False),
        "orb-no-robust": GroundOdometerConfig(robust="none"),
        "orb-mad": GroundOdometerConfig(robust="mad"),
        "orb-keyframes-no-tilt": GroundOdometerConfig(keyframes=True, estimate_tilt=False),
        "orb-keyframes-tilt": GroundOdometerConfig(keyframes=True, estimate_tilt=True),
    }
    for name, cfg in extra.items():
        if not quick or name in ("orb-no-subpixel", "orb-no-tilt", "orb-no-tilt-bias"):
            ablation[name] = Runner(name, "imu", GroundOdometer(cam, cfg))
    everything = runners + agreement + [r for name, r in ablation.items() if name in extra]
    data_info: dict[str, Any] = {}
    for ds_index, (ds, tr, texture) in enumerate(datasets(quick)):
        if only and ds not in only:
            continue
        scene = GroundScene(cam, texture=texture, north_range_m=(-5.0, 5.0), east_range_m=(-3.0, 6.0), seed=ds_index)
        rng = np.random.default_rng(100 + ds_index)
        roll_m, pitch_m, height_m, bias_true = imu_noise(tr, rng)
        data_info[ds] = {"frames": len(tr), "trajectory": tr.name, "texture": texture, "seconds": float(tr.stamp_s[-1])}
        for r in everything:
            r.errors[ds] = []
            r.seconds[ds] = 0.0
            r.failures[ds] = 0
            r.increments[ds] = []
            r.bias_errors[ds] = []
            if isinstance(r.odo, PlanarBaseline):
                r.odo.reset(float(tr.x_m[0]), float(tr.y_m[0]), float(tr.yaw_rad[0]))
            else:
                r.odo.reset(x_m=float(tr.x_m[0]), y_m=float(tr.y_m[0]), yaw_rad=float(tr.yaw_rad[0]))
        for k in range(len(tr)):
            img = scene.render(
                float(tr.x_m[k]),
                float(tr.y_m[k]),
                float(tr.height_m[k]),
                float(tr.roll_rad[k]),
                float(tr.pitch_rad[k]),
                float(tr.yaw_rad[k]),
                seed=1000 * ds_index + k,
                **photometric(k, len(tr), rng),
            )
            for r in everything:
                if r.condition == "perfect":
                    h, ro, pi = float(tr.height_m[k]), float(tr.roll_rad[k]), float(tr.pitch_rad[k])
                else:
                    h, ro, pi = float(height_m[k]), float(roll_m[k]), float(pitch_m[k])
                t0 = time.perf_counter()
                if isinstance(r.odo, PlanarBaseline):
                    est: Any = r.odo.update(img, h)
                else:
                    est = r.odo.update(img, float(tr.stamp_s[k]), h, ro, pi)
                    r.increments[ds].append([est.dx_m, est.dy_m, est.dyaw_rad])
                    if r.condition == "imu":
                        b_roll, b_pitch = r.odo.tilt_bias_rad
                        r.bias_errors[ds].append([b_roll, b_pitch, float(bias_true[k, 0]), float(bias_true[k, 1])])
                r.seconds[ds] += time.perf_counter() - t0
                r.failures[ds] += 0 if est.ok else 1
                dyaw = math.remainder(est.yaw_rad - float(tr.yaw_rad[k]), 2 * math.pi)
                r.errors[ds].append([est.x_m - float(tr.x_m[k]), est.y_m - float(tr.y_m[k]), math.degrees(dyaw)])

    def table(r: Runner) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for ds in r.errors:
            out[ds] = summarize(r.errors[ds]) | {
                "fps": len(r.errors[ds]) / max(r.seconds[ds], 1e-9),
                "failed_frames": r.failures[ds],
            }
        rows = [row for ds in r.errors for row in r.errors[ds]]
        loops = [row for ds in r.errors if data_info[ds]["trajectory"] != "hover" for row in r.errors[ds]]
        total_s = sum(r.seconds.values())
        out["All"] = summarize(rows) | {"fps": len(rows) / max(total_s, 1e-9)}
        out["Loops"] = summarize(loops) if loops else summarize(rows)
        return out

    tables: dict[str, Any] = {c: {} for c in conditions}
    for r in runners:
        tables[r.condition][r.name] = table(r)
    ratios = {}
    ref = "orb" if "orb" in detectors else detectors[0]
    for c in conditions:
        o, b = tables[c][ref]["Loops"], tables[c]["baseline"]["Loops"]
        ratios[c] = {k: b[k] / max(o[k], 1e-12) for k in ("x_m", "y_m", "yaw_deg")}

    def agree(r1: Runner, r2: Runner) -> dict[str, float]:
        d = np.abs(
            np.concatenate([np.asarray(r1.increments[ds]) - np.asarray(r2.increments[ds]) for ds in r1.increments])
        )
        return {
            "max_dx_mm": float(d[:, 0].max() * 1e3),
            "max_dy_mm": float(d[:, 1].max() * 1e3),
            "max_dyaw_deg": float(np.degrees(d[:, 2].max())),
            "p99_dxy_mm": float(np.percentile(np.hypot(d[:, 0], d[:, 1]), 99) * 1e3),
            "frames": int(d.shape[0]),
        }

    gen_sma = {
        "after_refinement": agree(agreement[0], agreement[1]),
        "closed_forms_only": agree(agreement[2], agreement[3]),
    }
    abl = {name: table(r)["Loops"] for name, r in ablation.items()}
    abl[f"{ref} (default: gen+lm+tilt+tilt-bias+subpixel+kalman+ransac)"] = tables["imu"][ref]["Loops"]
    speed = orb_speed(cam, quick)
    bias_tracking: dict[str, list[float]] = {}
    for r in runners:
        if r.condition == "imu" and r.name == ref:
            rows_b = np.asarray([row for ds in r.bias_errors for row in r.bias_errors[ds]])
            est_b, true_b = np.degrees(rows_b[:, :2]), np.degrees(rows_b[:, 2:])
            bias_tracking = {
                "true_rms_deg": [float(v) for v in np.sqrt(np.mean(true_b**2, axis=0))],
                "error_rms_deg": [float(v) for v in np.sqrt(np.mean((est_b - true_b) ** 2, axis=0))],
                "correlation": [float(np.corrcoef(est_b[:, j], true_b[:, j])[0, 1]) for j in range(2)],
            }
    imu_orb = tables["imu"][ref]["Loops"]
    acceptance = {
        "orb_imu_loops_xy_le_3cm": imu_orb["x_m"] <= 0.03 and imu_orb["y_m"] <= 0.03,
        "orb_imu_loops_yaw_le_0.5deg": imu_orb["yaw_deg"] <= 0.5,
        "baseline_over_orb_ge_2x": all(v >= 2.0 for v in ratios["imu"].values()),
        "orb_fps_ge_250": speed["fps_median_of_runs"] >= 250.0,
        "gen_sma_agree_1mm_0.05deg": gen_sma["after_refinement"]["max_dx_mm"] <= 1.0
        and gen_sma["after_refinement"]["max_dy_mm"] <= 1.0
        and gen_sma["after_refinement"]["max_dyaw_deg"] <= 0.05,
    }
    return {
        "benchmark": "ground_loops",
        "mode": "quick" if quick else "full",
        "machine": {
            "cpus": os.cpu_count(),
            "loadavg_1min": os.getloadavg()[0],
            "opencv": cv2.__version__,
            "opencv_threads": cv2.getNumThreads(),
        },
        "camera": {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "rate_hz": RATE_HZ},
        "imu_noise": {
            "roll_pitch_white_deg": math.degrees(IMU_WHITE_STD_RAD),
            "roll_pitch_bias_deg": math.degrees(IMU_BIAS_STD_RAD),
            "bias_tau_s": IMU_BIAS_TAU_S,
            "height_white_m": RANGE_STD_M,
        },
        "datasets": data_info,
        "tables": tables,
        "baseline_over_orb_loops": ratios,
        "ratio_reference_detector": ref,
        "gen_vs_sma": gen_sma,
        "ablation_imu_loops": abl,
        "tilt_bias_tracking_roll_pitch": bias_tracking,
        "orb_speed": speed,
        "acceptance": acceptance,
    }


def orb_speed(cam: PinholeCamera, quick: bool) -> dict[str, Any]:
    """ORB odometer alone on pre-rendered frames: frames/s of the time inside update()."""
    tr = loop_trajectory(1, RATE_HZ, seconds_per_loop=16.0, seed=7)
    n = min(len(tr), 100 if quick else 300)
    results: dict[str, dict[str, Any]] = {}
    for texture in ("gravel", "grass") if quick else ("gravel", "grass", "brick"):
        scene = GroundScene(cam, texture=texture, north_range_m=(-5.0, 5.0), east_range_m=(-3.0, 6.0), seed=7)
        frames = [
            scene.render(
                float(tr.x_m[k]),
                float(tr.y_m[k]),
                float(tr.height_m[k]),
                float(tr.roll_rad[k]),
                float(tr.pitch_rad[k]),
                float(tr.yaw_rad[k]),
                noise_std=2.0,
                seed=k,
            )
            for k in range(n)
        ]
        runs = []
        per_frame: list[float] = []
        for _ in range(3):
            odo = GroundOdometer(cam, GroundOdometerConfig(detector="orb"))
            total = 0.0
            for k in range(n):
                t0 = time.perf_counter()
                odo.update(
                    frames[k],
                    float(tr.stamp_s[k]),
                    float(tr.height_m[k]),
                    float(tr.roll_rad[k]),
                    float(tr.pitch_rad[k]),
                )
                dt = time.perf_counter() - t0
                total += dt
                per_frame.append(dt)
            runs.append(n / total)
        results[texture] = {
            "fps_runs": runs,
            "fps_median": float(np.median(runs)),
            "ms_p50": float(np.median(per_frame) * 1e3),
            "ms_p90": float(np.percentile(per_frame, 90) * 1e3),
        }
    med = float(np.median([v for r in results.values() for v in r["fps_runs"]]))
    return {"frames_per_run": n, "by_texture": results, "fps_median_of_runs": med}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="ORB + baseline on shortened flights (< 1 min)")
    parser.add_argument("--detectors", default=None, help="comma-separated detector list (default: all; quick: orb)")
    parser.add_argument("--datasets", default="", help="comma-separated subset of DS1,DS2,DS3,DS4 (default: all)")
    args = parser.parse_args()
    if args.detectors:
        dets = tuple(d.strip() for d in args.detectors.split(",") if d.strip())
    else:
        dets = ("orb",) if args.quick else DETECTORS
    t0 = time.perf_counter()
    only = tuple(d.strip() for d in args.datasets.split(",") if d.strip())
    result = run(args.quick, dets, only)
    result["wall_seconds"] = time.perf_counter() - t0
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
