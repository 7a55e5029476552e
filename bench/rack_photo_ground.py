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

A second set, `--photos gimp` (written down on 2026-12-02 at 10:40, before any run, after the first set's brick
paving had been looked into): four ground photographs of GIMP's pattern library (Debian's `gimp-data`, not in
this project's tree: `apt-get install gimp-data`): a dry-stone wall (`rock`), flagstones (`stone33`), paving
with curved joints (`terra`) and a brick wall (`brick`, transposed so that its long joints run along the pipes
again); seamless tiles of 64-156 px laid at 0.8 m per tile (5-12 mm a texel, about a camera pixel's footprint on
the ground), grey levels stretched as above; the same racks; seeds 12 and 13, new.

    python bench/rack_photo_ground.py [--photos skimage|gimp] [--cells a,b] [--rows vision,edge_only,prior]
           [--render-only]

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
GIMP_PATTERNS = Path("/usr/share/gimp/2.0/patterns")
GIMP_TILE_M = 0.8  # one pattern tile on the ground
GIMP_SEEDS = (12, 13)  # new seeds, never used for tuning
GIMP_CELLS: dict[str, dict[str, Any]] = {
    f"{rack}_f{F}_gimp_{photo}_tour": dict(rack=rack, F=F, ground="natural", traj="tour", gimp=photo,
                                           gimp_transposed=photo == "brick")
    for rack, F in (("p2", 10), ("p4", 40), ("paper_s5", 100))
    for photo in ("rock", "stone33", "terra", "brick")
}  # albedo columns run along rack x, rows along y: the brick tile is transposed so its long joints run along y


def gimp_pattern(name: str) -> np.ndarray[Any, np.dtype[np.uint8]]:
    """Grey pixels of GIMP's pattern `Stone/<name>.pat` (its header: size, version, width, height, bytes per
    pixel, magic "GPAT", name; then the rows)."""
    path = GIMP_PATTERNS / "Stone" / f"{name}.pat"
    if not path.is_file():
        raise SystemExit(f"{path}: not found; GIMP's patterns come with Debian's gimp-data (apt-get install gimp-data)")
    raw = path.read_bytes()
    header, _version, w, h, depth = (int.from_bytes(raw[i : i + 4], "big") for i in range(0, 20, 4))
    if raw[20:24] != b"GPAT" or depth not in (1, 3) or len(raw) < header + w * h * depth:
        raise SystemExit(f"{path}: not a grey or RGB GIMP pattern")
    px = np.frombuffer(raw[header : header + w * h * depth], dtype=np.uint8).reshape(h, w, depth)
    return px[:, :, 0].copy() if depth == 1 else cv2.cvtColor(px, cv2.COLOR_RGB2GRAY)


def stretched(g: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.float32]]:
    """Grey levels stretched to 0.06..0.9 between their 1st and 99th percentiles (as contrasted as the pipes)."""
    g = g.astype(np.float32)
    lo, hi = np.percentile(g, [1.0, 99.0])
    return np.asarray(0.06 + 0.84 * np.clip((g - lo) / max(hi - lo, 1e-6), 0.0, 1.0), dtype=np.float32)


def photo_albedo(name: str) -> np.ndarray[Any, np.dtype[np.float32]]:
    """The photograph `name` of scikit-image's data as a seamless ground albedo tile (1024 x 1024, 0.06..0.9)."""
    g = stretched(load_texture(name))
    # mirrored copies: the wrapping lookup of the renderer then meets no seam
    return np.ascontiguousarray(np.block([[g, g[:, ::-1]], [g[::-1], g[::-1, ::-1]]]), dtype=np.float32)


def load_photo_run(name: str, cell: dict[str, Any], seed: int, cache: Path | None) -> dict[str, Any]:
    if "gimp" in cell:  # a seamless pattern tile: laid as it is, the renderer's lookup wraps
        g = gimp_pattern(cell["gimp"])
        albedo = np.ascontiguousarray(stretched(g.T if cell["gimp_transposed"] else g))
        texel_m = GIMP_TILE_M / albedo.shape[1]
    else:
        albedo = photo_albedo(cell["photo"])
        texel_m = PHOTO_WIDTH_M / (albedo.shape[1] // 2)
    scene_cell = {k: v for k, v in cell.items() if k not in ("photo", "gimp", "gimp_transposed")}
    h = hashlib.sha256(rs._source_key(cell, seed).encode())
    h.update(albedo.tobytes())
    h.update(repr((PHOTO_WIDTH_M, GIMP_TILE_M)).encode() if "gimp" in cell else repr(PHOTO_WIDTH_M).encode())
    h.update(inspect.getsource(load_photo_run).encode())  # the albedo's own bytes are hashed above
    path = None if cache is None else cache / f"photo_{name}_s{seed}_{h.hexdigest()[:20]}.pkl"
    return rs.cached_pickle(path, lambda: rs.render_run(name, scene_cell, seed, albedo, texel_m))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photos", choices=("skimage", "gimp"), default="skimage",
                    help="the photo set: scikit-image's (seeds 10-11) or GIMP's patterns (seeds 12-13)")
    ap.add_argument("--cells", default="", help="comma-separated subset of the cells")
    ap.add_argument("--rows", default="vision,edge_only,prior")
    ap.add_argument("--cache-dir", default="/tmp/rack_stress_cache")
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--render-only", action="store_true")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t_start = time.perf_counter()
    cells, seeds = (GIMP_CELLS, GIMP_SEEDS) if args.photos == "gimp" else (PHOTO_CELLS, SEEDS)
    wanted = [c.strip() for c in args.cells.split(",") if c.strip()] or list(cells)
    for c in wanted:
        if c not in cells:
            raise SystemExit(f"--cells: unknown cell {c!r}; known: {', '.join(cells)}")
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    cache = None if args.no_cache else Path(args.cache_dir)
    out_cells: dict[str, dict[str, Any]] = {}
    for k, name in enumerate(wanted):
        cell = cells[name]
        per_row: dict[str, list[dict[str, Any]]] = {r: [] for r in rows}
        for seed in seeds:
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
            out_cells[name] = {"spec": cell, "seeds": list(seeds),
                               "rows": {r: rs.summarize(v) for r, v in per_row.items()}}
    summary = {r: rs.row_summary(out_cells, r) for r in rows} if out_cells else {}
    print(json.dumps({
        "benchmark": "rack_photo_ground", "photos": args.photos, "seeds": list(seeds),
        "photo_width_m": GIMP_TILE_M if args.photos == "gimp" else PHOTO_WIDTH_M,
        "render_only": args.render_only, "cells": out_cells, "summary": summary,
        "acceptance": rs.acceptance(out_cells, summary) if out_cells else {},
        "compiled_kernels": rs.compiled_names(), "elapsed_s": time.perf_counter() - t_start,
    }))


if __name__ == "__main__":
    main()
