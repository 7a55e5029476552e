"""Compiled limb geometry (numba, optional: `companion/jit.py`): the view clipping and the occlusion test of
`limbs.py`, per line and per sample instead of numpy's (N, M) arrays.

`clip_lines` is `limbs.clip_lines_to_view` element by element (the same bits). `occluded` is
`limbs.occluded` with its dot products summed left to right where numpy's matrix product may use fused
multiply-adds: distances can differ in the last bit, and the answer only where a sample lies within that of
another pipe's silhouette (`tests/rack/test_rack_jit.py` compares both).
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


# The helpers as the kernels call them: the Python functions, replaced by compiled ones in `_build`.
_max: Any = _nan_max
_min: Any = _nan_min


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


@dataclass(frozen=True)
class Kernels:
    """The compiled kernels (numba dispatchers with the signatures of `_clip_lines` and `_occluded`)."""

    clip_lines: Any
    occluded: Any


def _build(njit: Any) -> Kernels:
    global _max, _min
    _max, _min = njit(_nan_max), njit(_nan_min)  # before the kernels compile (they bind them then)
    return Kernels(clip_lines=njit(_clip_lines), occluded=njit(_occluded))


def _warm_up(ks: Kernels) -> None:
    one = np.ones((1, 3))
    ks.clip_lines(one, one, np.zeros(1), np.ones(1), 1.0, 1.0, 0.0, 0.0, 0.0, 9.0, 9.0, 1.0, 0.1)
    ro = np.ones((1, 3))
    ro1 = np.ones(1)
    ro.flags.writeable = False  # the model's pipe arrays are read-only (`TrackerState._pipe_arrays`)
    ro1.flags.writeable = False
    ks.occluded(np.zeros(3), one, np.zeros(1, dtype=np.intp), ro, ro, ro1, ro1, np.zeros(1))


def kernels() -> Kernels | None:
    """The compiled kernels, or None (numba unavailable or `COMPANION_JIT=0`: `limbs.py` runs numpy)."""
    return compile_kernels("rack.limbs", _build, _warm_up)


register(kernels)
