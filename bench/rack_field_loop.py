"""The rack tracker on `companion sim`'s camera and field appearance, open loop, along the example mission.

`companion sim --appearance field` flies the paper's rack with the harsher appearance model of issue #14
(sparse spots, high-contrast ground, shadows, JPEG) through the daemon. This benchmark isolates the tracker:
it renders the sim's own 360x240 frames (15 Hz, `companion/data/sim_default.toml`: mount, rack placement,
renderer seed) along a trajectory shaped like `paper_sweep.xml` (take-off from the deck, climb, the three
passes along pipes 1, 3 and 5 over the crossing pipe, back to the centre) with a low-pass attitude and
position wobble, tracks every frame from the true start with the daemon's settings (`DAEMON_RACK_TRACKER`)
or the library defaults, optionally with the attitude prior the daemon gives it (0.3 deg noise), and prints
one JSON object: RMS and max position error (cm; per rack axis: x across, y along the pipes, z up), RMS
orientation error (deg), lost frames, frames/s inside `track()`, and the same per mission phase.

    python bench/rack_field_loop.py                      # daemon settings, field appearance
    python bench/rack_field_loop.py --library --set ground_points=0
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rack_stress import parse_set  # the same --set overrides (bench/ is on the path as the script's folder)

from companion.daemon.wiring import DAEMON_RACK_TRACKER
from companion.geometry import frames, se3
from companion.sim.render import SceneRenderer
from companion.sim.run import sim_config
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig
from drivers.camera import load_camera_model

RATE_HZ = 15.0
SPEED_M_S = 0.5
PIPE_AXES_X_M = (0.15, 0.60, 1.05, 1.475, 1.95)  # paper_5pipe.toml
START_RACK_XY_M = (1.1, 0.5)  # NED origin over the rack (sim_default.toml: rack translation)


def waypoints(height_m: float) -> list[tuple[str, tuple[float, float, float]]]:
    """(phase, NED north, east, height above the deck) of the mission-like trajectory."""
    x = [a - START_RACK_XY_M[0] for a in PIPE_AXES_X_M]
    n0, n1 = 1.0, 8.0  # rack y 1.5 and 8.5
    return [("deck", (0.0, 0.0, 0.0)), ("takeoff", (0.0, 0.0, 1.5)), ("climb", (0.0, 0.0, height_m)),
            ("to-p1", (n0, x[0], height_m)), ("p1", (n1, x[0], height_m)), ("to-p3", (n1, x[2], height_m)),
            ("p3", (n0, x[2], height_m)), ("to-p5", (n0, x[4], height_m)), ("p5", (n1, x[4], height_m)),
            ("centre", (4.5, 0.0, height_m))]


def trajectory(height_m: float, seed: int, wobble: float = 1.0) -> tuple[list[Any], list[str]]:
    """Body poses in NED (4x4) at RATE_HZ with a cosine speed profile per leg, a 1 s hold at each
    waypoint and a low-pass wobble (about 1 deg of roll/pitch, 1-2 cm); the phase name of each pose."""
    wps = waypoints(height_m)
    pos: list[Any] = []
    names: list[str] = []
    for (_, a), (name, b) in itertools.pairwise(wps):
        p0, p1 = np.array(a), np.array(b)
        n = max(2, int(np.linalg.norm(p1 - p0) / SPEED_M_S * RATE_HZ))
        s = 0.5 - 0.5 * np.cos(np.pi * np.arange(n) / n)
        pos.extend(p0 + (p1 - p0) * si for si in s)
        pos.extend([p1] * int(RATE_HZ))
        names.extend([name] * (n + int(RATE_HZ)))
    rng = np.random.default_rng(seed)
    white = rng.normal(size=(len(pos), 6))
    wob = np.zeros_like(white)
    acc = np.zeros(6)
    for k in range(len(pos)):  # first-order low-pass, time constant ~1.3 s
        acc = acc + 0.05 * (white[k] - acc)
        wob[k] = acc
    wob *= wobble * np.array([0.02, 0.02, 0.01, math.radians(1.2), math.radians(1.2), math.radians(0.5)]) / 0.16
    poses = []
    for k, p in enumerate(pos):
        R = frames.rotation_from_euler_zyx(wob[k, 3], wob[k, 4], wob[k, 5])
        poses.append(se3.make(R, np.array([p[0], p[1], -p[2]]) + wob[k, :3]))
    return poses, names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--library", action="store_true", help="library defaults instead of DAEMON_RACK_TRACKER")
    ap.add_argument("--set", action="append", default=[], help="RackTrackerConfig override, name=value")
    ap.add_argument("--appearance", choices=("default", "field"), default="field")
    ap.add_argument("--seed", type=int, default=1, help="renderer (spots, ground) and wobble seed")
    ap.add_argument("--height", type=float, default=1.3, help="cruise height above the deck (m); the mission's is 1.3")
    ap.add_argument("--wobble", type=float, default=1.0, help="scale of the wobble (1: ~2 cm, 1.2 deg roll/pitch std)")
    ap.add_argument("--prior-std-deg", type=float, default=1.0, help="attitude prior std (0 = vision only)")
    args = ap.parse_args()
    cfg = sim_config(Path("/tmp/rack_field_loop"), {})
    camera = load_camera_model(cfg.camera)
    render = SceneRenderer.from_config(cfg, camera, seed=args.seed, appearance=args.appearance)
    kw = ({} if args.library else dict(DAEMON_RACK_TRACKER)) | parse_set(args.set)
    tracker = RackTracker(RackModel.load(cfg.rack.model), camera, RackTrackerConfig(**kw))
    T_ned_rack, T_body_cam = cfg.rack.T_ned_rack, render.T_body_cam
    poses, names = trajectory(args.height, args.seed, args.wobble)
    rng = np.random.default_rng([args.seed, 14])
    err_cm, ang_deg, lost, t_s = [], [], 0, 0.0
    for k, T_ned_body in enumerate(poses):
        T_true = frames.T_rack_cam_from_T_ned_body(T_ned_body, T_ned_rack, T_body_cam)
        img = render(T_ned_body)
        gray = img if img.ndim == 2 else img[..., 0]
        if k == 0:
            tracker.reset(T_true)
        prior: dict[str, Any] = {}
        if args.prior_std_deg > 0:
            rpy = frames.euler_zyx_from_rotation(T_ned_body[:3, :3])
            noise = rng.normal(0.0, math.radians(0.3), 2)
            R_nb = frames.rotation_from_euler_zyx(rpy[0] + noise[0], rpy[1] + noise[1], 0.0)
            prior = {"R_prior": T_ned_rack[:3, :3].T @ R_nb @ T_body_cam[:3, :3],
                     "R_prior_std_rad": math.radians(args.prior_std_deg)}
        t0 = time.perf_counter()
        est = tracker.track(gray, k / RATE_HZ, **prior)
        t_s += time.perf_counter() - t0
        lost += int(not est.ok)
        T = np.asarray(est.T_rack_cam)
        err_cm.append((T[:3, 3] - T_true[:3, 3]) * 100.0)
        c = (np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1.0) / 2.0
        ang_deg.append(math.degrees(math.acos(min(1.0, max(-1.0, c)))))
    e, a, ph = np.array(err_cm), np.array(ang_deg), np.array(names)

    def stats(m: Any) -> dict[str, float]:
        return {"rms_cm": round(float(np.sqrt((e[m] ** 2).sum(1).mean())), 2),
                "max_cm": round(float(np.linalg.norm(e[m], axis=1).max()), 2),
                "rms_x_y_z_cm": [round(float(np.sqrt((e[m][:, j] ** 2).mean())), 2) for j in range(3)],
                "rms_deg": round(float(np.sqrt((a[m] ** 2).mean())), 3)}

    out = {"benchmark": "rack_field_loop", "appearance": args.appearance, "seed": args.seed,
           "settings": "library" if args.library else "daemon", "overrides": parse_set(args.set),
           "height_above_deck_m": args.height, "wobble": args.wobble, "prior_std_deg": args.prior_std_deg,
           "frames": len(poses),
           "lost_frames": lost, "frames_per_s": round(len(poses) / t_s, 1), **stats(np.ones(len(poses), bool)),
           "phases": {n: stats(ph == n) for n, _ in waypoints(args.height)[1:]}}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
