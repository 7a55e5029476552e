"""The rigid-motion group SE(3): exp, log, hat, vee, adjoint, inverse and Jacobians.

Twists `xi` are ordered (v, w): translation part first, rotation vector second,
matching the generators G1..G6 of Lippiello & Cacace (translations x, y, z then
rotations about x, y, z). Transforms are 4x4 homogeneous matrices `T_a_b` with
p_a = T_a_b @ p_b. Every function is batched over leading axes: a twist has
shape (..., 6), a transform (..., 4, 4).

Jacobians follow Barfoot, "State Estimation for Robotics" (whose twist order is
also translation first):
    exp(xi + dxi) ~= exp(J_l(xi) dxi) exp(xi) ~= exp(xi) exp(J_r(xi) dxi).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from companion.checks import FloatArray, check_last_dim, check_last_two_dims
from companion.geometry import so3

_SMALL_RAD = 1e-3


def hat(xi: Any) -> FloatArray:
    """4x4 Lie-algebra matrices (..., 4, 4) of twists (..., 6) ordered (v, w)."""
    xi = check_last_dim(xi, 6, "xi")
    X = np.zeros(xi.shape[:-1] + (4, 4))
    X[..., :3, :3] = so3.hat(xi[..., 3:])
    X[..., :3, 3] = xi[..., :3]
    return X


def vee(X: Any) -> FloatArray:
    """Twists (..., 6) of Lie-algebra matrices (..., 4, 4); inverse of `hat`."""
    X = check_last_two_dims(X, 4, 4, "X")
    return np.concatenate([X[..., :3, 3], so3.vee(X[..., :3, :3])], axis=-1)


def make(R: Any, t: Any) -> FloatArray:
    """Transforms (..., 4, 4) from rotations (..., 3, 3) and translations (..., 3)."""
    R = check_last_two_dims(R, 3, 3, "R")
    t = check_last_dim(t, 3, "t")
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def exp(xi: Any) -> FloatArray:
    """Transforms (..., 4, 4) of twists (..., 6): R = exp(w), t = J_l(w) v."""
    xi = check_last_dim(xi, 6, "xi")
    v, w = xi[..., :3], xi[..., 3:]
    R = so3.exp(w)
    t = np.einsum("...ij,...j->...i", so3.left_jacobian(w), v)
    return make(R, t)


def exp_one(xi: FloatArray) -> FloatArray:
    """`exp` (4, 4) of ONE twist (6,) = (v (m), w (rad)), without batching and input checks.

    Same formulas and thresholds as `exp` / `so3.exp` (R = exp(w), t = J_l(w) v with the
    sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3 coefficients and their series below 1e-3 rad),
    for per-frame and per-iteration updates in hot loops (the rack tracker), where the batched
    path's checks dominate; agrees with it to rounding (tested).
    """
    w0, w1, w2 = float(xi[3]), float(xi[4]), float(xi[5])
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = math.sqrt(t2)
    if theta < _SMALL_RAD:
        A = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        C = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    else:
        s = math.sin(theta)
        A = s / theta
        B = 2.0 * math.sin(0.5 * theta) ** 2 / (theta * theta)
        C = (theta - s) / (theta * theta * theta)
    W = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    WW = W @ W
    T = np.zeros((4, 4))
    T[:3, :3] = A * W + B * WW
    T[0, 0] += 1.0
    T[1, 1] += 1.0
    T[2, 2] += 1.0
    J_l = B * W + C * WW
    J_l[0, 0] += 1.0
    J_l[1, 1] += 1.0
    J_l[2, 2] += 1.0
    T[:3, 3] = J_l @ np.asarray(xi[:3], dtype=np.float64)
    T[3, 3] = 1.0
    return T


def log(T: Any) -> FloatArray:
    """Twists (..., 6) of transforms (..., 4, 4); rotation angle in [0, pi]."""
    T = check_last_two_dims(T, 4, 4, "T")
    w = so3.log(T[..., :3, :3])
    v = np.einsum("...ij,...j->...i", so3.left_jacobian_inverse(w), T[..., :3, 3])
    return np.concatenate([v, w], axis=-1)


def log_one(T: FloatArray) -> FloatArray:
    """`log` (6,) of ONE transform (4, 4), without batching and input checks (hot loops: the rack tracker).

    The same operations as `log` in the same order (Shepperd's quaternion, its angle, J_l^-1 v), but
    only the quaternion branch that `log` selects is computed and the scalar steps run on numpy
    scalars: bit-identical to `log` (tested), about 8x faster.
    """
    R = T[:3, :3]
    m00, m11, m22 = R[0, 0], R[1, 1], R[2, 2]
    trace = m00 + m11 + m22
    k = int(np.argmax(np.array([trace, m00, m11, m22])))
    if k == 0:
        s = np.sqrt(np.maximum(1.0 + trace, 1e-300)) * 2.0
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif k == 1:
        s = np.sqrt(np.maximum(1.0 + m00 - m11 - m22, 1e-300)) * 2.0
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif k == 2:
        s = np.sqrt(np.maximum(1.0 - m00 + m11 - m22, 1e-300)) * 2.0
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = np.sqrt(np.maximum(1.0 - m00 - m11 + m22, 1e-300)) * 2.0
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    if q[0] < 0.0:
        q = -q
    # np.linalg.norm(x, axis=-1) is sqrt(add.reduce(x * x, axis=-1)); the same reductions on the same shapes.
    q = q / np.sqrt(np.add.reduce(q * q, axis=-1, keepdims=True))
    qw, qv = q[0], q[1:]
    n = np.sqrt(np.add.reduce(qv * qv, axis=-1))
    if n < 1e-6 * np.maximum(qw, 1e-300):
        ratio = (2.0 / qw) * (1.0 - (n / qw) ** 2 / 3.0)
    else:
        ratio = 2.0 * np.arctan2(n, qw) / n
    w = ratio * qv
    theta = np.sqrt(np.add.reduce(w * w, axis=-1))
    if theta < so3._SMALL_RAD:
        t2 = theta * theta
        D = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        half = 0.5 * theta
        D = (1.0 - half * np.cos(half) / np.sin(half)) / (theta * theta)
    W = np.zeros((3, 3))
    W[0, 1] = -w[2]
    W[0, 2] = w[1]
    W[1, 0] = w[2]
    W[1, 2] = -w[0]
    W[2, 0] = -w[1]
    W[2, 1] = w[0]
    J_inv = np.eye(3) - 0.5 * W + D * (W @ W)
    v = np.einsum("...ij,...j->...i", J_inv, T[..., :3, 3])
    return np.concatenate([v, w], axis=-1)


def inverse(T: Any) -> FloatArray:
    """Inverse transforms (..., 4, 4): (R, t) -> (R^T, -R^T t)."""
    T = check_last_two_dims(T, 4, 4, "T")
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def compose(T_a_b: Any, T_b_c: Any) -> FloatArray:
    """T_a_c = T_a_b @ T_b_c, batched."""
    result: FloatArray = check_last_two_dims(T_a_b, 4, 4, "T_a_b") @ check_last_two_dims(T_b_c, 4, 4, "T_b_c")
    return result


def act(T_a_b: Any, p_b: Any) -> FloatArray:
    """Points p_a (..., 3) = T_a_b applied to points p_b (..., 3)."""
    T = check_last_two_dims(T_a_b, 4, 4, "T_a_b")
    p = check_last_dim(p_b, 3, "p_b")
    result: FloatArray = np.einsum("...ij,...j->...i", T[..., :3, :3], p) + T[..., :3, 3]
    return result


def adjoint(T: Any) -> FloatArray:
    """Adjoint matrices (..., 6, 6) in (v, w) order: T exp(xi) T^-1 = exp(Ad_T xi).

    Ad_T = [[R, hat(t) R], [0, R]].
    """
    T = check_last_two_dims(T, 4, 4, "T")
    R, t = T[..., :3, :3], T[..., :3, 3]
    A = np.zeros(T.shape[:-2] + (6, 6))
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., :3, 3:] = so3.hat(t) @ R
    return A


def curly_hat(xi: Any) -> FloatArray:
    """The 6x6 adjoint of the Lie algebra (..., 6, 6): ad(xi) = [[hat w, hat v], [0, hat w]]."""
    xi = check_last_dim(xi, 6, "xi")
    A = np.zeros(xi.shape[:-1] + (6, 6))
    Wv = so3.hat(xi[..., :3])
    Ww = so3.hat(xi[..., 3:])
    A[..., :3, :3] = Ww
    A[..., 3:, 3:] = Ww
    A[..., :3, 3:] = Wv
    return A


def _q_matrix(v: FloatArray, w: FloatArray) -> FloatArray:
    """Barfoot's Q(v, w) (..., 3, 3): the off-diagonal block of the SE(3) left Jacobian."""
    theta = np.linalg.norm(w, axis=-1)
    small = theta < _SMALL_RAD
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    c1 = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - np.sin(t)) / t**3)
    c2 = np.where(
        small,
        1.0 / 24.0 - t2 / 720.0 + t2 * t2 / 40320.0,
        (t * t + 2.0 * np.cos(t) - 2.0) / (2.0 * t**4),
    )
    c3 = np.where(
        small,
        1.0 / 120.0 - t2 / 2520.0 + t2 * t2 / 120960.0,
        (2.0 * t - 3.0 * np.sin(t) + t * np.cos(t)) / (2.0 * t**5),
    )
    V = so3.hat(v)
    W = so3.hat(w)
    WV = W @ V
    VW = V @ W
    WVW = WV @ W
    WW = W @ W
    Q: FloatArray = (
        0.5 * V
        + c1[..., None, None] * (WV + VW + WVW)
        + c2[..., None, None] * (WW @ V + V @ WW - 3.0 * WVW)
        + c3[..., None, None] * (WVW @ W + W @ WVW)
    )
    return Q


