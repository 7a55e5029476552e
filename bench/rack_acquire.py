"""Benchmark: rack acquisition from one image, no start pose. Prints ONE JSON object.

Views (seeded): a rack from `missions/racks/` or a parallel rack of 2-5 pipes (radii 15-20 cm,
10 cm gaps, 10 m long); the camera 1.5-4 m above the pipe tops, up to 1.5 m to the side of the
rack's middle, anywhere along it, heading (yaw) within ±60 deg of the pipes, roll and pitch
within ±5 deg; 720x480, f = 630, Gaussian noise (4 grey levels). The acquirer is given the roll
and pitch with 1 deg noise, the height with 5 % noise (and that as its std), the along-pipe
position y with 0.5 m noise (std 1 m), and, unless `--yaw-std-deg 0`, the heading with that much
noise. Each view is rendered with the appearance models asked for (`default`: RackScene;
`field`: FieldRackScene, the grounds cycling through grating, concrete, natural).

Per attempt: `acquire_rack` is timed (one thread). Each failure is put in one category
(`failure_categories`): no pattern found / no hypothesis agrees with the edges / ambiguous / score
below the floor / strays from the autopilot's height or tilt (each with whether the best hypothesis
had the right assignment), confident with a wrong assignment, right but the pose off after the first
tracked frame, or right but that frame rejected by the tracker. Outcomes: `confident` or not; the
pipe assignment is right when the best hypothesis has the true direction of travel and its x is
within half the narrowest pipe pitch of the truth (a wrong pipe or direction moves it by a whole
pitch or flips it); it locks when `RackTracker.reset(best) + track(same image)` (the daemon's
tracker settings, `DAEMON_RACK_TRACKER`, and its attitude prior from the autopilot's roll and pitch,
1 deg: it is the daemon that takes over an acquired pose; the prior since 2026-11-26 evening) accepts
the frame and ends within 3 cm in x and z and 1 deg in attitude of the truth (a rejected frame
returns the prediction, i.e. the acquired pose itself: not a tracked pose; such attempts are counted
apart, `confident_right_first_frame_rejected`; before 2026-11-26 evening they counted as locked).
Correct = confident, assignment right and locked. Confident wrong = confident with a wrong
assignment. No lock = not confident. Rates are over the attempts where at least two parallel pipes
are fully in view (both limbs inside the image over at least 150 px, after occlusion) and,
separately, over all attempts. `tracker_from_truth_rate`: the same first tracked frame started at
the true pose, i.e. the correct rate a perfect acquisition would get with the daemon's tracker (the
tracker's own share of the misses, measured in the same run).

The attempts come from `view_cases` (in order; `bench/rack_acquire_ab.py` renders the same ones to
compare two implementations on them).

Usage: python bench/rack_acquire.py [--views 500] [--appearance default|field|both] [--seed 1]
                                    [--yaw-std-deg 20]
"""

from __future__ import annotations

import os

# Single-threaded measurement.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import glob  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from companion.camera import PinholeCamera  # noqa: E402
from companion.config import VisionConfig  # noqa: E402
from companion.daemon.wiring import DAEMON_RACK_TRACKER  # noqa: E402
from companion.geometry import frames, se3, so3  # noqa: E402
from companion.sim.rack_scene import RackScene  # noqa: E402
from companion.vision.rack import (  # noqa: E402
    AcquisitionPrior,
    RackModel,
    RackTracker,
    RackTrackerConfig,
    acquire_rack,
)
from companion.vision.rack.limbs import sample_limbs  # noqa: E402

CAMERA = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
RADII = (0.15, 0.20, 0.15, 0.175, 0.20)
NOISE_STD = 4.0
FIELD_GROUNDS = ("grating", "concrete", "natural")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def racks() -> list[tuple[str, RackModel]]:
    paths = sorted(glob.glob(os.path.join(ROOT, "missions/racks/*.toml")))
    out = [(os.path.basename(p), RackModel.load(p)) for p in paths]
    for n in range(2, 6):
        out.append((f"parallel_{n}", RackModel.parallel(radii=RADII[:n], gaps=[0.10] * (n - 1), length=10.0)))
    return out


def field_scene_class() -> Any:
    try:
        from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
    except ImportError:
        sys.exit("bench/rack_acquire.py: --appearance field needs companion.sim.rack_scene_field (branch rack)")
    return FieldRackScene, FieldSceneConfig


