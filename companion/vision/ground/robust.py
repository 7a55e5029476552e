"""Outlier rejection on ground-plane residuals (beyond the paper: real floors repeat patterns).

RANSAC draws 2-point rigid-motion hypotheses (vectorized over hypotheses and points) for
a_i = d + R(dyaw) b_i and keeps the largest consensus; MAD trims residuals iteratively around
least-squares fits. Both return a boolean inlier mask over the matches.
"""

from __future__ import annotations

import numpy as np

from companion.checks import FloatArray
from companion.vision.ground.closed_form import gen_to_increment, solve_gen
from companion.vision.ground.matching import BoolArray

# 1.4826 * MAD estimates the standard deviation of Gaussian residuals.
_MAD_TO_SIGMA = 1.4826


def residual_norms(a_m: FloatArray, b_m: FloatArray, increment: FloatArray) -> FloatArray:
    """|d + R(dyaw) b_i - a_i| (N,), metres."""
    # The residuals of `residuals_and_jacobian`, without building the Jacobian.
    c, s = np.cos(increment[2]), np.sin(increment[2])
    bx, by = b_m[:, 0], b_m[:, 1]
    r = np.stack([increment[0] + (c * bx - s * by) - a_m[:, 0], increment[1] + (s * bx + c * by) - a_m[:, 1]], axis=-1)
    out: FloatArray = np.sqrt(np.einsum("ij,ij->i", r, r))
    return out


def ransac_rigid(
    a_m: FloatArray,
    b_m: FloatArray,
    threshold_m: float,
    hypotheses: int,
    rng: np.random.Generator,
    min_pair_distance_m: float = 1e-3,
) -> BoolArray:
    """Inliers of the best 2-point rigid hypothesis (largest count, then smallest residual sum)."""
    n = a_m.shape[0]
    if n < 2:
        return np.zeros(n, dtype=bool)
    i = rng.integers(0, n, size=hypotheses)
    j = (i + rng.integers(1, n, size=hypotheses)) % n
    va = a_m[j] - a_m[i]
    vb = b_m[j] - b_m[i]
    theta = np.arctan2(vb[:, 0] * va[:, 1] - vb[:, 1] * va[:, 0], vb[:, 0] * va[:, 0] + vb[:, 1] * va[:, 1])
    c, s = np.cos(theta), np.sin(theta)
    # Translation that maps the pair's midpoint exactly.
    mb = 0.5 * (b_m[i] + b_m[j])
    ma = 0.5 * (a_m[i] + a_m[j])
    dx = ma[:, 0] - (c * mb[:, 0] - s * mb[:, 1])
    dy = ma[:, 1] - (s * mb[:, 0] + c * mb[:, 1])
    # Residuals of every point under every hypothesis: (H, N), evaluated in place (two (H, N)
    # buffers) with the same operations and order as dx + c bx - s by - ax, dy + s bx + c by - ay.
    bx, by = b_m[:, 0][None, :], b_m[:, 1][None, :]
    c_, s_ = c[:, None], s[:, None]
    rx = np.multiply(c_, bx)
    rx += dx[:, None]
    tmp = np.multiply(s_, by)
    rx -= tmp
    rx -= a_m[:, 0][None, :]
    ry = np.multiply(s_, bx)
    ry += dy[:, None]
    np.multiply(c_, by, out=tmp)
    ry += tmp
    ry -= a_m[:, 1][None, :]
    rx *= rx
    ry *= ry
    r2 = rx
    r2 += ry
    t2 = threshold_m * threshold_m
    inl = r2 <= t2
    counts = np.count_nonzero(inl, axis=1).astype(np.float64)
    degenerate = np.hypot(vb[:, 0], vb[:, 1]) < min_pair_distance_m
    # Ties broken by the truncated residual sum (MSAC-like).
    score = counts - np.minimum(r2, t2, out=tmp).sum(axis=1) / (t2 * (n + 1))
    score[degenerate] = -np.inf
    best = int(np.argmax(score))
    mask: BoolArray = inl[best]
    return mask


def mad_trim(a_m: FloatArray, b_m: FloatArray, threshold_m: float, rounds: int = 3) -> BoolArray:
    """Iteratively refit (GEN) and drop residuals above max(3 * 1.4826 * MAD, threshold)."""
    n = a_m.shape[0]
    mask: BoolArray = np.ones(n, dtype=bool)
    for _ in range(rounds):
        if mask.sum() < 3:
            break
        inc = gen_to_increment(solve_gen(a_m[mask], b_m[mask]))
        r = residual_norms(a_m, b_m, inc)
        med = float(np.median(r[mask]))
        mad = float(np.median(np.abs(r[mask] - med)))
        limit = max(med + 3.0 * _MAD_TO_SIGMA * mad, threshold_m)
        new_mask: BoolArray = r <= limit
        if np.array_equal(new_mask, mask):
            break
        mask = new_mask
    return mask
