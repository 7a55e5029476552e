"""Benchmark: the rack tracker over grounds nobody here made -- photographs (issue #14). Prints ONE JSON object.

The stress bench's grounds (`bench/rack_stress.py`) are procedural textures written in this project, and the
tracker was tuned on them for weeks. Here the ground under the rack is a photograph instead: scikit-image's
bundled texture photos (`skimage.data.brick`, `grass`, `gravel`, 512x512 grey; the ground odometer's simulator
uses them, the rack tracker never saw them), mirrored into a seamless tile
of 2.4 m and laid on the ground plane at 1.2 m per photo width (a brick 5 x 25 cm, a stone 2-4 cm), their grey
levels stretched to 0.06-0.9 (1st-99th percentile) so that the ground is as contrasted as the pipes. The brick
paving's joints run along the pipes, next to and parallel to the limbs. Everything else is the stress bench's:
the field appearance (`companion.sim.rack_scene_field`: sparse spots, pale shaded cladding, shadows, beams,
JPEG q70), the camera (720x480, f = 630, 25 Hz, noise 6 grey levels, blur 0.7 px, motion blur), the paper's tour
with wind, the start 1 cm / 0.5 deg off, the rows (`vision`, `edge_only`, `prior`) and their summaries.

The matrix below was written down on 2026-12-02 before any run, and it is an evaluation only: no tracker
setting is to be chosen on it (tune on `bench/rack_stress.py`'s tuning half). Its seeds are new.

    python bench/rack_photo_ground.py [--cells a,b] [--rows vision,edge_only,prior] [--render-only]

Frames are cached as in the stress bench (`--cache-dir`), keyed by the photo's pixels and the renderer's code.
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import json
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import rack_stress as rs  # the stress bench: its renderer set-up, tracker runs and summaries

from companion.sim.ground_scene import load_texture  # the ground odometer's photos

PHOTO_WIDTH_M = 1.2  # one photo width on the ground
SEEDS = (10, 11)  # new seeds, never used for tuning
# name: the stress bench's cell keys, and the photograph
PHOTO_CELLS: dict[str, dict[str, Any]] = {
    f"{rack}_f{F}_{photo}_tour": dict(rack=rack, F=F, ground="natural", traj="tour", photo=photo)
    for rack, F in (("p2", 10), ("p4", 40), ("paper_s5", 100))
    for photo in ("brick", "grass", "gravel")
}


def photo_albedo(name: str) -> np.ndarray[Any, np.dtype[np.float32]]:
    """The photograph `name` of scikit-image's data as a seamless ground albedo tile (1024 x 1024, 0.06..0.9)."""
    g = load_texture(name).astype(np.float32)
    lo, hi = np.percentile(g, [1.0, 99.0])
    g = 0.06 + 0.84 * np.clip((g - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    # mirrored copies: the wrapping lookup of the renderer then meets no seam
    return np.ascontiguousarray(np.block([[g, g[:, ::-1]], [g[::-1], g[::-1, ::-1]]]), dtype=np.float32)


def load_photo_run(name: str, cell: dict[str, Any], seed: int, cache: Path | None) -> dict[str, Any]:
    albedo = photo_albedo(cell["photo"])
    texel_m = PHOTO_WIDTH_M / (albedo.shape[1] // 2)
    scene_cell = {k: v for k, v in cell.items() if k != "photo"}
    h = hashlib.sha256(rs._source_key(cell, seed).encode())
    h.update(albedo.tobytes())
    h.update(repr(PHOTO_WIDTH_M).encode())
    h.update(inspect.getsource(load_photo_run).encode())  # the albedo's own bytes are hashed above
    path = None if cache is None else cache / f"photo_{name}_s{seed}_{h.hexdigest()[:20]}.pkl"
    return rs.cached_pickle(path, lambda: rs.render_run(name, scene_cell, seed, albedo, texel_m))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", default="", help="comma-separated subset of the cells")
    ap.add_argument("--rows", default="vision,edge_only,prior")
    ap.add_argument("--cache-dir", default="/tmp/rack_stress_cache")
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--render-only", action="store_true")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t_start = time.perf_counter()
    wanted = [c.strip() for c in args.cells.split(",") if c.strip()] or list(PHOTO_CELLS)
    for c in wanted:
        if c not in PHOTO_CELLS:
            raise SystemExit(f"--cells: unknown cell {c!r}; known: {', '.join(PHOTO_CELLS)}")
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    cache = None if args.no_cache else Path(args.cache_dir)
    out_cells: dict[str, dict[str, Any]] = {}
    for k, name in enumerate(wanted):
        cell = PHOTO_CELLS[name]
        per_row: dict[str, list[dict[str, Any]]] = {r: [] for r in rows}
        for seed in SEEDS:
            run = load_photo_run(name, cell, seed, cache)
            print(f"[{k + 1}/{len(wanted)}] {name} seed {seed}: {len(run['frames'])} frames", file=sys.stderr,
                  flush=True)
            if args.render_only:
                continue
            for r in rows:
                res = rs.track_run(name, cell, seed, run, r, {}, None)
                per_row[r].append(res)
                print(f"  {r}: rms {100 * np.sqrt(np.mean(np.square(res['perr']))):.2f} cm "
                      f"{np.sqrt(np.mean(np.square(res['aerr']))):.3f} deg, lost {res['lost']}", file=sys.stderr,
                      flush=True)
        if not args.render_only:
            out_cells[name] = {"spec": cell, "seeds": list(SEEDS),
                               "rows": {r: rs.summarize(v) for r, v in per_row.items()}}
    summary = {r: rs.row_summary(out_cells, r) for r in rows} if out_cells else {}
    print(json.dumps({
        "benchmark": "rack_photo_ground", "seeds": list(SEEDS), "photo_width_m": PHOTO_WIDTH_M,
        "render_only": args.render_only, "cells": out_cells, "summary": summary,
        "acceptance": rs.acceptance(out_cells, summary) if out_cells else {},
        "compiled_kernels": rs.compiled_names(), "elapsed_s": time.perf_counter() - t_start,
    }))


if __name__ == "__main__":
    main()
