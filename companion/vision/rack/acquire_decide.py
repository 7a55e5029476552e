"""Rack acquisition, step 5: which checked poses are credible, and whether the best deserves confidence.

A pose is credible when the tracker's edge measurement at it (`acquire_verify.EdgeCheck`) shows the
rack's pattern: two pipes with both limbs agreeing over long runs, or at close range (on the deck,
0.6 m over the pipes, where one pipe fills most of the image) one pipe flanked by the facing limbs of
its neighbours; no pipe in full view without edges; a small residual; height and tilt within the
autopilot's. The best is confident when nothing else credible, nor a rejected pose explaining as many
limbs, scores nearly as well (`decide`). Pure: no I/O, no clock.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.geometry import se3
from companion.vision.rack.acquire_types import AcquisitionConfig, AcquisitionPrior, RackHypothesis
from companion.vision.rack.acquire_verify import EdgeCheck

__all__ = ["close_range", "credible", "decide", "distinct", "flanked_pipes", "good_pipes", "limbs_ok",
           "num_limbs_ok", "pattern_seen"]


def decide(out: list[RackHypothesis], rivals: list[tuple[float, int, FloatArray, int]], prior: AcquisitionPrior,
            cfg: AcquisitionConfig, up_cam: FloatArray, rival_limbs: int, shown_score: float | None = None) -> str:
    """The empty string when the best of `out` (ranked, distinct) deserves confidence, else why not.
    Rejected poses (score, sign, pose, agreeing limbs) count as rivals when they agree on at least
    `rival_limbs` limbs (0 = all of them) at a height the autopilot allows (`height_gate_sigma`).
    `shown_score`: the best's score for the `min_score` floor (default its `score`)."""
    status = ""
    best = out[0].T_rack_cam
    tilt = float(np.arccos(np.clip(best[2, :3] @ up_cam, -1.0, 1.0)))
    floor_score = out[0].score if shown_score is None else max(shown_score, out[0].score)
    if floor_score < cfg.min_score:
        status = f"best score {floor_score:.2f} below {cfg.min_score:.2f}: the image is not explained"
    elif abs(best[2, 3] - prior.height_m) > cfg.confident_sigma * prior.height_std_m \
            or tilt > cfg.confident_sigma * cfg.attitude_std_rad:
        # Credible but in the tails of the autopilot's height or tilt: where the lateral / roll
        # confusion and shadows produce fits that look right. Offered, not trusted.
        status = "best pose strays from the autopilot's height or tilt"
    elif len(out) > 1 and out[1].score > cfg.ambiguity_ratio * out[0].score:
        status = f"ambiguous: {len(out)} hypotheses score alike"
    elif any(s > cfg.ambiguity_ratio * out[0].score and n_ok >= rival_limbs
             and abs(T[2, 3] - prior.height_m) <= cfg.height_gate_sigma * prior.height_std_m
             and ((sign < 0) != out[0].reversed or abs(T[0, 3] - best[0, 3]) >= cfg.distinct_m)
             for s, sign, T, n_ok in rivals):
        status = "ambiguous: a rejected pose fits about as well"
    return status


def credible(chk: EdgeCheck, cfg: AcquisitionConfig, prior: AcquisitionPrior, up_cam: FloatArray,
              n_par: int) -> bool:
    """Enough limb samples agree on enough pipes, tightly, at a height and tilt the autopilot allows."""
    if abs(chk.T_rack_cam[2, 3] - prior.height_m) > cfg.height_gate_sigma * prior.height_std_m:
        return False
    # Sliding sideways and rolling about the pipes look alike from high above: a pose that buys
    # its fit with a tilt the autopilot contradicts is that confusion, not the rack.
    tilt = float(np.arccos(np.clip(chk.T_rack_cam[2, :3] @ up_cam, -1.0, 1.0)))
    if tilt > cfg.tilt_gate_sigma * cfg.attitude_std_rad:
        return False
    # A pipe whose two limbs are in view but show (almost) no edge is not where the pose puts it.
    ls, la = chk.limb_samples, chk.limb_agree
    shown = (ls[0::2] >= 0.5 * cfg.samples_per_limb) & (ls[1::2] >= 0.5 * cfg.samples_per_limb)
    missing = shown & (la[0::2] + la[1::2] < cfg.missing_pipe_agree * (ls[0::2] + ls[1::2]))
    return chk.agree_fraction >= cfg.min_agree_fraction and chk.residual_px <= cfg.max_residual_px \
        and pattern_seen(chk, cfg, n_par) and not np.any(missing)


