"""The rotation group SO(3): exp, log, hat, vee and Jacobians, batched over leading axes.

Rotation vectors `w` (rad) have shape (..., 3); rotation matrices (..., 3, 3).
Every function accepts a single element or a stack and keeps the leading shape.
Small angles use Taylor branches and angles near pi go through a unit
quaternion, so nothing loses precision or returns NaN anywhere on [0, pi].

Jacobians follow the convention of Barfoot, "State Estimation for Robotics":
    exp(w + dw) ~= exp(J_l(w) dw) exp(w) ~= exp(w) exp(J_r(w) dw).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from companion.checks import FloatArray, check_last_dim, check_last_two_dims

# Below this angle the closed-form coefficients switch to Taylor series. The
# series are kept to theta^4 so their truncation error is < 1e-16 here.
_SMALL_RAD = 1e-3


def hat(w: Any) -> FloatArray:
    """Skew-symmetric matrix (..., 3, 3) of vectors (..., 3): hat(w) @ p = w x p."""
    w = check_last_dim(w, 3, "w")
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1] = -w[..., 2]
    W[..., 0, 2] = w[..., 1]
    W[..., 1, 0] = w[..., 2]
    W[..., 1, 2] = -w[..., 0]
    W[..., 2, 0] = -w[..., 1]
    W[..., 2, 1] = w[..., 0]
    return W


def vee(W: Any) -> FloatArray:
    """Inverse of `hat`: the vector (..., 3) of the skew part of (..., 3, 3)."""
    W = check_last_two_dims(W, 3, 3, "W")
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def _coefficients(theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, precise for all t >= 0."""
    small = theta < _SMALL_RAD
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    A = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(t) / t)
    # 2 sin^2(t/2) avoids the cancellation of 1 - cos t.
    B = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 2.0 * np.sin(0.5 * t) ** 2 / (t * t))
    C = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - np.sin(t)) / (t * t * t))
    return A, B, C


def exp(w: Any) -> FloatArray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues)."""
    w = check_last_dim(w, 3, "w")
    theta = np.linalg.norm(w, axis=-1)
    A, B, _ = _coefficients(theta)
    W = hat(w)
    WW = W @ W
    return np.eye(3) + A[..., None, None] * W + B[..., None, None] * WW


def quaternion_from_matrix(R: Any) -> FloatArray:
    """Unit quaternions (..., 4) ordered (w, x, y, z) with w >= 0, from rotations (..., 3, 3).

    Shepperd's method: pick the largest of the four squared components so the
    division is always by a number >= 1/2, which keeps full precision at pi.
    """
    R = check_last_two_dims(R, 3, 3, "R")
    if R.shape == (3, 3):
        return np.array(_quaternion_one(R))
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    cand = np.stack([trace, m00, m11, m22], axis=-1)
    k = np.argmax(cand, axis=-1)
    q = np.empty(R.shape[:-2] + (4,))
    # Case 0: w largest.
    s0 = np.sqrt(np.maximum(1.0 + trace, 1e-300)) * 2.0
    q0 = np.stack(
        [0.25 * s0, (R[..., 2, 1] - R[..., 1, 2]) / s0, (R[..., 0, 2] - R[..., 2, 0]) / s0,
         (R[..., 1, 0] - R[..., 0, 1]) / s0],
        axis=-1,
    )
    s1 = np.sqrt(np.maximum(1.0 + m00 - m11 - m22, 1e-300)) * 2.0
    q1 = np.stack(
        [(R[..., 2, 1] - R[..., 1, 2]) / s1, 0.25 * s1, (R[..., 0, 1] + R[..., 1, 0]) / s1,
         (R[..., 0, 2] + R[..., 2, 0]) / s1],
        axis=-1,
    )
    s2 = np.sqrt(np.maximum(1.0 - m00 + m11 - m22, 1e-300)) * 2.0
    q2 = np.stack(
        [(R[..., 0, 2] - R[..., 2, 0]) / s2, (R[..., 0, 1] + R[..., 1, 0]) / s2, 0.25 * s2,
         (R[..., 1, 2] + R[..., 2, 1]) / s2],
        axis=-1,
    )
    s3 = np.sqrt(np.maximum(1.0 - m00 - m11 + m22, 1e-300)) * 2.0
    q3 = np.stack(
        [(R[..., 1, 0] - R[..., 0, 1]) / s3, (R[..., 0, 2] + R[..., 2, 0]) / s3,
         (R[..., 1, 2] + R[..., 2, 1]) / s3, 0.25 * s3],
        axis=-1,
    )
    q = np.where((k == 0)[..., None], q0, q)
    q = np.where((k == 1)[..., None], q1, q)
    q = np.where((k == 2)[..., None], q2, q)
    q = np.where((k == 3)[..., None], q3, q)
    q = np.where((q[..., :1] < 0.0), -q, q)
    result: FloatArray = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return result


def _quaternion_one(R: FloatArray) -> tuple[float, float, float, float]:
    """`quaternion_from_matrix` of one (3, 3) matrix in Python floats: the same operations in the same order (the
    same bits), without the per-call cost of the array code (the tracker's health check calls it every frame)."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = R.tolist()
    trace = m00 + m11 + m22
    cand = (trace, m00, m11, m22)
    k = cand.index(max(cand)) if not any(c != c for c in cand) else next(i for i, c in enumerate(cand) if c != c)
    if k == 0:
        s = math.sqrt(max(1.0 + trace, 1e-300)) * 2.0
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif k == 1:
        s = math.sqrt(max(1.0 + m00 - m11 - m22, 1e-300)) * 2.0
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif k == 2:
        s = math.sqrt(max(1.0 - m00 + m11 - m22, 1e-300)) * 2.0
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = math.sqrt(max(1.0 - m00 - m11 + m22, 1e-300)) * 2.0
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    if q[0] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def matrix_from_quaternion(q: Any) -> FloatArray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) ordered (w, x, y, z); normalizes."""
    q = check_last_dim(q, 4, "q")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        from companion.errors import InputError

        raise InputError("q: zero-norm quaternion")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def log(R: Any) -> FloatArray:
    """Rotation vectors (..., 3) with angle in [0, pi] of rotations (..., 3, 3).

    At exactly pi the axis sign is arbitrary (both are valid logarithms).
    """
    if isinstance(R, np.ndarray) and R.shape == (3, 3):
        return _log_one(R)
    q = quaternion_from_matrix(R)
    qw = q[..., 0]
    qv = q[..., 1:]
    n = np.linalg.norm(qv, axis=-1)
    # theta = 2 atan2(n, w); w >= 0 so theta in [0, pi]. theta / n via series when n << w.
    small = n < 1e-6 * np.maximum(qw, 1e-300)
    n_safe = np.where(small, 1.0, n)
    ratio = np.where(
        small,
        (2.0 / np.where(small, qw, 1.0)) * (1.0 - (n / np.where(small, qw, 1.0)) ** 2 / 3.0),
        2.0 * np.arctan2(n, qw) / n_safe,
    )
    result: FloatArray = ratio[..., None] * qv
    return result


def _log_one(R: FloatArray) -> FloatArray:
    """`log` of one (3, 3) matrix in Python floats: the array code's operations in its order (the same bits;
    arctan2 is numpy's, which differs from `math.atan2` in the last bit)."""
    qw, x, y, z = _quaternion_one(R)
    n = math.sqrt(x * x + y * y + z * z)
    if n < 1e-6 * max(qw, 1e-300):
        r = n / qw
        ratio = (2.0 / qw) * (1.0 - r * r / 3.0)
    else:
        ratio = 2.0 * float(np.arctan2(n, qw)) / n
    return np.array([ratio * x, ratio * y, ratio * z])