def fully_in_view(T: np.ndarray, model: RackModel) -> int:
    """Parallel pipes whose two limbs are both in the image over >= 150 px (after occlusion)."""
    pipes = model.pipe_arrays()
    s = sample_limbs(T, CAMERA, pipes, 32, 4.0, 12.0, 0.1, 3.0)
    n = 0
    for m in range(model.num_parallel):
        ok = True
        for limb in (2 * m, 2 * m + 1):
            seg = np.flatnonzero(s.segment_limb == limb)
            if seg.size == 0:
                ok = False
                break
            a, b = s.segments_uv[seg[0]]
            vis = np.count_nonzero(s.limb == limb) / 32.0
            ok = ok and bool(float(np.hypot(*(b - a))) * vis >= 150.0)
        n += int(ok)
    return n


def random_view(rng: np.random.Generator, model: RackModel) -> tuple[np.ndarray, float, float, float]:
    """True T_rack_cam and the body roll, pitch, yaw (rad) of one random view."""
    par = model.pipe_arrays()
    n = model.num_parallel
    width = float(par.starts[n - 1, 0] + par.radii[n - 1])
    top = float(2.0 * max(model.radii))
    roll, pitch = rng.uniform(-np.deg2rad(5.0), np.deg2rad(5.0), 2)
    yaw = rng.uniform(-np.deg2rad(60.0), np.deg2rad(60.0))
    T_ned_body = se3.make(frames.rotation_from_euler_zyx(roll, pitch, yaw), np.zeros(3))
    T = frames.T_rack_cam_from_T_ned_body(T_ned_body, frames.default_T_ned_rack(), frames.default_T_body_cam())
    T[:3, 3] = [width / 2 + rng.uniform(-1.5, 1.5), rng.uniform(1.5, model.length - 1.5), top + rng.uniform(1.5, 4.0)]
    return T, float(roll), float(pitch), float(yaw)


def view_cases(views: int, appearance: str, seed: int, yaw_std_deg: float) -> Iterator[dict[str, Any]]:
    """The seeded attempts in order: per view, one rendered image per appearance, with its prior and truth
    (keys view, rack, model, appearance, T, prior, img, n_full, pitch_min)."""
    kinds = ["default", "field"] if appearance == "both" else [appearance]
    field_cls = field_scene_class() if "field" in kinds else None
    rack_list = racks()
    scenes: dict[tuple[int, str], Any] = {}
    for i in range(views):
        rng = np.random.default_rng([seed, i])
        ri = i % len(rack_list)
        name, model = rack_list[ri]
        T, roll, pitch, yaw = random_view(rng, model)
        n_full = fully_in_view(T, model)
        meas_h = T[2, 3] * (1.0 + 0.05 * rng.standard_normal())
        yaw_std = np.deg2rad(yaw_std_deg)
        prior = AcquisitionPrior(
            roll_rad=roll + np.deg2rad(1.0) * rng.standard_normal(),
            pitch_rad=pitch + np.deg2rad(1.0) * rng.standard_normal(),
            height_m=meas_h, height_std_m=0.05 * meas_h,
            y_m=T[1, 3] + 0.5 * rng.standard_normal(), y_std_m=1.0,
            yaw_rad=(yaw + yaw_std * rng.standard_normal()) if yaw_std > 0 else None,
            yaw_std_rad=yaw_std if yaw_std > 0 else 0.35,
        )
        pitch_min = float(np.min(np.diff(model.pipe_arrays().starts[: model.num_parallel, 0]))) if \
            model.num_parallel > 1 else 1.0
        for kind in kinds:
            key = (ri, kind if kind == "default" else f"field-{FIELD_GROUNDS[i % 3]}")
            if key not in scenes:
                if kind == "default":
                    scenes[key] = RackScene(model, seed=100 + ri)
                else:
                    assert field_cls is not None
                    cls, cfg_cls = field_cls
                    scenes[key] = cls(model, seed=100 + ri, config=cfg_cls(ground=FIELD_GROUNDS[i % 3]))
            img = scenes[key].render(T, CAMERA, noise_std=NOISE_STD, rng=rng)
            yield {"view": i, "rack": name, "model": model, "appearance": key[1], "T": T, "prior": prior,
                   "img": img, "n_full": n_full, "pitch_min": pitch_min}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=500)
    ap.add_argument("--appearance", choices=("default", "field", "both"), default="both")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--yaw-std-deg", type=float, default=20.0)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    last_view = -1
    for case in view_cases(args.views, args.appearance, args.seed, args.yaw_std_deg):
        i, model, T, prior, img = case["view"], case["model"], case["T"], case["prior"], case["img"]
        if i != last_view and i % 20 == 0 and i > 0:
            print(f"{i}/{args.views} views, {time.perf_counter() - t_start:.0f} s", file=sys.stderr)
        last_view = i
        t0 = time.perf_counter()
        res = acquire_rack(img, model, CAMERA, prior)
        dt_ms = (time.perf_counter() - t0) * 1e3
        row: dict[str, Any] = {"view": i, "rack": case["rack"], "appearance": case["appearance"],
                               "n_full": case["n_full"], "ms": dt_ms, "confident": res.confident,
                               "n_hyp": len(res.hypotheses), "status": res.status, "assign_ok": False,
                               "locked": False, "track_ms": None, "track_ok": None, "pose_within": False}
        best = res.best
        if best is not None:
            row["score"] = best.score
            row["assign_ok"] = bool(not best.reversed
                                    and abs(best.T_rack_cam[0, 3] - T[0, 3]) < case["pitch_min"] / 2)
            # the daemon's tracker takes over an acquired pose: check with its settings
            first = first_tracked_frame(model, best.T_rack_cam, img, prior, T)
            row.update(first)
            row.update(y_observed=best.y_observed, y_std_m=float(np.sqrt(max(
                float(best.T_rack_cam[1, :3] @ best.covariance[:3, :3] @ best.T_rack_cam[1, :3]), 0.0))))
        # The same first frame from the true pose (a perfect acquisition): what the tracker itself allows.
        row["from_truth_locked"] = bool(first_tracked_frame(model, T, img, prior, T)["locked"])
        rows.append(row)
    print(json.dumps(summary(rows, args), indent=1))


