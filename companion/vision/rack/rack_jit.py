"""Compiled inner loops of the rack tracker (numba), with the numpy code as fallback: the edge search and the
silhouette fit (`edges.py`), the pose Jacobian and the median (`motion.py`), the ground points (`ground.py`).

`edges.search_edges` and `edges.refine_silhouette` spend most of their time not in arithmetic but in
numpy's per-call overhead: each frame makes some two hundred calls on (N, 2R+1) or (N, 2R+1, M) arrays of a
few thousand elements, many of them reductions over a short axis. The loops below do the same arithmetic per
sample in one compiled call, in the same floating-point types and the same order of operations as the numpy
code (numpy's pairwise summation, `einsum`'s four-lane order for the eight-sample inner profile), so that
both give the same bits on x86-64 (`tests/rack/test_rack_jit.py`; `bench/rack_stress.py --throughput` for
the speed). einsum's lane order is that of numpy's SIMD width: on another CPU the correlations may differ
in their last bit.

Optional (`companion/jit.py`): without numba, or with `COMPANION_JIT=0`, `kernels()` is None and the
callers run their numpy code.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.jit import compile_kernels, register

# The inner-profile length whose correlation order is `np.einsum`'s (four lanes, then pairs); other lengths
# keep the numpy code.
EINSUM_LANES_M = 8


def _pairwise_py(x: Any, n: int) -> Any:
    """Sum of x[0..n-1] (float32 or float64, in that type) in numpy's pairwise order (`edges._pairwise_sum`):
    n < 8 left to right; otherwise eight running sums over blocks of eight, combined in pairs, then the rest."""
    if n < 8:
        acc = x[0]
        for i in range(1, n):
            acc = acc + x[i]
        return acc
    r0, r1, r2, r3, r4, r5, r6, r7 = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]
    i = 8
    while i < n - n % 8:
        r0 += x[i]
        r1 += x[i + 1]
        r2 += x[i + 2]
        r3 += x[i + 3]
        r4 += x[i + 4]
        r5 += x[i + 5]
        r6 += x[i + 6]
        r7 += x[i + 7]
        i += 8
    acc = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        acc = acc + x[i]
        i += 1
    return acc


def _window_py(p: Any, c: int, M: int, win: Any, tmp: Any) -> None:
    """Candidate c's zero-mean, unit-norm inner window p[1 + c .. c + M] (float32) into win[c]
    (`edges._inner_windows`, the same operations); `tmp` (M,) is scratch."""
    for m in range(M):
        tmp[m] = p[1 + c + m]
    mean = _pairwise(tmp, M) / np.float32(M)
    for m in range(M):
        d = p[1 + c + m] - mean
        win[c, m] = d
        tmp[m] = d * d
    nrm = max(np.sqrt(_pairwise(tmp, M)), np.float32(1e-3))
    for m in range(M):
        win[c, m] = win[c, m] / nrm


# The helpers as the kernels call them: the Python functions, replaced by their compiled versions in `kernels()`
# before the kernels are compiled (numba resolves a global function when it compiles its caller).
_pairwise: Any = _pairwise_py
_window: Any = _window_py


def _profile_maps(uv: Any, normal: Any, k: Any) -> Any:
    """`cv2.remap` maps (mx, my) (N, L) float32 of the points uv + k_j normal (one line per sample), in
    float32 as `edges.search_edges` forms them (uv, normal (N, 2) float64; k (L,) float32)."""
    n = uv.shape[0]
    L = k.shape[0]
    mx = np.empty((n, L), dtype=np.float32)
    my = np.empty((n, L), dtype=np.float32)
    for i in range(n):
        bx = np.float32(uv[i, 0])
        by = np.float32(uv[i, 1])
        nx = np.float32(normal[i, 0])
        ny = np.float32(normal[i, 1])
        for j in range(L):
            mx[i, j] = bx + k[j] * nx
            my[i, j] = by + k[j] * ny
    return mx, my


def _pick_edges(prof: Any, M: int, R: int, pol: Any, prior: Any, thr: Any, ref: Any, use_ref: bool,
                innermost: Any) -> Any:
    """`edges.search_edges` after its `cv2.remap`, one line per sample, for M = 0 or `EINSUM_LANES_M`.

    `prof` (N, 2R+3+M) float32 profiles (offsets -R-1-M..R+1), `pol` (N,) float32 polarity, `prior`
    (2R+1,) float32 distance prior, `thr` float32 threshold, `ref` (N, M) float32 inner references (used
    when `use_ref`), `innermost` (N,) float32 innermost ratios (0 = best candidate). Returns (offset (N,)
    float64 px, found (N,) bool, chosen index b (N,), gradient there (N,) float32, inner (N, M) float64).
    """
    n = prof.shape[0]
    W = 2 * R + 1
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    half = np.float32(0.5)
    offset = np.empty(n)
    found = np.zeros(n, dtype=np.bool_)
    b_out = np.empty(n, dtype=np.intp)
    g_out = np.empty(n, dtype=np.float32)
    inner = np.zeros((n, M))
    g = np.empty(W, dtype=np.float32)
    signed = np.empty(W, dtype=np.float32)
    score = np.empty(W, dtype=np.float32)
    win = np.empty((W, M), dtype=np.float32)
    tmp = np.empty(max(M, 1), dtype=np.float32)
    for i in range(n):
        p = prof[i]
        s = pol[i]
        for c in range(W):
            gc = p[M + c + 2] - p[M + c]
            g[c] = gc
            sg = gc * s if s != f0 else abs(gc)
            signed[c] = sg
            score[c] = (sg if sg >= thr else f0) * prior[c]
        has_ref = False
        if use_ref:
            for m in range(M):
                tmp[m] = ref[i, m] * ref[i, m]
            has_ref = _pairwise(tmp, M) > np.float32(0.25)
            if has_ref:
                for c in range(W):
                    if score[c] == f0:
                        continue  # a zero score stays zero whatever its window's correlation
                    _window(p, c, M, win, tmp)
                    # np.einsum's order over the eight: four lanes j + (j + 4), then pairs
                    q0 = win[c, 0] * ref[i, 0] + win[c, 4] * ref[i, 4]
                    q1 = win[c, 1] * ref[i, 1] + win[c, 5] * ref[i, 5]
                    q2 = win[c, 2] * ref[i, 2] + win[c, 6] * ref[i, 6]
                    q3 = win[c, 3] * ref[i, 3] + win[c, 7] * ref[i, 7]
                    fit = ((q0 + q1) + (q2 + q3)) * half + half
                    fit = min(max(fit, f0), f1)
                    score[c] = score[c] * (fit * fit)
        best = 0
        for c in range(1, W):
            if score[c] > score[best]:
                best = c
        ratio = f0 if has_ref else innermost[i]
        if ratio > f0:
            bar = ratio * score[best]
            for c in range(1, W - 1):
                sc = score[c]
                if sc >= score[c - 1] and sc >= score[c + 1] and sc > f0 and sc >= bar:
                    best = c
                    break
        found[i] = score[best] > f0 and best > 0 and best < 2 * R
        b = min(max(best, 1), 2 * R - 1)
        s_m = signed[b - 1]
        s_0 = signed[b]
        s_p = signed[b + 1]
        den = (s_m - np.float32(2.0) * s_0) + s_p
        frac = half * (s_m - s_p) / den if den < np.float32(-1e-6) else f0
        frac = min(max(frac, -half), half)
        offset[i] = float(b - R) + float(frac)
        b_out[i] = b
        g_out[i] = g[b]
        if use_ref:
            _window(p, b, M, win, tmp)
            for m in range(M):
                inner[i, m] = win[b, m]
    return offset, found, b_out, g_out, inner


def _silhouette_maps(uv: Any, normal: Any, p: Any, j: Any) -> Any:
    """`cv2.remap` maps (mx, my) (N, K) float32 of the points uv + (p + j_k) normal, formed in float64 and
    rounded as `edges.refine_silhouette` forms them (uv, normal (N, 2); p (N,) the rounded peaks; j (K,))."""
    n = uv.shape[0]
    K = j.shape[0]
    mx = np.empty((n, K), dtype=np.float32)
    my = np.empty((n, K), dtype=np.float32)
    for i in range(n):
        for k in range(K):
            step = p[i] + j[k]
            mx[i, k] = np.float32(uv[i, 0] + step * normal[i, 0])
            my[i, k] = np.float32(uv[i, 1] + step * normal[i, 1])
    return mx, my


def _fit_silhouettes(prof: Any, proj: Any, p: Any, deltas: Any, step: float, offset_px: Any,
                     max_rel_rms: float, n_dof: float) -> Any:
    """`edges.refine_silhouette` after its remap and its product `proj = prof @ Q`: the best silhouette
    offset (N,) float64 px per sample (`p` the rounded peaks, `deltas` the candidate positions)."""
    n, K = prof.shape
    D = proj.shape[1] // 4
    out = np.empty(n)
    sse = np.empty(D)
    sq = np.empty(K)
    for i in range(n):
        for k in range(K):
            sq[k] = prof[i, k] * prof[i, k]
        tot = _pairwise(sq, K)  # np.sum(prof * prof, axis=1), bit for bit
        for d in range(D):
            a0 = proj[i, 4 * d]
            a1 = proj[i, 4 * d + 1]
            a2 = proj[i, 4 * d + 2]
            a3 = proj[i, 4 * d + 3]
            sse[d] = tot - (((a0 * a0 + a1 * a1) + a2 * a2) + a3 * a3)
        best = 0
        for d in range(1, D):
            if sse[d] < sse[best]:
                best = d
        b = min(max(best, 1), D - 2)
        s_m = sse[b - 1]
        s_0 = sse[b]
        s_p = sse[b + 1]
        den = s_m - 2.0 * s_0 + s_p
        frac = 0.5 * (s_m - s_p) / den if den > 1e-9 else 0.0
        frac = min(max(frac, -0.5), 0.5)
        o = p[i] + deltas[b] + frac * step
        if max_rel_rms > 0.0:
            rms = np.sqrt(max(s_0, 0.0) / n_dof)
            hi = prof[i, 0]
            lo = prof[i, 0]
            for k in range(1, K):
                hi = max(hi, prof[i, k])
                lo = min(lo, prof[i, k])
            if not rms <= max_rel_rms * max(hi - lo, 1e-6):
                o = offset_px[i]
        out[i] = o
    return out


def _pose_jacobian(J: Any, p: Any) -> Any:
    """`motion.pose_jacobian`: image motion fields (N, 2, 6) of the six generators from d(u, v)/dp (N, 2, 3) and
    the points p (N, 3) (camera frame), element by element as the numpy code."""
    n = p.shape[0]
    out = np.empty((n, 2, 6))
    for i in range(n):
        x = p[i, 0]
        y = p[i, 1]
        z = p[i, 2]
        for r in range(2):
            j0 = J[i, r, 0]
            j1 = J[i, r, 1]
            j2 = J[i, r, 2]
            out[i, r, 0] = -j0
            out[i, r, 1] = -j1
            out[i, r, 2] = -j2
            out[i, r, 3] = j1 * z - j2 * y
            out[i, r, 4] = j2 * x - j0 * z
            out[i, r, 5] = j0 * y - j1 * x
    return out


def _median(a: Any) -> float:
    """`motion.median_1d` of a non-empty float64 array: the same value (NaN if any)."""
    n = a.size
    for i in range(n):
        if np.isnan(a[i]):
            return np.nan
    h = n // 2
    p = np.partition(a.copy(), h)
    if n % 2:
        return float(p[h])
    lo = p[0]
    for i in range(1, h):
        lo = max(lo, p[i])
    return float((lo + p[h]) / 2.0)


def _plane_points(o: Any, d: Any, z_g: float) -> Any:
    """`ground.plane_points`: where rays o + t d (rack frame; o (1, 3) for all or (K, 3), d (K, 3)) meet
    {z = z_g}, (K, 3), and dX/dz_g (K, 3); NaN rows for rays that do not point down to the plane."""
    k = d.shape[0]
    X = np.empty((k, 3))
    dX = np.empty((k, 3))
    for i in range(k):
        oi = i if o.shape[0] > 1 else 0
        dz = d[i, 2]
        dz_s = dz if dz < -1e-6 else np.nan
        t = (z_g - o[oi, 2]) / dz_s
        for c in range(3):
            X[i, c] = o[oi, c] + t * d[i, c] if t > 0.0 else np.nan
            dX[i, c] = d[i, c] / dz_s
    return X, dX


@dataclass(frozen=True)
class Kernels:
    """The compiled kernels (numba dispatchers with the signatures of the functions of the same names)."""

    profile_maps: Any
    pick_edges: Any
    silhouette_maps: Any
    fit_silhouettes: Any
    pose_jacobian: Any
    median: Any
    plane_points: Any


def _build(njit: Any) -> Kernels:
    global _pairwise, _window
    _pairwise = njit(_pairwise_py)  # before their callers compile (they bind them then)
    _window = njit(_window_py)
    return Kernels(profile_maps=njit(_profile_maps), pick_edges=njit(_pick_edges),
                   silhouette_maps=njit(_silhouette_maps), fit_silhouettes=njit(_fit_silhouettes),
                   pose_jacobian=njit(_pose_jacobian), median=njit(_median), plane_points=njit(_plane_points))


def _warm_up(ks: Kernels) -> None:
    """Compile (or load) both kernels for the argument types the callers pass (read-only prior included)."""
    R, M = 2, EINSUM_LANES_M
    prof = np.zeros((1, 2 * R + 3 + M), dtype=np.float32)
    one32 = np.ones(1, dtype=np.float32)
    prior = np.ones(2 * R + 1, dtype=np.float32)
    prior.flags.writeable = False  # as `edges._search_constants` returns it
    k = np.arange(-3.0, 4.0, dtype=np.float32)
    k.flags.writeable = False  # as `edges._search_constants` returns it
    ks.profile_maps(np.zeros((1, 2)), np.ones((1, 2)), k)
    ks.pick_edges(prof, M, R, one32, prior, np.float32(1.0), np.zeros((1, M), dtype=np.float32), True, one32)
    j = np.arange(-2.0, 3.0)
    j.flags.writeable = False  # as `edges._silhouette_bases` returns it
    ks.silhouette_maps(np.zeros((1, 2)), np.ones((1, 2)), np.zeros(1), j)
    ks.fit_silhouettes(np.zeros((1, 6)), np.zeros((1, 12)), np.zeros(1), np.zeros(3), 0.25, np.zeros(1), 0.1, 2.0)
    ks.pose_jacobian(np.zeros((1, 2, 3)), np.ones((1, 3)))
    ks.median(np.ones(2))
    ks.plane_points(np.zeros((1, 3)), -np.ones((1, 3)), -1.0)


def kernels() -> Kernels | None:
    """The compiled kernels, or None (numba unavailable or `COMPANION_JIT=0`: the callers run numpy)."""
    return compile_kernels("rack", _build, _warm_up)


register(kernels)