def left_jacobian(w: Any) -> FloatArray:
    """J_l(w) (..., 3, 3): exp(w + dw) ~= exp(J_l(w) dw) exp(w)."""
    w = check_last_dim(w, 3, "w")
    theta = np.linalg.norm(w, axis=-1)
    _, B, C = _coefficients(theta)
    W = hat(w)
    return np.eye(3) + B[..., None, None] * W + C[..., None, None] * (W @ W)


def right_jacobian(w: Any) -> FloatArray:
    """J_r(w) = J_l(-w) (..., 3, 3): exp(w + dw) ~= exp(w) exp(J_r(w) dw)."""
    return left_jacobian(-check_last_dim(w, 3, "w"))


def _inverse_coefficient(theta: FloatArray) -> FloatArray:
    """D = (1 - (t/2) cot(t/2)) / t^2, the K^2 coefficient of J_l^-1; finite on [0, 2 pi)."""
    small = theta < _SMALL_RAD
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    half = 0.5 * t
    return np.where(
        small,
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
        (1.0 - half * np.cos(half) / np.sin(half)) / (t * t),
    )


def left_jacobian_inverse(w: Any) -> FloatArray:
    """J_l(w)^-1 (..., 3, 3), closed form (valid for angles below 2 pi)."""
    w = check_last_dim(w, 3, "w")
    theta = np.linalg.norm(w, axis=-1)
    D = _inverse_coefficient(theta)
    W = hat(w)
    result: FloatArray = np.eye(3) - 0.5 * W + D[..., None, None] * (W @ W)
    return result


def right_jacobian_inverse(w: Any) -> FloatArray:
    """J_r(w)^-1 = J_l(-w)^-1 (..., 3, 3)."""
    return left_jacobian_inverse(-check_last_dim(w, 3, "w"))


def inverse(R: Any) -> FloatArray:
    """Inverse rotations (transposes) (..., 3, 3)."""
    R = check_last_two_dims(R, 3, 3, "R")
    result: FloatArray = np.swapaxes(R, -1, -2).copy()
    return result


def adjoint(R: Any) -> FloatArray:
    """Adjoint of SO(3): the rotation matrix itself (R hat(w) R^T = hat(R w))."""
    return check_last_two_dims(R, 3, 3, "R").copy()
