"""A/B of two `acquire_rack` implementations on the same views, timed interleaved. Prints ONE JSON object.

The machine may be shared: a time measured in one run and compared with one measured an hour
later says little. This renders the views of `bench/rack_acquire.py` once (`--cache`, pickled),
then runs each implementation in its own worker process (`--old` / `--new`: the roots of two
checkouts, e.g. a git worktree at the base commit and this one) and hands them the views in turn,
alternating which goes first, so both see the same load. Each call is timed in its worker (one
thread); per view the decisions are compared: confident, status, number of hypotheses, and for
every hypothesis its direction, pipes, y_observed, score and pose (largest differences reported).

Usage:
  python bench/rack_acquire_ab.py --cache /tmp/views.pkl --views 120 --appearance both   # render
  python bench/rack_acquire_ab.py --cache /tmp/views.pkl --old ../base --new . [--repeat 3]
  python bench/rack_acquire_ab.py --cache /tmp/views.pkl --run . --count 240 --profile          # cProfile
  valgrind --tool=callgrind python bench/rack_acquire_ab.py --cache /tmp/views.pkl --run . --count 40
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def render(path: str, views: int, appearance: str, seed: int, yaw_std_deg: float) -> None:
    sys.path.insert(0, HERE)
    import rack_acquire  # the same views as the bench

    cases = []
    for c in rack_acquire.view_cases(views, appearance, seed, yaw_std_deg):
        c.pop("model")
        cases.append(c)
    with open(path, "wb") as f:
        pickle.dump({"views": views, "appearance": appearance, "seed": seed, "yaw_std_deg": yaw_std_deg,
                     "cases": cases}, f)
    print(json.dumps({"cached": path, "attempts": len(cases)}))


def _load(root: str, path: str) -> tuple[Any, dict[str, Any], Any, list[dict[str, Any]]]:
    """Checkout `root`'s `acquire_rack`, the bench's rack models, the 720x480 camera and the cached attempts."""
    sys.path.insert(0, root)
    import cv2

    from companion.camera import PinholeCamera
    from companion.vision.rack import RackModel, acquire_rack

    cv2.setNumThreads(1)
    sys.path.insert(0, os.path.join(root, "bench"))
    import rack_acquire

    models = dict(rack_acquire.racks())
    assert all(isinstance(m, RackModel) for m in models.values())
    cam = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
    with open(path, "rb") as f:
        cases = pickle.load(f)["cases"]
    return acquire_rack, models, cam, cases


def worker(root: str, path: str) -> None:
    """Serve `index repeat` lines from stdin: one JSON line per request (times and the decision)."""
    acquire_rack, models, cam, cases = _load(root, path)
    for line in sys.stdin:
        i, rep = (int(v) for v in line.split())
        c = cases[i]
        ms = []
        res = None
        for _ in range(rep):
            t0 = time.perf_counter()
            res = acquire_rack(c["img"], models[c["rack"]], cam, c["prior"])
            ms.append((time.perf_counter() - t0) * 1e3)
        assert res is not None
        hyps = [{"reversed": h.reversed, "pipes": list(h.pipes), "y_observed": h.y_observed, "score": h.score,
                 "T": np.asarray(h.T_rack_cam).tolist()} for h in res.hypotheses]
        print(json.dumps({"ms": ms, "confident": res.confident, "status": res.status, "hyps": hyps}), flush=True)


def run(root: str, path: str, count: int, profile: bool) -> None:
    """One warm-up call, then `acquire_rack` on the first `count` cached attempts of checkout `root`
    (for `valgrind --tool=callgrind`: instructions with `count` minus with 0), under cProfile when asked."""
    import cProfile
    import pstats

    acquire_rack, models, cam, cases = _load(root, path)
    acquire_rack(cases[0]["img"], models[cases[0]["rack"]], cam, cases[0]["prior"])
    prof = cProfile.Profile() if profile else None
    if prof is not None:
        prof.enable()
    for c in cases[:count]:
        acquire_rack(c["img"], models[c["rack"]], cam, c["prior"])
    if prof is not None:
        prof.disable()
        pstats.Stats(prof).sort_stats("cumulative").print_stats(40)


def compare(a: dict[str, Any], b: dict[str, Any]) -> tuple[bool, float, float]:
    """(same decision, largest pose difference, largest score difference) of two worker answers."""
    same = a["confident"] == b["confident"] and a["status"] == b["status"] and len(a["hyps"]) == len(b["hyps"])
    dT, ds = 0.0, 0.0
    for ha, hb in zip(a["hyps"], b["hyps"], strict=False):
        same = same and all(ha[k] == hb[k] for k in ("reversed", "pipes", "y_observed"))
        dT = max(dT, float(np.max(np.abs(np.asarray(ha["T"]) - np.asarray(hb["T"])))))
        ds = max(ds, abs(ha["score"] - hb["score"]))
    return same, dT, ds


def outcome(case: dict[str, Any], ans: dict[str, Any]) -> str:
    """confident_right / confident_wrong / not_confident (assignment as in the bench; no tracking step)."""
    if not ans["confident"]:
        return "not_confident"
    h = ans["hyps"][0]
    right = not h["reversed"] and abs(h["T"][0][3] - float(case["T"][0, 3])) < case["pitch_min"] / 2
    return "confident_right" if right else "confident_wrong"


def ab(path: str, old: str, new: str, repeat: int) -> None:
    with open(path, "rb") as f:
        data = pickle.load(f)
    cases = data["cases"]
    env = dict(os.environ, PYTHONHASHSEED="0")
    procs = {name: subprocess.Popen([sys.executable, os.path.abspath(__file__), "--worker", root, "--cache", path],
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=root)
             for name, root in (("old", old), ("new", new))}
    answers: dict[str, list[dict[str, Any]]] = {"old": [], "new": []}
    for i in range(len(cases)):
        order = ("old", "new") if i % 2 == 0 else ("new", "old")
        for name in order:
            p = procs[name]
            assert p.stdin is not None and p.stdout is not None
            p.stdin.write(f"{i} {repeat}\n")
            p.stdin.flush()
            answers[name].append(json.loads(p.stdout.readline()))
    for p in procs.values():
        assert p.stdin is not None
        p.stdin.close()
        p.wait()
    same, dT, ds = [], [], []
    for a, b in zip(answers["old"], answers["new"], strict=True):
        s, t, sc = compare(a, b)
        same.append(s)
        dT.append(t)
        ds.append(sc)
    t_old = np.array([a["ms"] for a in answers["old"]])  # (views, repeat)
    t_new = np.array([a["ms"] for a in answers["new"]])
    two = [k for k, c in enumerate(cases) if c["n_full"] >= 2]

    def counts(name: str) -> dict[str, int]:
        out: dict[str, int] = {}
        for k in two:
            o = outcome(cases[k], answers[name][k])
            out[o] = out.get(o, 0) + 1
        return out

    print(json.dumps({
        "benchmark": "rack_acquire_ab", "views": data["views"], "appearance": data["appearance"], "seed": data["seed"],
        "attempts": len(cases), "repeat": repeat, "old": old, "new": new,
        "median_ms": {"old": float(np.median(t_old)), "new": float(np.median(t_new))},
        "median_of_per_view_min_ms": {"old": float(np.median(t_old.min(axis=1))),
                                      "new": float(np.median(t_new.min(axis=1)))},
        "ratio_new_old_of_medians": float(np.median(t_new) / np.median(t_old)),
        "median_per_view_ratio": float(np.median(t_new.min(axis=1) / t_old.min(axis=1))),
        "total_s": {"old": float(t_old.sum() / 1e3), "new": float(t_new.sum() / 1e3)},
        "same_decision": int(sum(same)), "different_decision_attempts": [
            [cases[k]["view"], cases[k]["appearance"]] for k in range(len(cases)) if not same[k]],
        "max_pose_diff": float(max(dT)), "max_score_diff": float(max(ds)),
        "two_or_more_pipes_outcomes": {"old": counts("old"), "new": counts("new"), "attempts": len(two)},
        "load_average_at_end": [round(x, 2) for x in os.getloadavg()],
    }, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", required=True)
    ap.add_argument("--views", type=int, default=120)
    ap.add_argument("--appearance", choices=("default", "field", "both"), default="both")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--yaw-std-deg", type=float, default=20.0)
    ap.add_argument("--old")
    ap.add_argument("--new")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--worker")
    ap.add_argument("--run", help="checkout root: run the first --count attempts (for callgrind / --profile)")
    ap.add_argument("--count", type=int, default=40)
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.cache)
    elif args.run:
        run(args.run, args.cache, args.count, args.profile)
    elif args.old and args.new:
        ab(args.cache, args.old, args.new, args.repeat)
    else:
        render(args.cache, args.views, args.appearance, args.seed, args.yaw_std_deg)


if __name__ == "__main__":
    main()
