"""Compiled limb geometry (numba, optional: `companion/jit.py`): the view clipping, the occlusion test and the
sampling of `limbs.py`, per line and per sample instead of numpy's (N, M) arrays.

`clip_lines` is `limbs.clip_lines_to_view` element by element (the same bits). `limb_points` and
`limb_normals` are `limbs.sample_limbs`' steps from the clipped lines to the samples and from the projection
Jacobians to the normals: the same bits, with numpy's matrix product (N, 3) x (3, 3) written as the fused
multiply-adds it is on x86-64 (OpenBLAS: fma(a2, b2, fma(a1, b1, a0 b0)), checked against exact rational
arithmetic) and `np.einsum`'s order for three terms ((0 + 2) + 1). `occluded` is `limbs.occluded` with its dot
products summed left to right: distances can differ in the last bit, and the answer only where a sample lies
within that of another pipe's silhouette (`tests/rack/test_rack_jit.py` compares them all).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.jit import compile_kernels, register


def _nan_max(x: float, y: float) -> float:
    """max(x, y), NaN if either is NaN (as `np.maximum`)."""
    return x if (x >= y or x != x) else y


def _nan_min(x: float, y: float) -> float:
    """min(x, y), NaN if either is NaN (as `np.minimum`)."""
    return x if (x <= y or x != x) else y


def _fma_py(a: float, b: float, c: float) -> float:
    """a * b + c with one rounding, as numpy's matrix product computes (the Python fallback rounds twice)."""
    return a * b + c


# The helpers as the kernels call them: the Python functions, replaced by compiled ones in `_build`.
_max: Any = _nan_max
_min: Any = _nan_min
_fma: Any = _fma_py


def _clip_lines(A: Any, D: Any, s_min: Any, s_max: Any, fx: float, fy: float, sk: float, cx: float, cy: float,
                umax: float, vmax: float, m: float, z_near_m: float) -> Any:
    """(s0, s1) (L,) of lines A + s D (L, 3) (camera frame) clipped to z >= z_near_m and the image rectangle
    [m, umax] x [m, vmax] (pinhole part), from [s_min, s_max]; s1 = s0 - 1 where a constraint fails for every s."""
    n = A.shape[0]
    s0 = np.empty(n)
    s1 = np.empty(n)
    a = np.empty(5)
    b = np.empty(5)
    for i in range(n):
        for row in range(2):
            P = A if row == 0 else D
            X = P[i, 0]
            Y = P[i, 1]
            Z = P[i, 2]
            u_lin = fx * X + sk * Y
            v_lin = fy * Y
            q = a if row == 0 else b
            q[0] = Z - z_near_m if row == 0 else Z
            q[1] = u_lin + (cx - m) * Z
            q[2] = -(u_lin + (cx - umax) * Z)
            q[3] = v_lin + (cy - m) * Z
            q[4] = -(v_lin + (cy - vmax) * Z)
        lo = -np.inf
        hi = np.inf
        bad = False
        for c in range(5):
            if b[c] > 1e-12:
                lo = _max(lo, -a[c] / b[c])
            elif b[c] < -1e-12:
                hi = _min(hi, -a[c] / b[c])
            elif a[c] < 0.0:
                bad = True
        s0[i] = _max(s_min[i], lo)
        s1[i] = s0[i] - 1.0 if bad else _min(s_max[i], hi)
    return s0, s1