def close_range(chk: EdgeCheck, cfg: AcquisitionConfig, n_par: int) -> bool:
    """Fewer than `min_pipes` parallel pipes have both limbs in view at this pose (on the deck, 0.6 m
    over the pipes, one pipe fills most of the image)."""
    ls = chk.limb_samples[: 2 * n_par]
    shown = (ls[0::2] >= 0.5 * cfg.samples_per_limb) & (ls[1::2] >= 0.5 * cfg.samples_per_limb)
    return int(np.count_nonzero(shown)) < cfg.min_pipes


def num_limbs_ok(chk: EdgeCheck, cfg: AcquisitionConfig, n_par: int) -> int:
    """Limbs of the parallel pipes in view that agree (see `_limbs_ok`)."""
    return int(np.count_nonzero(limbs_ok(chk, cfg)[: 2 * n_par]))


def pattern_seen(chk: EdgeCheck, cfg: AcquisitionConfig, n_par: int) -> bool:
    """`min_pipes` pipes with both limbs agreeing; at close range, one pipe flanked by an agreeing
    limb of each neighbour (gap, width, gap: a pattern that a single pipe or a stripe has not)."""
    if good_pipes(chk, cfg).size >= cfg.min_pipes:
        return True
    return close_range(chk, cfg, n_par) and flanked_pipes(chk, cfg, n_par).size >= 1


def limbs_ok(chk: EdgeCheck, cfg: AcquisitionConfig, run_scale: float = 1.0) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Limbs in view (half a limb's samples or more) that agree (min_pipe_agree, with a run of
    consecutive agreeing samples of at least run_scale × min_limb_run of the limb)."""
    ls, la = chk.limb_samples, chk.limb_agree
    ok = (ls >= 0.5 * cfg.samples_per_limb) & (la >= cfg.min_pipe_agree * np.maximum(ls, 1.0))
    return np.asarray(ok & (chk.limb_run >= run_scale * cfg.min_limb_run * ls))


def flanked_pipes(chk: EdgeCheck, cfg: AcquisitionConfig, n_par: int) -> np.ndarray[Any, np.dtype[np.intp]]:
    """Interior parallel pipes m whose two limbs agree and so do the facing limbs of their neighbours
    m - 1 and m + 1. Limb 2m is pipe m's limb towards rack -x."""
    if n_par < 2:
        return np.zeros(0, dtype=np.intp)
    # At 0.6 m a rust spot on a limb or the image border cuts a limb into pieces: half the run asked
    # from afar, for each of the pattern's four limbs (which together are what a stripe has not).
    ok = limbs_ok(chk, cfg, 0.5)[: 2 * n_par]
    # The outermost pipes do not qualify: their outer side shows the ground, which an interior pipe of the
    # same radius shows too where its neighbour's limb is not seen (found at 0.6 m: pipe 5 taken for pipe 2).
    left = np.concatenate([[False], ok[1:-2:2]])  # limb 2m - 1 (pipe m - 1's, facing pipe m)
    right = np.concatenate([ok[2::2], [False]])  # limb 2m + 2
    return np.flatnonzero(ok[0::2] & ok[1::2] & left & right)


def good_pipes(chk: EdgeCheck, cfg: AcquisitionConfig) -> np.ndarray[Any, np.dtype[np.intp]]:
    """Pipes both of whose limbs are in view (half a limb's samples or more) and agree (min_pipe_agree,
    with a run of consecutive agreeing samples of at least min_limb_run of the limb)."""
    ok = limbs_ok(chk, cfg)
    return np.flatnonzero(ok[0::2] & ok[1::2])


def distinct(hyps: list[RackHypothesis], cfg: AcquisitionConfig) -> list[RackHypothesis]:
    """Drop hypotheses that are the same pose as a better one (same direction, close pose)."""
    out: list[RackHypothesis] = []
    for h in hyps:
        same = False
        for b in out:
            rot = float(np.linalg.norm(se3.log(se3.inverse(b.T_rack_cam) @ h.T_rack_cam)[3:]))
            d_rack = h.T_rack_cam[:3, 3] - b.T_rack_cam[:3, 3]
            if h.reversed == b.reversed and float(np.hypot(d_rack[0], d_rack[2])) < cfg.distinct_m \
                    and rot < cfg.distinct_rad:
                same = True
                break
        if not same:
            out.append(h)
    return out
