"""The ground-height fit's iterations compiled (numba, optional: `companion/jit.py`), and the scalar steps both
its numpy code and the kernel share.

`ground_height.fit_ground_height` runs four Gauss-Newton iterations over some fifty ground points on two frames
in three; each iteration is some forty numpy calls on arrays of that size, so its time was numpy's per-call
overhead (8 % of a tracked frame on the throughput scene, `bench/rack_stress.py --throughput`). `_fit` is the
whole loop for a camera without distortion, per point and in the order of the numpy code in `ground_height.py`
(element-wise products, numpy's pairwise sums, `_solve4` and `_turn` below), so that both give the same bits
(`tests/rack/test_ground_height.py`). The sums follow numpy's pairwise summation up to `MAX_POINTS` values (one
block of eight running sums); more points than that run the numpy code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.jit import compile_kernels, register
from companion.vision.rack.rack_jit import _pairwise_py  # numpy's pairwise summation order, up to 128 values

ITERATIONS = 4
MAX_POINTS = 128  # numpy's pairwise summation block: up to this many values it is one block of eight sums
# (`rack_jit._pairwise_py`, which starts a short sum from its first value where numpy adds it to 0.0: the same
# value, but for the sign of a zero)
TUKEY_C = 4.685
MIN_SCALE_PX = 0.3  # residual scale floor: LK's own error on a good corner
MIN_POINTS = 8
# The fit's rotation (rad) is the two poses' relative attitude error, a fraction of a degree: the ridge (px² per
# rad², tiny beside a point's ~600² px² per rad²) only keeps H invertible with few points, the step bound keeps
# one bad iteration from turning the camera.
ROTATION_RIDGE = 1.0
MAX_ROTATION_STEP_RAD = 0.02
_SMALL_RAD = 1e-3  # `so3._coefficients`' series below this angle


def solve4(H: Any, b: Any, step: Any) -> float:
    """Gauss-Newton step of the (4, 4) normal equations H (symmetric, positive definite once the rotation's ridge
    is added): step (4,) = -H⁻¹ b (written in place), returning (H⁻¹)₀₀ (the height's variance per px²); NaN
    when H is singular. Gauss-Jordan elimination with partial pivoting, scalar by scalar (H and b are kept)."""
    a = np.empty((4, 8))
    for i in range(4):
        for j in range(4):
            a[i, j] = H[i, j]
            a[i, 4 + j] = 1.0 if i == j else 0.0
    for c in range(4):
        p = c
        for r in range(c + 1, 4):
            if abs(a[r, c]) > abs(a[p, c]):
                p = r
        piv = a[p, c]
        if not abs(piv) > 0.0:
            return math.nan
        if p != c:
            for j in range(8):
                tmp = a[c, j]
                a[c, j] = a[p, j]
                a[p, j] = tmp
        for j in range(8):
            a[c, j] = a[c, j] / piv
        for r in range(4):
            if r != c:
                f = a[r, c]
                for j in range(8):
                    a[r, j] = a[r, j] - f * a[c, j]
    for i in range(4):
        s = 0.0
        for j in range(4):
            s += a[i, 4 + j] * b[j]
        step[i] = -s
    return float(a[0, 4])


def turn(R: Any, w0: float, w1: float, w2: float) -> None:
    """R (3, 3) <- R exp(hat(w)) in place (Rodrigues, `so3.exp`'s coefficients), scalar by scalar."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = math.sqrt(t2)
    if theta < _SMALL_RAD:
        A = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    else:
        A = math.sin(theta) / theta
        s = math.sin(0.5 * theta)
        B = 2.0 * (s * s) / (theta * theta)
    E = np.empty((3, 3))
    E[0, 0] = 1.0 + B * (-(w1 * w1) - w2 * w2)
    E[0, 1] = -A * w2 + B * (w0 * w1)
    E[0, 2] = A * w1 + B * (w0 * w2)
    E[1, 0] = A * w2 + B * (w0 * w1)
    E[1, 1] = 1.0 + B * (-(w0 * w0) - w2 * w2)
    E[1, 2] = -A * w0 + B * (w1 * w2)
    E[2, 0] = -A * w1 + B * (w0 * w2)
    E[2, 1] = A * w0 + B * (w1 * w2)
    E[2, 2] = 1.0 + B * (-(w0 * w0) - w1 * w1)
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = R[i, 0] * E[0, j] + R[i, 1] * E[1, j] + R[i, 2] * E[2, j]
    for i in range(3):
        for j in range(3):
            R[i, j] = out[i, j]


# The shared steps as the kernel calls them: the Python functions, replaced by their compiled versions in `_build`
# before the kernel is compiled (numba resolves a global function when it compiles its caller).
_sum: Any = _pairwise_py
_solve4: Any = solve4
_turn: Any = turn


def _fit(R0: Any, t: Any, ao: Any, ad: Any, q: Any, z0: float, top: float, fx: float, fy: float, sk: float,
         cx: float, cy: float, estimate_rotation: bool) -> Any:
    """`ground_height.fit_ground_height`'s iterations for a pinhole camera: (status, z, var, n_used), status 1 when
    the fit holds, 0 when it gives none (too few usable points, no information, a singular system)."""
    k = ao.shape[0]
    R = R0.copy()
    z = z0
    var = math.inf
    n_used = 0
    n_par = 4.0 if estimate_rotation else 1.0
    e = np.empty(k)
    A = np.empty((k, 4))
    w = np.empty(k)
    tmp = np.empty(k)
    H = np.empty((4, 4))
    b = np.empty(4)
    step = np.empty(4)
    for _ in range(ITERATIONS):
        m = 0  # the usable points, compacted to the front as the numpy code's e[ok]
        for i in range(k):
            dz = ad[i, 2]
            dz_s = dz if dz < -1e-6 else math.nan
            tt = (z - ao[i, 2]) / dz_s
            if not tt > 0.0:
                continue
            x0 = ao[i, 0] + tt * ad[i, 0]
            x1 = ao[i, 1] + tt * ad[i, 1]
            x2 = ao[i, 2] + tt * ad[i, 2]
            d0, d1, d2 = x0 - t[0], x1 - t[1], x2 - t[2]
            pz = d0 * R[0, 2] + d1 * R[1, 2] + d2 * R[2, 2]
            if not pz > 1e-3:
                continue
            px = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
            py = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
            xn = px / pz
            yn = py / pz
            u = fx * xn + sk * yn + cx
            v = fy * yn + cy
            inv_z = 1.0 / pz
            j02 = -xn / pz
            j12 = -yn / pz
            J00, J01, J02 = fx * inv_z, sk * inv_z, fx * j02 + sk * j12
            J10, J11, J12 = 0.0, fy * inv_z, fy * j12
            du = -(J00 * R[0, 0] + J01 * R[0, 1] + J02 * R[0, 2])
            dv = -(J10 * R[0, 0] + J11 * R[0, 1] + J12 * R[0, 2])
            nrm = math.sqrt(du * du + dv * dv)
            if not nrm >= 1e-12:
                nrm = 1e-12
            du = du / nrm
            dv = dv / nrm
            e[m] = du * (q[i, 0] - u) + dv * (q[i, 1] - v)
            g0 = (ad[i, 0] / dz_s) * R[0, 0] + (ad[i, 1] / dz_s) * R[1, 0] + (ad[i, 2] / dz_s) * R[2, 0]
            g1 = (ad[i, 0] / dz_s) * R[0, 1] + (ad[i, 1] / dz_s) * R[1, 1] + (ad[i, 2] / dz_s) * R[2, 1]
            g2 = (ad[i, 0] / dz_s) * R[0, 2] + (ad[i, 1] / dz_s) * R[1, 2] + (ad[i, 2] / dz_s) * R[2, 2]
            A[m, 0] = -(du * (J00 * g0 + J01 * g1 + J02 * g2) + dv * (J10 * g0 + J11 * g1 + J12 * g2))
            h0 = du * J00 + dv * J10
            h1 = du * J01 + dv * J11
            h2 = du * J02 + dv * J12
            A[m, 1] = py * h2 - pz * h1
            A[m, 2] = pz * h0 - px * h2
            A[m, 3] = px * h1 - py * h0
            m += 1
        if m < MIN_POINTS:
            return 0, z, var, n_used
        for i in range(m):
            tmp[i] = abs(e[i])
        srt = np.sort(tmp[:m])
        h = m // 2
        med = srt[h] if m % 2 else (srt[h - 1] + srt[h]) / 2.0
        scale = 1.4826 * med
        if not scale >= MIN_SCALE_PX:
            scale = MIN_SCALE_PX
        for i in range(m):
            uu = e[i] / (TUKEY_C * scale)
            a1 = 1.0 - uu * uu
            w[i] = a1 * a1 if abs(uu) < 1.0 else 0.0
        for i in range(m):
            tmp[i] = w[i] * A[i, 0] * A[i, 0]
        info = _sum(tmp, m)
        if not info > 0.0:
            return 0, z, var, n_used
        if estimate_rotation:
            for r in range(4):
                for c in range(4):
                    for i in range(m):
                        tmp[i] = (A[i, r] * w[i]) * A[i, c]
                    H[r, c] = _sum(tmp, m)
                for i in range(m):
                    tmp[i] = (A[i, r] * w[i]) * e[i]
                b[r] = _sum(tmp, m)
            for r in range(1, 4):
                H[r, r] = H[r, r] + ROTATION_RIDGE
            var_per_px2 = _solve4(H, b, step)
            if math.isnan(var_per_px2):
                return 0, z, var, n_used
            z_step = step[0]
            _turn(R, min(max(step[1], -MAX_ROTATION_STEP_RAD), MAX_ROTATION_STEP_RAD),
                  min(max(step[2], -MAX_ROTATION_STEP_RAD), MAX_ROTATION_STEP_RAD),
                  min(max(step[3], -MAX_ROTATION_STEP_RAD), MAX_ROTATION_STEP_RAD))
        else:
            for i in range(m):
                tmp[i] = w[i] * A[i, 0] * e[i]
            z_step = -_sum(tmp, m) / info
            var_per_px2 = 1.0 / info
        z = min(z + min(max(z_step, -1.0), 1.0), top)
        n_used = 0
        for i in range(m):
            if w[i] > 0.0:
                n_used += 1
        dof = max(_sum(w, m) - n_par, 1.0)
        for i in range(m):
            tmp[i] = w[i] * e[i] * e[i]
        var = max(_sum(tmp, m) / dof, MIN_SCALE_PX * MIN_SCALE_PX) * var_per_px2
    return 1, z, var, n_used


@dataclass(frozen=True)
class Kernels:
    """The compiled kernel (a numba dispatcher with `_fit`'s signature)."""

    fit: Any


def _build(njit: Any) -> Kernels:
    global _sum, _solve4, _turn
    _sum, _solve4, _turn = njit(_pairwise_py), njit(solve4), njit(turn)  # before their caller compiles
    return Kernels(fit=njit(_fit))


def _warm_up(ks: Kernels) -> None:
    d = np.zeros((1, 3))
    for rot in (False, True):
        ks.fit(np.eye(3), np.zeros(3), d, d, np.zeros((1, 2)), -1.0, -0.5, 1.0, 1.0, 0.0, 0.0, 0.0, rot)


def kernels() -> Kernels | None:
    """The compiled kernel, or None (numba unavailable or `COMPANION_JIT=0`: the fit runs numpy)."""
    return compile_kernels("rack.ground_height", _build, _warm_up)


register(kernels)