def _occluded(o: Any, p: Any, own: Any, starts: Any, dirs: Any, radii: Any, lengths: Any, margin: Any) -> Any:
    """(N,) True where point p[i] (rack frame) on pipe own[i] is hidden from o by another pipe (each radius
    inflated by margin[i] m), as `limbs.occluded`."""
    n = p.shape[0]
    n_pipes = starts.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        d0 = p[i, 0] - o[0]
        d1 = p[i, 1] - o[1]
        d2 = p[i, 2] - o[2]
        dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        s = max(dist, 1e-12)
        d0 /= s
        d1 /= s
        d2 /= s
        for k in range(n_pipes):
            if k == own[i]:
                continue
            w0 = o[0] - starts[k, 0]
            w1 = o[1] - starts[k, 1]
            w2 = o[2] - starts[k, 2]
            v0 = dirs[k, 0]
            v1 = dirs[k, 1]
            v2 = dirs[k, 2]
            wv = w0 * v0 + w1 * v1 + w2 * v2
            dv = d0 * v0 + d1 * v1 + d2 * v2
            dw = d0 * w0 + d1 * w1 + d2 * w2
            A = 1.0 - dv * dv
            B = dw - dv * wv
            rr = radii[k] + margin[i]
            C = (w0 * w0 + w1 * w1 + w2 * w2 - wv * wv) - rr * rr
            disc = B * B - A * C
            if not (disc > 0.0 and A > 1e-12):
                continue
            sq = math.sqrt(disc)
            t_out = np.inf
            for sign in (-1.0, 1.0):
                t = (-B + sign * sq) / A
                s_ax = wv + t * dv
                if t > 0.0 and s_ax >= 0.0 and s_ax <= lengths[k] and t < t_out:
                    t_out = t
            if t_out < dist * (1.0 - 1e-6):
                out[i] = True
                break
    return out


def _limb_points(A: Any, D: Any, s0: Any, s1: Any, valid: Any, t: Any, omt: Any, fx: float, fy: float, sk: float,
                 cx: float, cy: float, min_length_px: float, R_cr: Any, o: Any, occlusion_margin_px: float) -> Any:
    """`limbs.sample_limbs` from the clipped lines to the samples, before their occlusion and projection.

    Lines A + s D (L, 3) (camera frame) kept where `valid` and s1 > s0 and at least `min_length_px` long in the
    image; each sampled at the K image-uniform fractions t (omt = 1 - t). Returns (kept line indices (L',),
    their end pixels (L', 2, 2), p_cam (L' K, 3), p_rack (L' K, 3) = p_cam R_cr + o with numpy's fused
    multiply-adds, the samples' limb (L' K,), their occlusion margins (L' K,) m)."""
    L = A.shape[0]
    K = t.shape[0]
    sel = np.empty(L, dtype=np.intp)
    P = np.empty((L, 2, 3))
    U = np.empty((L, 2, 2))
    n = 0
    for l in range(L):
        if not (valid[l] and s1[l] > s0[l]):
            continue
        for e in range(2):
            s = s0[l] if e == 0 else s1[l]
            for c in range(3):
                P[n, e, c] = A[l, c] + s * D[l, c]
            U[n, e, 0] = P[n, e, 0] / P[n, e, 2]
            U[n, e, 1] = P[n, e, 1] / P[n, e, 2]
        if math.hypot((U[n, 1, 0] - U[n, 0, 0]) * fx, (U[n, 1, 1] - U[n, 0, 1]) * fy) >= min_length_px:
            sel[n] = l
            n += 1
    seg = np.empty((n, 2, 2))
    p_cam = np.empty((n * K, 3))
    p_rack = np.empty((n * K, 3))
    limb = np.empty(n * K, dtype=np.intp)
    margin = np.empty(n * K)
    for l in range(n):
        for e in range(2):
            seg[l, e, 0] = U[l, e, 0] * fx + U[l, e, 1] * sk + cx
            seg[l, e, 1] = U[l, e, 1] * fy + cy
        Za = P[l, 0, 2]
        Zb = P[l, 1, 2]
        for k in range(K):
            i = l * K + k
            tZa = t[k] * Za
            lam = tZa / (tZa + omt[k] * Zb)
            for c in range(3):
                p_cam[i, c] = (1.0 - lam) * P[l, 0, c] + lam * P[l, 1, c]
            for c in range(3):
                p_rack[i, c] = _fma(p_cam[i, 2], R_cr[2, c], _fma(p_cam[i, 1], R_cr[1, c],
                                                                  p_cam[i, 0] * R_cr[0, c])) + o[c]
            limb[i] = sel[l]
            margin[i] = occlusion_margin_px * p_cam[i, 2] / fx
    return sel[:n].copy(), seg, p_cam, p_rack, limb, margin


