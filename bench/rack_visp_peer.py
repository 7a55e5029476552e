"""Benchmark: a peer nobody here wrote, ViSP's model-based tracker, on the stress bench's frames (issue #14).

Prints ONE JSON object. For each cell and seed of `bench/rack_stress.py`'s frozen matrix (the same cached
frames, the same start 1 cm / 0.5 deg off the true first pose), three trackers run on the same frames:
- `visp_hybrid`: ViSP 3.5's `vpMbGenericTracker` with moving edges and KLT points on the model's cylinders (the
  peer of the issue's evaluation), through `bench/visp_peer/rack_peer.cpp`, built here against Debian's
  `libvisp-dev` (`apt-get install libvisp-dev`); ViSP's tutorial settings, not tuned on these scenes;
- `visp_edge`: the same with moving edges only;
- `ours`: `RackTracker` with its default configuration, vision only (the stress bench's `vision` row).
The model given to ViSP is the one our tracker gets (its wrong gaps in the wrong-gap cell: ViSP cannot estimate
them). ViSP's camera model has one radial coefficient, so in the two cells with lens distortion it gets the
frames undistorted with the calibration (cv2.undistort, same intrinsics), as its users do with a two-coefficient
calibration; our tracker gets the distorted frames and the calibration. A frame where ViSP throws counts as lost
(its last pose is kept and it starts again from there).

With `--scene default` the frames come instead from the project's own renderer (`companion.sim.rack_scene`,
the appearance `bench/rack_table1.py` uses: dense-free spots, plain ground) over the same tour (noise 6 grey
levels, blur 0.7 px), for the issue's cases: 2 pipes / 10 spots, 4 / 40, 5 / 50 and the paper's §V rack
(`DEFAULT_CASES`), as a check that the peer and its harness track where the scene is easy.

Usage: python bench/rack_visp_peer.py [--scene stress|default] [--seeds tuning|heldback|all] [--cells a,b]
       [--frames N] [--no-ours]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import rack_stress as rs  # noqa: E402

from companion.geometry import se3  # noqa: E402
from companion.sim.rack_scene import RackScene, RackSceneConfig  # noqa: E402
from companion.vision.rack import RackModel  # noqa: E402

PEER_SOURCE = ROOT / "bench" / "visp_peer" / "rack_peer.cpp"
# --scene default: (rack of `rs.build_rack`, spots in total over the rack), the cases
DEFAULT_CASES: dict[str, dict[str, Any]] = {
    "default_p2_f10_tour": dict(rack="p2", F=10, traj="tour"),
    "default_p4_f40_tour": dict(rack="p4", F=40, traj="tour"),
    "default_p5_f50_tour": dict(rack="p5", F=50, traj="tour"),
    "default_paper_s5_f40_tour": dict(rack="paper_s5", F=40, traj="tour"),
}


def render_default_run(name: str, case: dict[str, Any], seed: int) -> dict[str, Any]:
    """A run (poses, PNG frames) of the project's own renderer over the stress bench's trajectory."""
    cell_seed = int(hashlib.sha256(f"{name}/{seed}".encode()).hexdigest()[:8], 16)
    rng = np.random.default_rng(cell_seed)
    model = rs.build_rack(case["rack"])
    scene = RackScene(model, seed=cell_seed, config=RackSceneConfig(total_spots=case["F"]))
    poses = rs.make_trajectory(case["traj"], model, rng)
    frames = [cv2.imencode(".png", scene.render(T, rs.CAMERA, noise_std=rs.NOISE_STD, blur_sigma_px=rs.BLUR_PX,
                                                rng=rng))[1].tobytes() for T in poses]
    return {"poses": poses, "frames": frames, "distort": False, "cell_seed": cell_seed}


def build_peer(build_dir: Path) -> Path:
    """Compile the ViSP peer (cached by the source's hash); SystemExit naming the missing package if it cannot."""
    src = PEER_SOURCE.read_bytes()
    exe = build_dir / f"rack_peer_{hashlib.sha256(src).hexdigest()[:12]}"
    if exe.exists():
        return exe
    try:
        flags = subprocess.run(["pkg-config", "--cflags", "--libs", "visp"], capture_output=True, text=True,
                               check=True).stdout.split()
    except (OSError, subprocess.CalledProcessError) as exc:
        raise SystemExit(f"rack_visp_peer: ViSP not found by pkg-config ({exc}); apt-get install libvisp-dev") from exc
    build_dir.mkdir(parents=True, exist_ok=True)
    tmp = exe.with_suffix(".tmp")
    res = subprocess.run(["g++", "-O2", "-o", str(tmp), str(PEER_SOURCE), *flags], capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"rack_visp_peer: building {PEER_SOURCE.name} failed:\n{res.stderr[-3000:]}")
    tmp.replace(exe)
    return exe


def cao_model(model: RackModel) -> str:
    """ViSP's CAO (V1) text of the rack: one cylinder per pipe between its axis' end points (rack frame, m)."""
    pipes = model.pipe_arrays()
    pts = []
    for c, v, length in zip(pipes.starts, pipes.directions, pipes.lengths, strict=True):
        pts += [c, c + length * v]
    lines = ["V1", "# 3D Points", str(len(pts))]
    lines += [" ".join(f"{x:.9f}" for x in p) for p in pts]
    lines += ["# 3D Lines", "0", "# Faces from 3D lines", "0", "# Faces from 3D points", "0", "# 3D cylinders",
              str(len(pipes.radii))]
    lines += [f"{2 * m} {2 * m + 1} {r:.9f}" for m, r in enumerate(pipes.radii)]
    lines += ["# 3D circles", "0", ""]
    return "\n".join(lines)


def start_pose(run: dict[str, Any]) -> np.ndarray:
    """The stress bench's start: the true first pose moved 1 cm / 0.5 deg (the same draw as `rs.track_run`)."""
    T0: np.ndarray = run["poses"][0] @ se3.exp(rs.start_offset(np.random.default_rng(run["cell_seed"] + 1)))
    return T0


def run_visp(exe: Path, model: RackModel, run: dict[str, Any], n: int, mode: str, work: Path,
             me: dict[str, float] | None = None) -> dict[str, Any]:
    """ViSP over the first `n` frames of `run`: per-frame position / orientation errors, lost frames, time.

    `me`: moving-edge settings other than ViSP's tutorial values (keys range, threshold, step, mu)."""
    frames_dir = work / "frames"
    if not frames_dir.exists():
        frames_dir.mkdir()
        undistort = run["distort"]
        cam = rs.CAMERA_DIST
        K = np.array([[cam.fx, cam.skew, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
        for k in range(n):
            img = rs.decode_frame(run["frames"][k])
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            if undistort:
                img = cv2.undistort(img, K, np.asarray(cam.dist, dtype=np.float64))
            cv2.imwrite(str(frames_dir / f"frame_{k:05d}.pgm"), img)
    (work / "rack.cao").write_text(cao_model(model))
    cMo = np.linalg.inv(start_pose(run))
    (work / "init.txt").write_text(" ".join(f"{x:.12f}" for x in cMo.ravel()))
    out = work / f"poses_{mode}.txt"
    cam = rs.CAMERA
    t0 = time.perf_counter()
    res = subprocess.run([str(exe), str(work / "rack.cao"), str(frames_dir), str(n), repr(cam.fx), repr(cam.fy),
                          repr(cam.cx), repr(cam.cy), str(work / "init.txt"), mode, str(out)],
                         capture_output=True, text=True,
                         env={**os.environ, **{f"RACK_PEER_ME_{k.upper()}": repr(v) for k, v in (me or {}).items()}})
    elapsed = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"rack_visp_peer: the peer failed ({res.returncode}): {res.stderr[-2000:]}")
    perr, aerr, lost = [], [], 0
    rows = [ln.split() for ln in out.read_text().splitlines()]
    if len(rows) != n:
        raise SystemExit(f"rack_visp_peer: the peer wrote {len(rows)} poses for {n} frames")
    for k, row in enumerate(rows):
        vals = np.array([float(x) for x in row[1:]])
        cMo = np.eye(4)
        cMo[:3, :] = vals.reshape(3, 4)
        p, a = rs.pose_errors(np.linalg.inv(cMo), run["poses"][k])
        perr.append(p)
        aerr.append(a)
        lost += 0 if row[0] == "1" else 1
    # the peer's wall time per frame includes reading the PGM: an upper bound of its tracking time
    return {"perr": perr, "aerr": aerr, "lost": lost, "t_ms": [1000.0 * elapsed / n] * n, "gap_err_100_cm": None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", choices=("stress", "default"), default="stress")
    ap.add_argument("--seeds", choices=("tuning", "heldback", "all"), default="tuning")
    ap.add_argument("--cells", default="", help="comma-separated subset of the stress bench's cells")
    ap.add_argument("--frames", type=int, default=0, help="first N frames of each run (default: all)")
    ap.add_argument("--no-ours", action="store_true", help="ViSP only (our tracker's rows: bench/rack_stress.py)")
    for key, help_ in (("range", "search range (px), tutorial 8"),
                       ("threshold", "likelihood threshold, tutorial 10000"),
                       ("step", "sample step along a limb (px), tutorial 4"),
                       ("mu", "contrast tolerance, tutorial 0.5")):
        ap.add_argument(f"--me-{key}", type=float, default=None, help=f"ViSP moving edges: {help_}")
    ap.add_argument("--cache-dir", default=os.environ.get("RACK_STRESS_CACHE", "/tmp/rack_stress_cache"))
    ap.add_argument("--build-dir", default=os.path.join(tempfile.gettempdir(), "rack_visp_peer"))
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t_start = time.perf_counter()
    exe = build_peer(Path(args.build_dir))
    seeds = {"tuning": rs.TUNING_SEEDS, "heldback": rs.HELDBACK_SEEDS,
             "all": rs.TUNING_SEEDS + rs.HELDBACK_SEEDS}[args.seeds]
    matrix = rs.CELLS if args.scene == "stress" else DEFAULT_CASES
    wanted = [c.strip() for c in args.cells.split(",") if c.strip()] or list(matrix)
    for c in wanted:
        if c not in matrix:
            raise SystemExit(f"--cells: unknown cell {c!r} (of --scene {args.scene})")
    rows = ["visp_hybrid", "visp_edge"] + ([] if args.no_ours else ["ours"])
    me = {k: float(v) for k in ("range", "threshold", "step", "mu") if (v := getattr(args, f"me_{k}")) is not None}
    cells: dict[str, dict[str, Any]] = {}
    for name in wanted:
        cell = matrix[name]
        model = rs.paper_s5_rack(cell["model_gaps"]) if "model_gaps" in cell else rs.build_rack(cell["rack"])
        per_row: dict[str, list[dict[str, Any]]] = {r: [] for r in rows}
        for seed in seeds:
            run = rs.load_run(name, cell, seed, Path(args.cache_dir)) if args.scene == "stress" \
                else render_default_run(name, cell, seed)
            n = min(args.frames or len(run["frames"]), len(run["frames"]))
            work = Path(tempfile.mkdtemp(prefix="visp_peer_"))
            try:
                for r in rows:
                    if r == "ours":
                        res = rs.track_run(name, cell, seed, run, "vision", {}, n)
                    else:
                        res = run_visp(exe, model, run, n, r.removeprefix("visp_"), work, me)
                    per_row[r].append(res)
                    print(f"{name} seed {seed} {r}: rms {100 * np.sqrt(np.mean(np.square(res['perr']))):.2f} cm "
                          f"{np.sqrt(np.mean(np.square(res['aerr']))):.3f} deg, lost {res['lost']}, {n} frames",
                          file=sys.stderr, flush=True)
            finally:
                shutil.rmtree(work, ignore_errors=True)
        cells[name] = {"seeds": list(seeds), "rows": {r: rs.summarize(v) for r, v in per_row.items()}}
    summary = {r: rs.row_summary({n: {"rows": {r: c["rows"][r]}} for n, c in cells.items()}, r) for r in rows}
    out: dict[str, Any] = {"benchmark": "rack_visp_peer", "scene": args.scene, "seeds": args.seeds,
                           "seed_values": list(seeds), "visp_moving_edges": me or "ViSP's tutorial values",
                           "frames": args.frames or "all", "visp": subprocess.run(
                               ["pkg-config", "--modversion", "visp"], capture_output=True, text=True).stdout.strip(),
                           "cells": cells, "summary": summary,
                           "fps_note": "ViSP rows: frames over the peer process's wall time (reading the PGM frames "
                                       "and the model included), an upper bound of its tracking time; ours: time "
                                       "inside track()"}
    if not args.no_ours:
        out["ours_position_le_visp_hybrid"] = sum(
            c["rows"]["ours"]["rms_position_cm"] <= c["rows"]["visp_hybrid"]["rms_position_cm"] for c in cells.values())
        out["ours_orientation_le_visp_hybrid"] = sum(
            c["rows"]["ours"]["rms_orientation_deg"] <= c["rows"]["visp_hybrid"]["rms_orientation_deg"]
            for c in cells.values())
        out["ours_orientation_le_visp_edge"] = sum(
            c["rows"]["ours"]["rms_orientation_deg"] <= c["rows"]["visp_edge"]["rms_orientation_deg"]
            for c in cells.values())
    out["elapsed_s"] = time.perf_counter() - t_start
    print(json.dumps(out))


if __name__ == "__main__":
    main()