def first_tracked_frame(model: RackModel, T_start: np.ndarray, img: np.ndarray, prior: AcquisitionPrior,
                        T_true: np.ndarray) -> dict[str, Any]:
    """`RackTracker.reset(T_start) + track(img)` with the daemon's settings and attitude prior, against the truth.

    A rejected frame returns the prediction (the start pose itself): not a tracked pose, so `locked` needs the
    frame accepted (`track_ok`) and the pose within 3 cm in x and z and 1 deg (`pose_within`).
    """
    tr = RackTracker(model, CAMERA, RackTrackerConfig(**DAEMON_RACK_TRACKER))
    tr.reset(T_start)
    t1 = time.perf_counter()
    est = tr.track(img, 0.0, **attitude_prior(prior))
    track_ms = (time.perf_counter() - t1) * 1e3
    err = pose_error(est.T_rack_cam, T_true)
    return {"track_ms": track_ms, **err, "track_ok": bool(est.ok), "track_status": est.status,
            "locked": bool(est.ok and err["pose_within"])}


def pose_error(T_rack_cam: np.ndarray, T_true: np.ndarray) -> dict[str, Any]:
    """Error of a pose against the truth (rack frame, m / deg) and whether it is within the bar: 3 cm in x and z,
    1 deg in attitude."""
    E = se3.inverse(T_true) @ T_rack_cam
    d = T_rack_cam[:3, 3] - T_true[:3, 3]
    rot_deg = float(np.rad2deg(np.linalg.norm(so3.log(E[:3, :3]))))
    return {"dx_m": float(d[0]), "dz_m": float(d[2]), "rot_deg": rot_deg, "y_err_m": float(d[1]),
            "pose_within": bool(abs(d[0]) <= 0.03 and abs(d[2]) <= 0.03 and rot_deg <= 1.0)}


def attitude_prior(prior: AcquisitionPrior) -> dict[str, Any]:
    """`RackTracker.track`'s attitude prior as the daemon gives it (`pipeline._attitude_prior`): the autopilot's
    roll and pitch (here the noisy ones the acquirer got) at `vision.rack_attitude_prior_std_deg`."""
    R_ned_body = frames.rotation_from_euler_zyx(prior.roll_rad, prior.pitch_rad, 0.0)
    R_rack_cam = frames.default_T_ned_rack()[:3, :3].T @ R_ned_body @ frames.default_T_body_cam()[:3, :3]
    return {"R_prior": R_rack_cam, "R_prior_std_rad": np.deg2rad(VisionConfig().rack_attitude_prior_std_deg)}


