"""Compiled pinhole projection (numba, optional: `companion/jit.py`) for `PinholeCamera` without distortion.

The trackers project a few hundred points a dozen times per frame; the numpy code's time there is its
per-call overhead. `_pinhole` is the same element-wise arithmetic as `PinholeCamera._project` without a
distortion model, in the same order, so both give the same bits (`tests/test_jit.py`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.jit import compile_kernels, register


def _pinhole(p: Any, fx: float, fy: float, sk: float, cx: float, cy: float, min_depth_m: float,
             with_jacobian: bool) -> Any:
    """Pixels (N, 2) of camera-frame points p (N, 3) and, if asked, d(u, v)/dp (N, 2, 3) (else (0, 2, 3));
    NaN rows where z <= `min_depth_m` (their Jacobian too)."""
    n = p.shape[0]
    uv = np.empty((n, 2))
    J = np.empty((n if with_jacobian else 0, 2, 3))
    for i in range(n):
        z = p[i, 2]
        front = z > min_depth_m
        zs = z if front else 1.0
        x = p[i, 0] / zs
        y = p[i, 1] / zs
        if front:
            uv[i, 0] = fx * x + sk * y + cx
            uv[i, 1] = fy * y + cy
        else:
            uv[i, 0] = np.nan
            uv[i, 1] = np.nan
        if with_jacobian:
            if front:
                inv_z = 1.0 / zs
                j02 = -x / zs
                j12 = -y / zs
                J[i, 0, 0] = fx * inv_z
                J[i, 0, 1] = sk * inv_z
                J[i, 0, 2] = fx * j02 + sk * j12
                J[i, 1, 0] = 0.0
                J[i, 1, 1] = fy * inv_z
                J[i, 1, 2] = fy * j12
            else:
                for a in range(2):
                    for b in range(3):
                        J[i, a, b] = np.nan
    return uv, J


@dataclass(frozen=True)
class Kernels:
    """The compiled kernel (a numba dispatcher with `_pinhole`'s signature)."""

    pinhole: Any


def _build(njit: Any) -> Kernels:
    return Kernels(pinhole=njit(_pinhole))


def _warm_up(ks: Kernels) -> None:
    for with_jacobian in (False, True):
        ks.pinhole(np.ones((1, 3)), 1.0, 1.0, 0.0, 0.0, 0.0, 1e-9, with_jacobian)


def kernels() -> Kernels | None:
    """The compiled kernel, or None (numba unavailable or `COMPANION_JIT=0`: the camera runs numpy)."""
    return compile_kernels("camera.pinhole", _build, _warm_up)


register(kernels)
