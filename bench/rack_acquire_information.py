"""Benchmark: how much one image can tell, on bench/rack_acquire.py's views. Prints ONE JSON object.

`bench/rack_acquire.py` counts an acquisition correct when the first tracked frame ends within 3 cm in
x and z and 1 deg in attitude of the truth. From high above two pipes, sliding sideways and rolling
about the pipes look nearly alike (the roll / slide valley), and the misses are mostly there. Is that
the image's limit or the estimator's? This bench computes, for the same seeded views (no rendering),
the Cramér-Rao covariance of the pose from one image: the normal position of every limb pixel
(`sample_limbs` at the true pose, each sample standing for its share of the limb's length in pixels,
independent with standard deviation `--edge-std-px`), two edge offsets as nuisances (one per limb
side, as the tracker and the acquirer estimate them), the autopilot's tilt (1 deg), height (5 %) and
the along-pipe prior (1 m) the bench gives the acquirer. From that Gaussian, the probability that an
efficient, unbiased estimate lands within the bar (Monte Carlo, 2000 draws per view, seeded) is
averaged over the views with at least two pipes fully in view: the rate a perfect single-image
estimator would reach. A rate far above the bench's means the misses are the estimator's (bias,
convergence), not the image's. `--limb-bias-px` adds, per draw, a constant offset on every limb
(independent between limbs, that standard deviation), carried into the pose through the same
estimator's gain: how much edge bias per limb the bar tolerates (a bias common to all limbs of one
side is the nuisance offsets', and costs nothing). `--measure-views N` renders the bench's first N views
(`rack_acquire.view_cases`, both appearances) and measures that bias: the edge check's edges at the TRUE
pose (three-line profiles at its 3 px range, either polarity, moved to the fitted silhouettes as on its
fine iterations), each limb's median offset less the mean of its view's limbs of the same side; those
deviations (per appearance, heavy-tailed: drawn from the measured ones, not a Gaussian) are then also
put through the ceiling.

Usage: python bench/rack_acquire_information.py [--views 500] [--seed 1] [--edge-std-px 0.2 0.5]
                                                [--limb-bias-px 0 0.02 0.03 0.05 0.1 0.2] [--measure-views 100]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from typing import Any

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from rack_acquire import CAMERA, fully_in_view, racks, random_view, view_cases

from companion.vision.rack import AcquisitionConfig
from companion.vision.rack.acquire_edges import normal_profiles, pick_edges
from companion.vision.rack.acquire_verify import up_axis_with_jacobian
from companion.vision.rack.edges import refine_silhouette
from companion.vision.rack.limbs import sample_limbs
from companion.vision.rack.motion import pose_jacobian

SAMPLES_PER_LIMB = 64
DRAWS = 2000
ATTITUDE_STD_RAD = np.deg2rad(1.0)
HEIGHT_REL_STD = 0.05
Y_STD_M = 1.0


def information(T: np.ndarray, model: Any, edge_std_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Fisher information (8, 8) of (pose twist (v, w), right perturbation, cam frame; two edge offsets, px), and
    the gain (6, L) of the efficient estimate's pose from a unit offset on each limb's every sample."""
    pipes = model.pipe_arrays()
    s = sample_limbs(T, CAMERA, pipes, SAMPLES_PER_LIMB, 6.0, 12.0, 0.1, 3.0)
    A = np.zeros((s.limb.size, 8))
    A[:, :6] = np.einsum("nij,ni->nj", pose_jacobian(s.J_uv_pcam, s.p_cam), s.normal_px)
    A[np.arange(s.limb.size), 6 + s.limb % 2] = 1.0
    n_limbs = 2 * pipes.radii.size
    seg_len = np.linalg.norm(s.segments_uv[:, 1] - s.segments_uv[:, 0], axis=1)
    length_px = np.bincount(s.segment_limb, weights=seg_len, minlength=n_limbs)
    count = np.bincount(s.limb, minlength=n_limbs)
    w = length_px[s.limb] / np.maximum(count[s.limb], 1) / edge_std_px**2  # each sample: its share of the limb
    H = (A * w[:, None]).T @ A
    _, J_up = up_axis_with_jacobian(T)
    H[:6, :6] += J_up.T @ J_up / ATTITUDE_STD_RAD**2
    e_z, e_y = T[2, :3], T[1, :3]  # rack z / y of a camera-frame translation
    H[:3, :3] += np.outer(e_z, e_z) / (HEIGHT_REL_STD * T[2, 3]) ** 2 + np.outer(e_y, e_y) / Y_STD_M**2
    H[6:, 6:] += np.eye(2)  # the acquirer's 1 px prior on the edge offsets
    per_limb = np.zeros((8, n_limbs))
    np.add.at(per_limb.T, s.limb, A * w[:, None])  # sum over each limb's samples of w a
    return H, np.linalg.solve(H, per_limb)[:6]


