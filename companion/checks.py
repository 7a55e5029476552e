"""Input validation helpers: return float64 arrays or raise `InputError` naming the argument."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError

FloatArray = NDArray[np.float64]


def as_float_array(x: Any, name: str) -> FloatArray:
    """`x` as a float64 array; raises if it is not numeric or holds NaN/inf."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a numeric array, got {type(x).__name__}") from exc
    if not np.isfinite(arr).all():  # the method: np.all's dispatch costs more than the test on small arrays
        raise InputError(f"{name}: contains NaN or infinite values")
    return arr


def check_last_dim(x: Any, n: int, name: str) -> FloatArray:
    """`x` as float64 with shape (..., n)."""
    arr = as_float_array(x, name)
    if arr.ndim == 0 or arr.shape[-1] != n:
        raise InputError(f"{name}: expected shape (..., {n}), got {arr.shape}")
    return arr


def check_last_two_dims(x: Any, rows: int, cols: int, name: str) -> FloatArray:
    """`x` as float64 with shape (..., rows, cols)."""
    arr = as_float_array(x, name)
    if arr.ndim < 2 or arr.shape[-2:] != (rows, cols):
        raise InputError(f"{name}: expected shape (..., {rows}, {cols}), got {arr.shape}")
    return arr


def check_rotation(R: Any, name: str = "R", tol: float = 1e-6) -> FloatArray:
    """`R` as a float64 (..., 3, 3) proper rotation (orthonormal, det +1 within tol)."""
    arr = check_last_two_dims(R, 3, 3, name)
    err = np.abs(np.swapaxes(arr, -1, -2) @ arr - np.eye(3)).max(initial=0.0)
    if err > tol:
        raise InputError(f"{name}: not orthonormal (max |R^T R - I| = {err:.2e})")
    if np.any(np.linalg.det(arr) < 0.0):
        raise InputError(f"{name}: determinant is negative (a reflection, not a rotation)")
    return arr


def check_transform(T: Any, name: str = "T", tol: float = 1e-6) -> FloatArray:
    """`T` as a float64 (..., 4, 4) rigid transform with a proper rotation block."""
    arr = check_last_two_dims(T, 4, 4, name)
    check_rotation(arr[..., :3, :3], f"{name}[:3, :3]", tol)
    bottom = arr[..., 3, :]
    if np.abs(bottom - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0) > tol:
        raise InputError(f"{name}: last row must be [0, 0, 0, 1]")
    return arr