def _limb_normals(J: Any, D: Any, out_dir: Any, limb: Any) -> Any:
    """Unit image normals (N, 2) pointing out of the pipe: the image of the axis direction D[limb] (L, 3) through
    the projection Jacobians J (N, 2, 3), turned a quarter and signed by the image of the outward direction
    out_dir[limb] (L, 3) (as `sample_limbs`: `np.einsum`'s order for the three terms, 0 + 2 then 1)."""
    n = J.shape[0]
    nrm = np.empty((n, 2))
    for i in range(n):
        l = limb[i]
        t0 = (J[i, 0, 0] * D[l, 0] + J[i, 0, 2] * D[l, 2]) + J[i, 0, 1] * D[l, 1]
        t1 = (J[i, 1, 0] * D[l, 0] + J[i, 1, 2] * D[l, 2]) + J[i, 1, 1] * D[l, 1]
        m0 = (J[i, 0, 0] * out_dir[l, 0] + J[i, 0, 2] * out_dir[l, 2]) + J[i, 0, 1] * out_dir[l, 1]
        m1 = (J[i, 1, 0] * out_dir[l, 0] + J[i, 1, 2] * out_dir[l, 2]) + J[i, 1, 1] * out_dir[l, 1]
        s = max(math.sqrt(t0 * t0 + t1 * t1), 1e-12)
        t0 /= s
        t1 /= s
        n0 = -t1
        n1 = t0
        if n0 * m0 + n1 * m1 < 0.0:
            n0 = -n0
            n1 = -n1
        nrm[i, 0] = n0
        nrm[i, 1] = n1
    return nrm


@dataclass(frozen=True)
class Kernels:
    """The compiled kernels (numba dispatchers with the signatures of `_clip_lines` and `_occluded`)."""

    clip_lines: Any
    occluded: Any
    limb_points: Any
    limb_normals: Any


def _build(njit: Any) -> Kernels:
    global _max, _min, _fma
    _max, _min = njit(_nan_max), njit(_nan_min)  # before the kernels compile (they bind them then)
    _fma = _fused_multiply_add()
    return Kernels(clip_lines=njit(_clip_lines), occluded=njit(_occluded), limb_points=njit(_limb_points),
                   limb_normals=njit(_limb_normals))


def _fused_multiply_add() -> Any:
    """a * b + c rounded once (LLVM's fma), for compiled callers."""
    from numba.core import types
    from numba.extending import intrinsic

    @intrinsic  # type: ignore[misc]
    def fma(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
        sig = types.float64(types.float64, types.float64, types.float64)

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            return builder.fma(*args)

        return sig, codegen

    return fma


def _warm_up(ks: Kernels) -> None:
    one = np.ones((1, 3))
    ks.clip_lines(one, one, np.zeros(1), np.ones(1), 1.0, 1.0, 0.0, 0.0, 0.0, 9.0, 9.0, 1.0, 0.1)
    ro = np.ones((1, 3))
    ro1 = np.ones(1)
    ro.flags.writeable = False  # the model's pipe arrays are read-only (`TrackerState._pipe_arrays`)
    ro1.flags.writeable = False
    ks.occluded(np.zeros(3), one, np.zeros(1, dtype=np.intp), ro, ro, ro1, ro1, np.zeros(1))
    t = np.linspace(0.1, 0.9, 3)
    t.flags.writeable = False  # as `limbs._image_uniform` returns them
    R = np.eye(3)
    lines = ks.limb_points(one, one, np.zeros(1), np.ones(1), np.ones(1, dtype=np.bool_), t, t, 1.0, 1.0, 0.0, 0.0,
                           0.0, 0.0, R.T, np.zeros(3), 3.0)
    ks.limb_normals(np.ones((2, 2, 3)), one, one, np.zeros(2, dtype=np.intp))
    del lines


def kernels() -> Kernels | None:
    """The compiled kernels, or None (numba unavailable or `COMPANION_JIT=0`: `limbs.py` runs numpy)."""
    return compile_kernels("rack.limbs", _build, _warm_up)


register(kernels)
