"""Rack acquisition, step 2: pair limbs into pipes and match them to the model's pipes.

Works in the cross-section plane of `acquire_lines` (angles `theta` of the limb rays, rad). With
the camera at (X, Z) in the rack's (x, z) plane, travelling along `sign` * rack +y (sign = +1:
image left to right is rack +x; sign = -1: the reverse), the axis of parallel pipe m at
(x_m, r_m) is seen at `phi` = atan2(r_m - Z, sign (x_m - X)) and its limbs at phi -/+ beta,
beta = asin(r_m / l), l the distance to the axis. A residual roll `alpha` about the pipe
direction (the autopilot's attitude error) adds to every angle.

Hypotheses come from every pair of observed limbs with opposite polarities (a pipe darker or
brighter than what lies around it) whose width, read as model pipe m, puts the camera at the
measured height: that fixes X and Z exactly for each (pair, m, sign), i.e. any subset of the
pipes in view, either direction of travel. Each hypothesis then predicts every model limb
(with occlusion and the image's field of view) and is scored by the observed limb length it
explains against what it predicts plus what it leaves unexplained; the best are refined by
Gauss-Newton on (X, Z, alpha) with the height and attitude as priors.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.vision.rack.acquire_lines import LimbClusters

IntArray = np.ndarray[Any, np.dtype[np.intp]]
BoolArray = np.ndarray[Any, np.dtype[np.bool_]]


@dataclass(frozen=True)
class SectionHypothesis:
    """A camera position in the rack cross-section explaining the observed limbs.

    `x_m`, `z_m`: camera centre (rack x, z, m); `alpha_rad`: roll about the pipe direction to add to
    the attitude; `sign`: +1 travelling along rack +y, -1 along -y; `polarity`: +1 when the pipes
    are brighter than their surroundings; `score`: explained / (predicted + unexplained) limb
    length in [0, 1]; `coverage` the fraction of the observed limb length it explains; `pipes`:
    model pipe indices (0-based) with both limbs matched, in image left-to-right order;
    `matched_limbs`: number of matched limbs.
    """

    x_m: float
    z_m: float
    alpha_rad: float
    sign: int
    polarity: int
    score: float
    coverage: float
    pipes: tuple[int, ...]
    matched_limbs: int


def predict_limb_angles(
    X: FloatArray, Z: FloatArray, alpha: FloatArray, sign: FloatArray, x_axes: FloatArray, radii: FloatArray
) -> tuple[FloatArray, BoolArray]:
    """Observed-frame angles (C, 2M) of the limbs of M pipes for C camera hypotheses and their
    visibility (C, 2M) against occlusion by nearer pipes. Columns 2m, 2m+1: left, right limb of
    pipe m (left = smaller angle)."""
    dx = sign[:, None] * (x_axes[None, :] - X[:, None])  # (C, M)
    dz = radii[None, :] - Z[:, None]
    l = np.hypot(dx, dz)
    phi = np.arctan2(dz, dx)
    beta = np.arcsin(np.minimum(radii[None, :] / np.maximum(l, 1e-9), 1.0))
    C, M = dx.shape
    th = np.empty((C, 2 * M))
    th[:, 0::2] = phi - beta + alpha[:, None]
    th[:, 1::2] = phi + beta + alpha[:, None]
    # A limb is hidden when it lies inside the angular interval of a nearer pipe.
    lo, hi = th[:, 0::2], th[:, 1::2]  # (C, M)
    l2 = np.repeat(l, 2, axis=1)
    hidden = np.zeros(th.shape, dtype=bool)
    for m in range(M):
        hidden |= (th > lo[:, m : m + 1]) & (th < hi[:, m : m + 1]) & (l2 > l[:, m : m + 1])
    visible = ~hidden & (l > radii[None, :] * 1.001).repeat(2, axis=1)
    return th, visible


def anchor_hypotheses(
    limbs: LimbClusters, x_axes: FloatArray, radii: FloatArray, height_m: float, height_tol_m: float,
    signs: tuple[int, ...],
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, IntArray]:
    """Camera (X, Z), sign and pipe polarity of every (limb pair, model pipe, sign) whose width
    matches the model pipe's radius at the measured height (|Z - height| <= height_tol).

    Returns X (C,), Z (C,), sign (C,), polarity (C,), anchor pipe (C,).
    """
    th, pol = limbs.theta, limbs.polarity
    i, j = np.triu_indices(th.size, k=1)
    ok = (pol[i] == -pol[j]) & (th[j] - th[i] > 1e-4)
    i, j = i[ok], j[ok]
    phi = 0.5 * (th[i] + th[j])
    sin_b = np.sin(0.5 * (th[j] - th[i]))
    # (pairs, M): distance to the axis and camera height for each model pipe.
    l = radii[None, :] / sin_b[:, None]
    Zc = radii[None, :] - l * np.sin(phi)[:, None]
    good = np.abs(Zc - height_m) <= height_tol_m
    pi, mi = np.nonzero(good)
    Xs, Zs, Ss, Ps, Ms = [], [], [], [], []
    for s in signs:
        Xs.append(x_axes[mi] - s * l[pi, mi] * np.cos(phi[pi]))
        Zs.append(Zc[pi, mi])
        Ss.append(np.full(pi.size, float(s)))
        Ps.append(pol[i[pi]])
        Ms.append(mi)
    return (np.concatenate(Xs), np.concatenate(Zs), np.concatenate(Ss), np.concatenate(Ps),
            np.concatenate(Ms).astype(np.intp))


def match_limbs(
    pred: FloatArray, pred_pol: FloatArray, pred_weight: FloatArray, limbs: LimbClusters, tol_rad: float
) -> tuple[IntArray, FloatArray]:
    """Nearest observed limb (same polarity, within tol) of each predicted limb, -1 if none.

    `pred` (C, L) angles, `pred_pol` (C, L) polarities, `pred_weight` (C, L) predicted visible
    length (0 = not predicted). Returns the matched cluster index (C, L) and |angle error| (C, L).
    """
    if limbs.theta.size == 0:
        return np.full(pred.shape, -1, dtype=np.intp), np.full(pred.shape, np.inf)
    err = np.abs(pred[:, :, None] - limbs.theta[None, None, :])
    err = np.where(pred_pol[:, :, None] == limbs.polarity[None, None, :], err, np.inf)
    k = np.argmin(err, axis=2)
    e = np.take_along_axis(err, k[:, :, None], axis=2)[:, :, 0]
    ok = (e <= tol_rad) & (pred_weight > 0)
    return np.where(ok, k, -1), e


def score_hypotheses(
    X: FloatArray, Z: FloatArray, alpha: FloatArray, sign: FloatArray, polarity: FloatArray,
    limbs: LimbClusters, x_axes: FloatArray, radii: FloatArray, theta_range: tuple[float, float],
    visible_length: Any, tol_rad: float, min_length_px: float,
) -> tuple[FloatArray, IntArray, FloatArray, FloatArray]:
    """Score (C,) of camera hypotheses, their limb matches (C, 2M), predicted angles (C, 2M) and
    the fraction (C,) of the observed limb length they explain; `visible_length(theta)` gives a
    limb's length in view (px). Limbs predicted shorter than `min_length_px` may explain an
    observation but are not required."""
    th, vis = predict_limb_angles(X, Z, alpha, sign, x_axes, radii)
    in_view = (th > theta_range[0]) & (th < theta_range[1])
    L_any = np.where(vis & in_view, visible_length(th.ravel()).reshape(th.shape), 0.0)
    L = np.where(L_any >= min_length_px, L_any, 0.0)
    pol = np.empty_like(th)
    pol[:, 0::2] = polarity[:, None]
    pol[:, 1::2] = -polarity[:, None]
    k, _ = match_limbs(th, pol, L_any, limbs, tol_rad)
    matched = k >= 0
    obs_len = np.where(matched, limbs.length_px[np.maximum(k, 0)], 0.0)
    explained = np.minimum(obs_len, L).sum(axis=1)
    # Observed limbs no predicted limb claims count against the hypothesis.
    claimed = np.zeros((X.size, limbs.theta.size), dtype=bool)
    rows = np.repeat(np.arange(X.size), th.shape[1])
    claimed[rows[matched.ravel()], k.ravel()[matched.ravel()]] = True
    unexplained = np.where(claimed, 0.0, limbs.length_px[None, :]).sum(axis=1)
    score = explained / np.maximum(L.sum(axis=1) + unexplained, 1e-9)
    coverage = 1.0 - unexplained / max(float(limbs.length_px.sum()), 1e-9)
    return score, k, th, coverage


def refine_section(
    X: float, Z: float, alpha: float, sign: float, matches: IntArray, limbs: LimbClusters,
    x_axes: FloatArray, radii: FloatArray, height_m: float, height_std_m: float, alpha_std_rad: float,
    angle_std_rad: float, iterations: int = 3,
) -> tuple[float, float, float]:
    """Gauss-Newton on (X, Z, alpha) over the matched limbs (`matches` (2M,), -1 = none), with the
    height and a zero roll correction as priors (`refine_sections` for one hypothesis)."""
    p = refine_sections(np.array([[X, Z, alpha]]), np.array([float(sign)]), matches[None, :], limbs.theta,
                        x_axes, radii, height_m, height_std_m, alpha_std_rad, angle_std_rad, iterations)
    return float(p[0, 0]), float(p[0, 1]), float(p[0, 2])


def refine_sections(
    P0: FloatArray, sign: FloatArray, matches: IntArray, obs_theta: FloatArray, x_axes: FloatArray,
    radii: FloatArray, height_m: float, height_std_m: float, alpha_std_rad: float, angle_std_rad: float,
    iterations: int = 3,
) -> FloatArray:
    """Gauss-Newton on (X, Z, alpha) (C, 3) of C hypotheses at once, each over its matched limbs
    (`matches` (C, 2M) indices into `obs_theta`, -1 = none), with the height and a zero roll correction
    as priors; central-difference Jacobian (3 parameters). A hypothesis stops when its step in (X, Z)
    falls below 1e-5 m; one without a matched limb is returned unchanged."""
    P = np.array(P0, dtype=np.float64, copy=True)
    sel = matches >= 0  # (C, 2M)
    obs = np.where(sel, obs_theta[np.maximum(matches, 0)] if obs_theta.size else 0.0, 0.0)
    active = np.flatnonzero(sel.any(axis=1))
    prior_w = np.array([0.0, 1.0 / height_std_m**2, 1.0 / alpha_std_rad**2])
    prior_mean = np.array([0.0, height_m, 0.0])
    h = np.array([1e-5, 1e-5, 1e-6])
    steps = np.vstack([np.zeros(3), np.diag(h), -np.diag(h)])  # (7, 3): the centre and the six +/- steps
    inv_var = 1.0 / angle_std_rad**2
    for _ in range(iterations):
        if active.size == 0:
            break
        n = active.size
        Q = (P[active, None, :] + steps[None, :, :]).reshape(-1, 3)
        th, _ = predict_limb_angles(Q[:, 0], Q[:, 1], Q[:, 2], np.repeat(sign[active], 7), x_axes, radii)
        th = th.reshape(n, 7, -1)
        m = sel[active]
        r = np.where(m, obs[active] - th[:, 0], 0.0)  # (n, 2M)
        J = np.where(m[:, :, None], ((th[:, 1:4] - th[:, 4:7]) / (2.0 * h[None, :, None])).transpose(0, 2, 1),
                     0.0)  # (n, 2M, 3)
        H = np.einsum("cki,ckj->cij", J, J) * inv_var + np.diag(prior_w) + 1e-9 * np.eye(3)
        g = np.einsum("cki,ck->ci", J, r) * inv_var + prior_w * (prior_mean - P[active])
        try:
            step = np.linalg.solve(H, g[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            step = np.zeros((n, 3))
            ok = np.ones(n, dtype=bool)
            for k in range(n):
                try:
                    step[k] = np.linalg.solve(H[k], g[k])
                except np.linalg.LinAlgError:
                    ok[k] = False
            step, active = step[ok], active[ok]
        P[active] += step
        active = active[np.abs(step[:, 0]) + np.abs(step[:, 1]) >= 1e-5]
    return P


def section_hypotheses(
    limbs: LimbClusters, x_axes: FloatArray, radii: FloatArray, height_m: float, height_std_m: float,
    signs: tuple[int, ...], theta_range: tuple[float, float], visible_length: Any, tol_rad: float,
    min_length_px: float, alpha_std_rad: float, max_hypotheses: int, merge_m: float,
) -> list[SectionHypothesis]:
    """Anchor, score, refine and de-duplicate the cross-section hypotheses (best first)."""
    tol_h = 3.0 * height_std_m + 0.05
    X, Z, S, P, _ = anchor_hypotheses(limbs, x_axes, radii, height_m, tol_h, signs)
    if X.size == 0:
        return []
    A0 = np.zeros(X.size)
    score, _, _, _ = score_hypotheses(X, Z, A0, S, P, limbs, x_axes, radii, theta_range, visible_length,
                                      tol_rad, min_length_px)
    def anchors_to_refine() -> Iterator[int]:
        """The anchors in score order, one per neighbourhood (fixed by the anchors alone)."""
        tried: list[tuple[float, float, float]] = []
        for c in np.argsort(-score):
            if score[c] <= 0.0:
                return
            if any(s == S[c] and abs(x - X[c]) < merge_m and abs(z - Z[c]) < 2 * merge_m for x, z, s in tried):
                continue
            tried.append((float(X[c]), float(Z[c]), float(S[c])))
            yield int(c)

    todo = anchors_to_refine()
    out: list[SectionHypothesis] = []
    while len(out) < max_hypotheses:
        # Refined in batches of as many as may still be kept (a refined one may merge into a kept one).
        batch = np.fromiter(itertools.islice(todo, max_hypotheses - len(out)), dtype=np.intp)
        if batch.size == 0:
            break
        Sb, Pb = S[batch], P[batch]
        Q = np.column_stack([X[batch], Z[batch], np.zeros(batch.size)])
        for _ in range(2):  # match, refine, re-match
            _, k, _, _ = score_hypotheses(Q[:, 0], Q[:, 1], Q[:, 2], Sb, Pb, limbs, x_axes, radii, theta_range,
                                          visible_length, tol_rad, min_length_px)
            Q = refine_sections(Q, Sb, k, limbs.theta, x_axes, radii, height_m, height_std_m, alpha_std_rad,
                                2.5 * tol_rad / 6.0)
        sc, k, th, cov = score_hypotheses(Q[:, 0], Q[:, 1], Q[:, 2], Sb, Pb, limbs, x_axes, radii, theta_range,
                                          visible_length, tol_rad, min_length_px)
        for b in range(batch.size):
            if len(out) >= max_hypotheses:
                break
            x, z, a = (float(v) for v in Q[b])
            both = (k[b, 0::2] >= 0) & (k[b, 1::2] >= 0)
            pipes = np.flatnonzero(both)
            pipes = pipes[np.argsort(th[b, 2 * pipes])]
            hyp = SectionHypothesis(x_m=x, z_m=z, alpha_rad=a, sign=int(Sb[b]), polarity=int(Pb[b]),
                                    score=float(sc[b]), coverage=float(cov[b]), pipes=tuple(int(m) for m in pipes),
                                    matched_limbs=int(np.count_nonzero(k[b] >= 0)))
            if any(h.sign == hyp.sign and abs(h.x_m - x) < merge_m and abs(h.z_m - z) < 2 * merge_m for h in out):
                continue
            out.append(hyp)
    out.sort(key=lambda h: -h.score)
    return out