def rates(rows: list[dict[str, Any]]) -> dict[str, Any]:
    n = len(rows)
    if n == 0:
        return {"attempts": 0}
    conf = [r for r in rows if r["confident"]]
    correct = sum(1 for r in conf if r["assign_ok"] and r["locked"])
    wrong = sum(1 for r in conf if not r["assign_ok"])
    conf_unlocked = sum(1 for r in conf if r["assign_ok"] and not r["locked"])
    return {
        "attempts": n,
        "correct_rate": correct / n,
        "confident_wrong_rate": wrong / n,
        "confident_right_but_not_locked_rate": conf_unlocked / n,
        # confident and right, the pose within the bar, but the tracker rejected that first frame
        "confident_right_first_frame_rejected": sum(1 for r in conf if r["assign_ok"] and r["pose_within"]
                                                    and not r["locked"]),
        "no_lock_rate": (n - len(conf)) / n,
        "best_right_when_not_confident": sum(1 for r in rows if not r["confident"] and r["assign_ok"]),
        # the same first tracked frame started at the true pose: the rate a perfect acquisition would get
        "tracker_from_truth_rate": sum(1 for r in rows if r["from_truth_locked"]) / n,
        "failure_categories": categories(rows),
    }


def category(r: dict[str, Any]) -> str | None:
    """Why an attempt is not correct (None when it is): the acquirer's own verdict, or the outcome."""
    if r["confident"]:
        if not r["assign_ok"]:
            return "confident_wrong_assignment"
        if r["locked"]:
            return None
        return "first_tracked_frame_rejected" if r["pose_within"] else "pose_off_after_first_tracked_frame"
    status = str(r["status"])
    if r["n_hyp"] == 0:
        return "no_pattern_found" if status.startswith("no pipe pattern") else "no_hypothesis_agrees"
    if status.startswith("ambiguous"):
        return "ambiguous"
    if status.startswith("best score"):
        return "score_below_floor"
    return "strays_from_height_or_tilt"


def categories(rows: list[dict[str, Any]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for r in rows:
        c = category(r)
        if c is not None:
            key = c if c.startswith(("confident", "pose")) else f"{c}_best_{'right' if r['assign_ok'] else 'wrong'}"
            out[key] = out.get(key, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def summary(rows: list[dict[str, Any]], args: argparse.Namespace) -> dict[str, Any]:
    ms = np.array([r["ms"] for r in rows])
    tr = np.array([r["track_ms"] for r in rows if r["track_ms"] is not None])
    two = [r for r in rows if r["n_full"] >= 2]
    by_app: dict[str, Any] = {}
    for app in sorted({r["appearance"].split("-")[0] for r in rows}):
        sel = [r for r in two if r["appearance"].startswith(app)]
        by_app[app] = rates(sel)
    fails = [{k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()} for r in two
             if not (r["confident"] and r["assign_ok"] and r["locked"])][:30]
    return {
        "benchmark": "rack_acquire",
        "views": args.views,
        "appearance": args.appearance,
        "seed": args.seed,
        "yaw_prior_std_deg": args.yaw_std_deg if args.yaw_std_deg > 0 else None,
        "image": [CAMERA.width, CAMERA.height],
        "two_or_more_pipes_in_view": rates(two),
        "two_or_more_by_appearance": by_app,
        "all_views": rates(rows),
        "acquire_ms": {"median": float(np.median(ms)), "p90": float(np.percentile(ms, 90)),
                       "max": float(ms.max())},
        "first_track_ms_median": float(np.median(tr)) if tr.size else None,
        "targets": {"correct_rate": 0.98, "confident_wrong_rate": 0.002, "acquire_ms_median": 30.0},
        "confident_wrong_views": [[r["view"], r["appearance"]] for r in rows if r["confident"] and not r["assign_ok"]],
        "failures_sample": fails,
        "machine": {"python": platform.python_version(), "opencv": cv2.__version__, "threads": 1,
                    "cpus": os.cpu_count(), "load_average_at_end": [round(x, 2) for x in os.getloadavg()]},
    }


if __name__ == "__main__":
    main()
