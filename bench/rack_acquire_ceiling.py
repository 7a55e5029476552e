"""Benchmark: what the rack tracker itself allows on `bench/rack_acquire.py`'s views. Prints ONE JSON object.

The acquisition bench counts an attempt correct when the daemon's tracker, reset at the acquired pose and run
on the same image, ends within 3 cm in x and z and 1 deg of the truth with the frame accepted. Here the
tracker starts at the TRUE pose instead, on the same seeded views (`rack_acquire.view_cases`), so the rates
bound what any acquisition could score with that tracker:

- `--mode one`: the default tight reset prior and one frame (a perfect acquisition; the acquisition bench's
  `tracker_from_truth_rate`);
- `--mode settle`: the tight reset, then nine frames of the same image (does the tracker hold the truth?);
- `--mode loose`: a reset prior of 10 cm / 2 deg (its wide first search) and three frames: where the image and
  the edge model put the pose when the start does not hold it.

Each with the autopilot's noisy roll and pitch as the attitude prior (1 deg, as the daemon gives it) and
without. `--settings daemon` (`DAEMON_RACK_TRACKER`) or `library` (`RackTrackerConfig()` defaults). Rates over
the views with at least two parallel pipes fully in view, per appearance and per number of pipes in full view;
a rejected frame (`ok` false: its pose is the prediction) is not within the bar and is counted apart.

Usage: python bench/rack_acquire_ceiling.py [--views 500] [--appearance default|field|both] [--seed 1]
                                            [--mode one|settle|loose] [--settings daemon|library]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import rack_acquire as ra  # noqa: E402

from companion.daemon.wiring import DAEMON_RACK_TRACKER  # noqa: E402
from companion.vision.rack import RackTracker, RackTrackerConfig  # noqa: E402

MODES = {"one": (False, 1), "settle": (False, 9), "loose": (True, 3)}  # (loose reset prior, frames)


def run_view(case: dict[str, Any], cfg: RackTrackerConfig, mode: str, with_prior: bool) -> dict[str, Any]:
    """Track `case`'s image from its true pose as `mode` says; the final pose's error and whether it is in the bar."""
    loose, frames = MODES[mode]
    T_true = case["T"]
    tr = RackTracker(case["model"], ra.CAMERA, cfg)
    if loose:
        tr.reset(T_true, position_std_m=0.10, rotation_std_rad=float(np.deg2rad(2.0)))
    else:
        tr.reset(T_true)
    prior = ra.attitude_prior(case["prior"]) if with_prior else {}
    for k in range(frames):
        est = tr.track(case["img"], k / 25.0, **prior)
    err = ra.pose_error(est.T_rack_cam, T_true)
    return {"dx_cm": err["dx_m"] * 100, "dz_cm": err["dz_m"] * 100, "rot_deg": err["rot_deg"], "ok": bool(est.ok),
            "within": bool(est.ok and err["pose_within"])}


def rates(rows: list[dict[str, Any]], key: str) -> dict[str, Any]:
    n = len(rows)
    return {"views": n, "within_rate": sum(r[key]["within"] for r in rows) / n if n else None,
            "rejected": sum(not r[key]["ok"] for r in rows)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=500)
    ap.add_argument("--appearance", choices=("default", "field", "both"), default="both")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--mode", choices=tuple(MODES), default="one")
    ap.add_argument("--settings", choices=("daemon", "library"), default="daemon")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    cfg = RackTrackerConfig(**DAEMON_RACK_TRACKER) if args.settings == "daemon" else RackTrackerConfig()
    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    for case in ra.view_cases(args.views, args.appearance, args.seed, 20.0):
        if case["n_full"] < 2:
            continue
        if case["view"] % 50 == 0 and case["appearance"] in ("default", "field-grating"):
            print(f"view {case['view']}/{args.views}, {time.perf_counter() - t_start:.0f} s", file=sys.stderr)
        rows.append({"view": case["view"], "appearance": case["appearance"], "n_full": case["n_full"],
                     "prior": run_view(case, cfg, args.mode, True), "no_prior": run_view(case, cfg, args.mode, False)})
    out: dict[str, Any] = {"benchmark": "rack_acquire_ceiling", "views": args.views, "appearance": args.appearance,
                           "seed": args.seed, "mode": args.mode, "settings": args.settings, "by_appearance": {}}
    for app in sorted({r["appearance"].split("-")[0] for r in rows}):
        sel = [r for r in rows if r["appearance"].startswith(app)]
        out["by_appearance"][app] = {
            "with_prior": rates(sel, "prior"), "no_prior": rates(sel, "no_prior"),
            "by_pipes_in_view": {str(n): {"with_prior": rates([r for r in sel if r["n_full"] == n], "prior"),
                                          "no_prior": rates([r for r in sel if r["n_full"] == n], "no_prior")}
                                 for n in sorted({r["n_full"] for r in sel})},
        }
    out["machine"] = {"python": platform.python_version(), "opencv": cv2.__version__, "threads": 1,
                      "load_average_at_end": [round(x, 2) for x in os.getloadavg()]}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
