"""IMU propagation of the navigation filter: the nominal state step and its error transition F (21, 21).

Body FRD gyro (rad/s) and specific force (m/s^2) in, NED state out; gravity along +z (down).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from companion.checks import FloatArray
from companion.estimation.model_so3 import _rodrigues_terms
from companion.estimation.model_state import ERROR_SIZE, R_SL


def new_transition() -> FloatArray:
    """A (21, 21) buffer for `propagate_in_place`: identity, its constant part."""
    return np.eye(ERROR_SIZE)


def propagate_in_place(
    x: FloatArray,
    gyro_rad_s: Sequence[float] | FloatArray,
    accel_m_s2: Sequence[float] | FloatArray,
    dt_s: float,
    gravity_m_s2: float,
    F_out: FloatArray,
) -> None:
    """Advance the nominal state `x` by `dt_s` and write the error transition into `F_out` (21, 21).

    `gyro_rad_s` / `accel_m_s2` (body FRD, raw, biases not removed) are the mean
    IMU readings over the step (the filter passes the mean of the readings at
    both ends: trapezoidal rule). Discrete model (w = gyro - b_g, a = accel - b_a):

        R_half = exp(w dt / 2),  R_mid = R R_half
        v' = v + (R_mid a + g e_down) dt
        p' = p + v dt + (R_mid a + g e_down) dt^2 / 2
        R' = R exp(w dt) = R R_half^2;  biases and clone unchanged.

    `F_out` = d(dx')/d(dx) (right attitude perturbation). Only its variable
    blocks (rows 0:9, columns 3:15) are written: start from `new_transition()`
    and reuse the buffer. In place on purpose: this is the filter's hot path, so
    the 3x3 algebra is scalar code and the products with R are one matmul.
    """
    dt = dt_s
    bg0, bg1, bg2, ba0, ba1, ba2 = x[15:21].tolist()
    hdt = 0.5 * dt
    # Half-step rotation vector and its terms; the full step uses 2x the same vector.
    u0 = (gyro_rad_s[0] - bg0) * hdt
    u1 = (gyro_rad_s[1] - bg1) * hdt
    u2 = (gyro_rad_s[2] - bg2) * hdt
    a0 = accel_m_s2[0] - ba0
    a1 = accel_m_s2[1] - ba1
    a2 = accel_m_s2[2] - ba2
    A, B, C, t2 = _rodrigues_terms(u0, u1, u2)
    c = 1.0 - B * t2
    d = 1.0 - C * t2
    u00, u11, u22, u01, u02, u12 = u0 * u0, u1 * u1, u2 * u2, u0 * u1, u0 * u2, u1 * u2
    # R_half = exp(u), J = J_r(u) (rows).
    h00, h01, h02 = c + B * u00, B * u01 - A * u2, B * u02 + A * u1
    h10, h11, h12 = B * u01 + A * u2, c + B * u11, B * u12 - A * u0
    h20, h21, h22 = B * u02 - A * u1, B * u12 + A * u0, c + B * u22
    j00, j01, j02 = d + C * u00, C * u01 + B * u2, C * u02 - B * u1
    j10, j11, j12 = C * u01 - B * u2, d + C * u11, C * u12 + B * u0
    j20, j21, j22 = C * u02 + B * u1, C * u12 - B * u0, d + C * u22
    # J_r(2u) for the full step.
    Af, Bf, Cf, tf2 = _rodrigues_terms(2.0 * u0, 2.0 * u1, 2.0 * u2)
    df = 1.0 - Cf * tf2
    Bf2, Cf4 = 2.0 * Bf, 4.0 * Cf
    del Af
    # ra = R_half a.
    r0 = h00 * a0 + h01 * a1 + h02 * a2
    r1 = h10 * a0 + h11 * a1 + h12 * a2
    r2 = h20 * a0 + h21 * a1 + h22 * a2
    # M = hat(a) J (columns are a x J[:, k]), then K = R_half M.
    m00, m01, m02 = a1 * j20 - a2 * j10, a1 * j21 - a2 * j11, a1 * j22 - a2 * j12
    m10, m11, m12 = a2 * j00 - a0 * j20, a2 * j01 - a0 * j21, a2 * j02 - a0 * j22
    m20, m21, m22 = a0 * j10 - a1 * j00, a0 * j11 - a1 * j01, a0 * j12 - a1 * j02
    cbg = 0.5 * dt * dt
    k00 = (h00 * m00 + h01 * m10 + h02 * m20) * cbg
    k01 = (h00 * m01 + h01 * m11 + h02 * m21) * cbg
    k02 = (h00 * m02 + h01 * m12 + h02 * m22) * cbg
    k10 = (h10 * m00 + h11 * m10 + h12 * m20) * cbg
    k11 = (h10 * m01 + h11 * m11 + h12 * m21) * cbg
    k12 = (h10 * m02 + h11 * m12 + h12 * m22) * cbg
    k20 = (h20 * m00 + h21 * m10 + h22 * m20) * cbg
    k21 = (h20 * m01 + h21 * m11 + h22 * m21) * cbg
    k22 = (h20 * m02 + h21 * m12 + h22 * m22) * cbg
    # R_full = R_half @ R_half.
    f00 = h00 * h00 + h01 * h10 + h02 * h20
    f01 = h00 * h01 + h01 * h11 + h02 * h21
    f02 = h00 * h02 + h01 * h12 + h02 * h22
    f10 = h10 * h00 + h11 * h10 + h12 * h20
    f11 = h10 * h01 + h11 * h11 + h12 * h21
    f12 = h10 * h02 + h11 * h12 + h12 * h22
    f20 = h20 * h00 + h21 * h10 + h22 * h20
    f21 = h20 * h01 + h21 * h11 + h22 * h21
    f22 = h20 * h02 + h21 * h12 + h22 * h22
    n = -dt
    # One product R @ [ -dt hat(ra) | K | -dt R_half | ra | R_full ] gives
    # A_th, A_bg, A_ba, the specific force in NED and the new attitude.
    X = np.array(
        [
            [0.0, -n * r2, n * r1, k00, k01, k02, n * h00, n * h01, n * h02, r0, f00, f01, f02],
            [n * r2, 0.0, -n * r0, k10, k11, k12, n * h10, n * h11, n * h12, r1, f10, f11, f12],
            [-n * r1, n * r0, 0.0, k20, k21, k22, n * h20, n * h21, n * h22, r2, f20, f21, f22],
        ]
    )
    Y = x[R_SL].reshape(3, 3) @ X
    F = F_out
    F[3:6, 6:15] = Y[:, 0:9]
    F[0:3, 6:15] = Y[:, 0:9] * hdt
    F[0, 3] = F[1, 4] = F[2, 5] = dt
    # Attitude rows: R_full^T and -dt J_r(w dt), with J_r(2u) = I(1 - Cf tf2) + Cf (2u)(2u)^T - Bf hat(2u).
    F[6:9, 6:12] = [
        [f00, f10, f20, n * (df + Cf4 * u00), n * (Cf4 * u01 + Bf2 * u2), n * (Cf4 * u02 - Bf2 * u1)],
        [f01, f11, f21, n * (Cf4 * u01 - Bf2 * u2), n * (df + Cf4 * u11), n * (Cf4 * u12 + Bf2 * u0)],
        [f02, f12, f22, n * (Cf4 * u02 + Bf2 * u1), n * (Cf4 * u12 - Bf2 * u0), n * (df + Cf4 * u22)],
    ]
    dv = Y[:, 9] * dt
    dv[2] += gravity_m_s2 * dt
    x[0:3] += x[3:6] * dt + dv * hdt
    x[3:6] += dv
    x[R_SL] = Y[:, 10:13].ravel()
