"""Scalar SO(3) helpers of the navigation filter's hot path (rotation vectors in rad, 3x3 rotation matrices).

exp and right Jacobian, log, inverse left Jacobian and the Rodrigues coefficients, as scalar code for
the filter's hot path.
"""

from __future__ import annotations

import math

import numpy as np

from companion.checks import FloatArray
from companion.geometry import so3

_I3 = np.eye(3)
_SMALL = 1e-4


def _hat(w0: float, w1: float, w2: float) -> FloatArray:
    return np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])


def exp_and_right_jacobian(w0: float, w1: float, w2: float) -> tuple[FloatArray, FloatArray]:
    """(exp(w), J_r(w)) of one rotation vector (rad), scalar code for the hot path."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < _SMALL * _SMALL:
        A = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        C = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    else:
        t = math.sqrt(t2)
        s = math.sin(t)
        A = s / t
        h = math.sin(0.5 * t)
        B = 2.0 * h * h / t2
        C = (t - s) / (t2 * t)
    W = _hat(w0, w1, w2)
    WW = W @ W
    return _I3 + A * W + B * WW, _I3 - B * W + C * WW


def log_so3(R: FloatArray) -> FloatArray:
    """Rotation vector (3,) of one rotation matrix; scalar fast path, `so3.log` near pi."""
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    v0 = R[2, 1] - R[1, 2]
    v1 = R[0, 2] - R[2, 0]
    v2 = R[1, 0] - R[0, 1]
    if c > 0.999999:
        # theta < 1.4e-3: theta / (2 sin theta) ~= 1/2 + theta^2 / 12, theta^2 ~= 2 (1 - c).
        k = 0.5 + (1.0 - c) / 6.0
        return np.array([k * v0, k * v1, k * v2])
    if c < -0.99:
        return so3.log(R)
    theta = math.acos(c)
    k = 0.5 * theta / math.sin(theta)
    return np.array([k * v0, k * v1, k * v2])


def left_jacobian_inverse_so3(w: FloatArray) -> FloatArray:
    """J_l(w)^-1 (3, 3) of one rotation vector: I - hat(w) / 2 + D hat(w)^2."""
    w0, w1, w2 = float(w[0]), float(w[1]), float(w[2])
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-6:
        D = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        t = math.sqrt(t2)
        h = 0.5 * t
        D = (1.0 - h * math.cos(h) / math.sin(h)) / t2
    W = _hat(w0, w1, w2)
    result: FloatArray = _I3 - 0.5 * W + D * (W @ W)
    return result


def _rodrigues_terms(w0: float, w1: float, w2: float) -> tuple[float, float, float, float]:
    """(A, B, C, theta^2): sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3 for t = |w|."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < _SMALL * _SMALL:
        return (1.0 - t2 / 6.0 + t2 * t2 / 120.0, 0.5 - t2 / 24.0 + t2 * t2 / 720.0,
                1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, t2)
    t = math.sqrt(t2)
    s = math.sin(t)
    h = math.sin(0.5 * t)
    return s / t, 2.0 * h * h / t2, (t - s) / (t2 * t), t2