def left_jacobian(xi: Any) -> FloatArray:
    """J_l(xi) (..., 6, 6): exp(xi + dxi) ~= exp(J_l(xi) dxi) exp(xi)."""
    xi = check_last_dim(xi, 6, "xi")
    v, w = xi[..., :3], xi[..., 3:]
    Jw = so3.left_jacobian(w)
    J = np.zeros(xi.shape[:-1] + (6, 6))
    J[..., :3, :3] = Jw
    J[..., 3:, 3:] = Jw
    J[..., :3, 3:] = _q_matrix(v, w)
    return J


def right_jacobian(xi: Any) -> FloatArray:
    """J_r(xi) = J_l(-xi) (..., 6, 6): exp(xi + dxi) ~= exp(xi) exp(J_r(xi) dxi)."""
    return left_jacobian(-check_last_dim(xi, 6, "xi"))


def left_jacobian_inverse(xi: Any) -> FloatArray:
    """J_l(xi)^-1 (..., 6, 6) = [[J^-1, -J^-1 Q J^-1], [0, J^-1]] with J = SO(3) J_l(w)."""
    xi = check_last_dim(xi, 6, "xi")
    v, w = xi[..., :3], xi[..., 3:]
    Jinv = so3.left_jacobian_inverse(w)
    J = np.zeros(xi.shape[:-1] + (6, 6))
    J[..., :3, :3] = Jinv
    J[..., 3:, 3:] = Jinv
    J[..., :3, 3:] = -Jinv @ _q_matrix(v, w) @ Jinv
    return J


def right_jacobian_inverse(xi: Any) -> FloatArray:
    """J_r(xi)^-1 = J_l(-xi)^-1 (..., 6, 6)."""
    return left_jacobian_inverse(-check_last_dim(xi, 6, "xi"))


def generators() -> FloatArray:
    """The six 4x4 generators G1..G6 (6, 4, 4): translations x, y, z, rotations about x, y, z."""
    return hat(np.eye(6))
