"""Benchmark: how far the rack tracker's texture tracks drift off their surface points.

On the Table I 2-pipe flights (`rack_table1.py`'s scenes, trajectories, camera and noise), every
texture point is identified by its `point_id`; the surface point it stands for is the ray of the
pixel it was found at, cut with its pipe at the TRUE pose of that frame. Each later frame the
tracked pixel is compared with that surface point's true projection. Reported per age of the
track (frames since found): median and 90th percentile of that error (px), for drift-free
tracking (`texture_templates = true`, the default) and for frame-to-frame Lucas-Kanade alone;
plus each variant's mean RMS orientation error over the runs (deg) for context. Accuracy only,
no timing. Prints ONE JSON object.

Usage: python bench/rack_texture_drift.py [--runs N] [--features F]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import rack_table1 as table1  # noqa: E402

from companion.sim.rack_scene import RackScene  # noqa: E402
from companion.vision.rack import RackTracker, RackTrackerConfig  # noqa: E402
from companion.vision.rack.limbs import ray_cylinder_hits  # noqa: E402

AGE_EDGES = (1, 20, 40, 80, 10**9)


def _bucket_name(i: int) -> str:
    lo, hi = AGE_EDGES[i], AGE_EDGES[i + 1]
    return f"{lo}-{hi - 1}" if hi < 10**9 else f">={lo}"


def run(n_runs: int, features: int) -> dict[str, Any]:
    model = table1.rack(2)
    pipes = model.pipe_arrays()
    variants = {"templates": True, "lk_only": False}
    errors: dict[str, list[list[float]]] = {v: [[] for _ in AGE_EDGES[:-1]] for v in variants}
    rms_deg: dict[str, list[float]] = {v: [] for v in variants}
    for run_i in range(n_runs):
        seed = 2000 + run_i
        rng = np.random.default_rng(seed)
        scene = RackScene(model, seed=seed)
        traj = table1.make_trajectory(rng, model, 8.0)
        trackers = {v: RackTracker(model, table1.CAMERA, RackTrackerConfig(max_texture_points=features,
                                                                            texture_templates=on))
                    for v, on in variants.items()}
        truth: dict[str, dict[int, tuple[np.ndarray, int]]] = {v: {} for v in variants}
        ang: dict[str, list[float]] = {v: [] for v in variants}
        for tr in trackers.values():
            tr.reset(traj.poses[0])
        for k, T in enumerate(traj.poses):
            img = scene.render(T, table1.CAMERA, noise_std=table1.NOISE_STD, rng=rng)
            for v, tr in trackers.items():
                est = tr.track(img, k / table1.RATE_HZ)
                ang[v].append(table1.pose_errors(est.T_rack_cam, T)[1])
                tm = tr._texture  # diagnostics: the tracker's own map (ids, pixels)
                for i, pid in enumerate(tm.point_id.tolist()):
                    known = truth[v].get(pid)
                    if known is None:
                        d = table1.CAMERA.unproject(tm.uv_last[i : i + 1]) @ T[:3, :3].T
                        t = ray_cylinder_hits(T[:3, 3], d, pipes)[0, tm.pipe[i]]
                        if np.isfinite(t):
                            truth[v][pid] = (T[:3, 3] + t * d[0], k)
                        continue
                    age = k - known[1]
                    p_cam = (known[0] - T[:3, 3]) @ T[:3, :3]
                    err = float(np.linalg.norm(table1.CAMERA.project(p_cam[None])[0] - tm.uv_last[i]))
                    b = int(np.searchsorted(AGE_EDGES, age, side="right")) - 1
                    errors[v][b].append(err)
        for v in variants:
            rms_deg[v].append(float(np.sqrt(np.mean(np.square(ang[v])))))
        print(f"run {run_i + 1}/{n_runs}: rms orientation "
              + ", ".join(f"{v} {rms_deg[v][-1]:.3f} deg" for v in variants), file=sys.stderr, flush=True)
    out: dict[str, Any] = {}
    for v in variants:
        out[v] = {
            "track_error_px_by_age_frames": {
                _bucket_name(i): {
                    "n": len(e),
                    "median": float(np.median(e)) if e else None,
                    "p90": float(np.percentile(e, 90)) if e else None,
                }
                for i, e in enumerate(errors[v])
            },
            "mean_rms_orientation_deg": float(np.mean(rms_deg[v])),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--features", type=int, default=20)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t0 = time.time()
    res = run(args.runs, args.features)
    print(json.dumps({"benchmark": "rack_texture_drift", "pipes": 2, "features": args.features, "runs": args.runs,
                      "seconds_per_run": 8.0, **res, "wall_s": round(time.time() - t0, 1)}, indent=1))


if __name__ == "__main__":
    main()