def measured_limb_bias(views: int, seed: int) -> dict[str, np.ndarray]:
    """Per appearance: each limb's median edge offset at the true pose less its view's same-side mean (px)."""
    cfg = AcquisitionConfig()
    dev: dict[str, list[float]] = {}
    for case in view_cases(views, "both", seed, 20.0):
        if case["n_full"] < 2:
            continue
        img = case["img"]
        gray = np.asarray(img if img.ndim == 2 else img[..., 0], dtype=np.float32)
        s = sample_limbs(case["T"], CAMERA, case["model"].pipe_arrays(), cfg.samples_per_limb, cfg.margin_px, 12.0,
                         0.1, 3.0)
        prof = normal_profiles(gray, s.uv, s.normal_px, 3, 1.5)
        m = pick_edges(prof, np.zeros(s.limb.size), 3, cfg.edge_threshold)
        off = refine_silhouette(gray, s.uv, s.normal_px, m.offset_px, 6, 5, max_rel_rms=cfg.silhouette_max_rms)
        limbs = [int(L) for L in np.unique(s.limb) if np.count_nonzero((s.limb == L) & m.found) >= 6]
        med = {L: float(np.median(off[(s.limb == L) & m.found])) for L in limbs}
        key = "default" if case["appearance"] == "default" else "field"
        for side in (0, 1):
            same = [med[L] for L in limbs if side == L % 2]
            if len(same) >= 2:
                # n limbs share their mean: scaled so that the deviations' variance is the limbs' own
                scale = float(np.sqrt(len(same) / (len(same) - 1.0)))
                mean = float(np.mean(same))
                dev.setdefault(key, []).extend(scale * (v - mean) for v in same)
    return {key: np.array(v) for key, v in dev.items()}


def within_rate(T: np.ndarray, cov6: np.ndarray, gain: np.ndarray, limb_bias: float | np.ndarray,
                rng: np.random.Generator) -> float:
    """Probability that a pose drawn from N(T, cov6), plus `gain` (6, L) times per-limb offsets (a float: Gaussian
    of that std, px; an array: drawn from those values), is within 3 cm in rack x and z and 1 deg in attitude."""
    d = rng.multivariate_normal(np.zeros(6), cov6, DRAWS)
    if isinstance(limb_bias, np.ndarray):
        d = d + rng.choice(limb_bias, (DRAWS, gain.shape[1])) @ gain.T
    elif limb_bias > 0:
        d = d + (limb_bias * rng.standard_normal((DRAWS, gain.shape[1]))) @ gain.T
    R = T[:3, :3]
    dx, dz = d[:, :3] @ R[0], d[:, :3] @ R[2]
    rot_deg = np.rad2deg(np.linalg.norm(d[:, 3:], axis=1))
    return float(np.mean((np.abs(dx) <= 0.03) & (np.abs(dz) <= 0.03) & (rot_deg <= 1.0)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=500)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--edge-std-px", type=float, nargs="+", default=[0.2, 0.5])
    ap.add_argument("--limb-bias-px", type=float, nargs="+", default=[0.0, 0.02, 0.03, 0.05, 0.1, 0.2])
    ap.add_argument("--measure-views", type=int, default=100)
    args = ap.parse_args()
    t0 = time.perf_counter()
    rack_list = racks()
    views = []
    for i in range(args.views):
        # the same draws as rack_acquire.view_cases (its first use of the view's generator)
        rng = np.random.default_rng([args.seed, i])
        _, model = rack_list[i % len(rack_list)]
        T, _, _, _ = random_view(rng, model)
        n_full = fully_in_view(T, model)
        if n_full >= 2:
            views.append((T, model, n_full))
    out: dict[str, Any] = {"benchmark": "rack_acquire_information", "views": args.views, "seed": args.seed,
                           "views_two_pipes_in_view": len(views), "bar": "3 cm in x and z, 1 deg",
                           "machine": platform.machine(), "rates": []}
    biases: list[tuple[str, float | np.ndarray]] = [(str(b), b) for b in args.limb_bias_px]
    if args.measure_views > 0:
        measured = measured_limb_bias(args.measure_views, args.seed)
        out["measured_limb_bias"] = {
            key: {"limbs": int(v.size), "std_px": float(np.std(v)), "abs_p50_px": float(np.percentile(np.abs(v), 50)),
                  "abs_p90_px": float(np.percentile(np.abs(v), 90))} for key, v in measured.items()}
        biases += [(f"measured {key}", v) for key, v in measured.items()]
    for sig in args.edge_std_px:
        # the information and the gain of each view depend on the noise only, not on the bias: once per view
        solved = []
        for T, model, n_full in views:
            H, gain = information(T, model, sig)
            solved.append((T, n_full, np.linalg.inv(H)[:6, :6], gain))
        for label, bias in biases:
            rng = np.random.default_rng(0)
            rates: dict[int, list[float]] = {}
            x_std_cm: dict[int, list[float]] = {}
            for T, n_full, cov, gain in solved:
                rates.setdefault(n_full, []).append(within_rate(T, cov, gain, bias, rng))
                x_std_cm.setdefault(n_full, []).append(100.0 * float(np.sqrt(T[0, :3] @ cov[:3, :3] @ T[0, :3])))
            every = [p for v in rates.values() for p in v]
            out["rates"].append({
                "edge_std_px": sig, "limb_bias_px": label, "expected_within_rate": float(np.mean(every)),
                "by_pipes_in_view": {str(n): {"views": len(rates[n]),
                                              "expected_within_rate": float(np.mean(rates[n])),
                                              "x_std_cm_median": float(np.median(x_std_cm[n])),
                                              "x_std_cm_p90": float(np.percentile(x_std_cm[n], 90))}
                                     for n in sorted(rates)},
            })
    out["elapsed_s"] = time.perf_counter() - t0
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
