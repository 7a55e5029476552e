"""State layout, IMU propagation and measurement models of the navigation filter.

Nominal state `x` (33 floats, one flat array so a snapshot is one copy):

    x[0:3]    p_ned_m        position of the body origin in NED
    x[3:6]    v_ned_m_s      velocity in NED
    x[6:15]   R_ned_body     attitude, row-major 3x3
    x[15:18]  b_gyro_rad_s   gyroscope bias, body FRD
    x[18:21]  b_accel_m_s2   accelerometer bias, body FRD
    x[21:24]  p_clone_ned_m  cloned (delayed) position, NED
    x[24:33]  R_clone        cloned attitude R_ned_body, row-major 3x3

Error state `dx` (21): dp (0:3), dv (3:6), dtheta (6:9), dbg (9:12), dba (12:15),
dp_clone (15:18), dtheta_clone (18:21). Positions, velocity and biases are
additive; attitudes use a RIGHT perturbation in the body frame:
R_true = R_est @ exp(dtheta). `boxplus` / `boxminus` implement exactly this.

Every function returning a Jacobian `H` follows r(x_est [+] eps) ~= r(x_est) - H eps,
i.e. r ~= H dx_true + noise with dx_true = x_true [-] x_est. The tests check each
one against central differences.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from companion.checks import FloatArray
from companion.geometry import so3

STATE_SIZE = 33
ERROR_SIZE = 21
NAV_ERROR_SIZE = 15

# Slices into the nominal state.
P_SL = slice(0, 3)
V_SL = slice(3, 6)
R_SL = slice(6, 15)
BG_SL = slice(15, 18)
BA_SL = slice(18, 21)
PC_SL = slice(21, 24)
RC_SL = slice(24, 33)

# Slices into the error state.
EP = slice(0, 3)
EV = slice(3, 6)
ETH = slice(6, 9)
EBG = slice(9, 12)
EBA = slice(12, 15)
EPC = slice(15, 18)
ETHC = slice(18, 21)
# The 6 error coordinates of the current pose (dp, dtheta) and of the clone.
POSE_IDX = np.array([0, 1, 2, 6, 7, 8])
CLONE_IDX = np.arange(15, 21)

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


def new_state(
    p_ned_m: FloatArray,
    v_ned_m_s: FloatArray,
    R_ned_body: FloatArray,
    b_gyro_rad_s: FloatArray,
    b_accel_m_s2: FloatArray,
) -> FloatArray:
    """A nominal state (33,) with the clone equal to the current pose."""
    x = np.empty(STATE_SIZE)
    x[P_SL] = p_ned_m
    x[V_SL] = v_ned_m_s
    x[R_SL] = np.asarray(R_ned_body).ravel()
    x[BG_SL] = b_gyro_rad_s
    x[BA_SL] = b_accel_m_s2
    x[PC_SL] = p_ned_m
    x[RC_SL] = x[R_SL]
    return x


def rotation(x: FloatArray) -> FloatArray:
    """R_ned_body (3, 3) view of the current attitude in state `x`."""
    return x[R_SL].reshape(3, 3)


def clone_rotation(x: FloatArray) -> FloatArray:
    """R_ned_body (3, 3) view of the cloned attitude in state `x`."""
    return x[RC_SL].reshape(3, 3)


def boxplus(x: FloatArray, dx: FloatArray) -> FloatArray:
    """x [+] dx: a new state with the error `dx` (21,) injected (right perturbation on attitudes)."""
    y = x.copy()
    inject_in_place(y, dx)
    return y


def inject_in_place(x: FloatArray, dx: FloatArray) -> None:
    """x <- x [+] dx for the filter's own state buffer (the only in-place writer besides propagation)."""
    x[P_SL] += dx[EP]
    x[V_SL] += dx[EV]
    x[R_SL] = (rotation(x) @ exp_and_right_jacobian(dx[6], dx[7], dx[8])[0]).ravel()
    x[BG_SL] += dx[EBG]
    x[BA_SL] += dx[EBA]
    x[PC_SL] += dx[EPC]
    x[RC_SL] = (clone_rotation(x) @ exp_and_right_jacobian(dx[18], dx[19], dx[20])[0]).ravel()


def boxminus(x1: FloatArray, x0: FloatArray) -> FloatArray:
    """x1 [-] x0: the error (21,) with x1 = x0 [+] dx."""
    dx = np.empty(ERROR_SIZE)
    dx[EP] = x1[P_SL] - x0[P_SL]
    dx[EV] = x1[V_SL] - x0[V_SL]
    dx[ETH] = so3.log(rotation(x0).T @ rotation(x1))
    dx[EBG] = x1[BG_SL] - x0[BG_SL]
    dx[EBA] = x1[BA_SL] - x0[BA_SL]
    dx[EPC] = x1[PC_SL] - x0[PC_SL]
    dx[ETHC] = so3.log(clone_rotation(x0).T @ clone_rotation(x1))
    return dx


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


def body_to_error_pose_covariance(R_ned_body: FloatArray, cov_body_6x6: FloatArray) -> FloatArray:
    """Map a right-perturbation pose covariance (body frame, twist (v, w)) to the filter's (dp_ned, dtheta).

    T_true = T exp(d) with d = (dv, dw) gives, to first order, dp_ned = R dv and
    dtheta = dw; the result is J cov J^T with J = blockdiag(R, I).
    """
    J = np.zeros((6, 6))
    J[:3, :3] = R_ned_body
    J[3:, 3:] = _I3
    out: FloatArray = J @ cov_body_6x6 @ J.T
    return out


def absolute_pose_residual(x: FloatArray, R_meas: FloatArray, p_meas: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Residual (6,) and Jacobian H (6, 21) of a measured pose T_ned_body = (R_meas, p_meas).

    With T_true = T_meas exp(d), d = (dv, dw) in the measured body frame:
    r = [R_meas^T (p_meas - p); log(R^T R_meas)] ~= [R_meas^T dp - dv; dtheta - dw],
    so the noise covariance is the measurement's right-perturbation covariance
    and the position rows do not depend on the estimated attitude.
    """
    R = rotation(x)
    r = np.empty(6)
    rth = log_so3(R.T @ R_meas)
    r[:3] = R_meas.T @ (p_meas - x[P_SL])
    r[3:] = rth
    H = np.zeros((6, ERROR_SIZE))
    H[0:3, EP] = R_meas.T
    H[3:6, ETH] = left_jacobian_inverse_so3(rth)
    return r, H


def _yaw_and_gradient(R: FloatArray) -> tuple[float, FloatArray]:
    """Yaw (rad, ZYX Euler) of R_ned_body and its gradient (3,) w.r.t. a right perturbation."""
    c2 = R[0, 0] * R[0, 0] + R[1, 0] * R[1, 0]
    c2 = max(c2, 1e-12)
    yaw = math.atan2(R[1, 0], R[0, 0])
    return yaw, np.array([0.0, R[2, 1] / c2, R[2, 2] / c2])


def wrap(angle_rad: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def relative_pose_residual(
    x: FloatArray, dx_m: float, dy_m: float, dyaw_rad: float
) -> tuple[FloatArray, FloatArray]:
    """Residual (3,) and Jacobian H (3, 21) of a planar increment between the clone and now.

    h(x) = [p_n - pc_n, p_e - pc_e, yaw(R) - yaw(R_clone)] (NED, rad); the yaw
    residual is wrapped to [-pi, pi).
    """
    yaw, g = _yaw_and_gradient(rotation(x))
    yaw_c, g_c = _yaw_and_gradient(clone_rotation(x))
    r = np.array(
        [
            dx_m - (x[0] - x[21]),
            dy_m - (x[1] - x[22]),
            wrap(dyaw_rad - (yaw - yaw_c)),
        ]
    )
    H = np.zeros((3, ERROR_SIZE))
    H[0, 0] = H[1, 1] = 1.0
    H[0, 15] = H[1, 16] = -1.0
    H[2, ETH] = g
    H[2, ETHC] = -g_c
    return r, H


def range_residual(x: FloatArray, range_m: float, ground_z_ned_m: float) -> tuple[FloatArray, FloatArray]:
    """Residual (1,) and Jacobian H (1, 21) of a downward rangefinder over flat ground.

    The rangefinder points along body +z (down); over a horizontal ground plane at
    z_ned = ground_z_ned_m it reads h(x) = (ground_z - p_z) / R[2, 2], the height
    divided by the cosine of the tilt.
    """
    R = rotation(x)
    c = R[2, 2]
    height = ground_z_ned_m - x[2]
    pred = height / c
    r = np.array([range_m - pred])
    H = np.zeros((1, ERROR_SIZE))
    H[0, 2] = -1.0 / c
    # d R22 under R exp(dtheta): (R hat(dtheta))[2, 2] = R[2, 0] dth_y - R[2, 1] dth_x.
    dpred_dc = -height / (c * c)
    H[0, 6] = dpred_dc * (-R[2, 1])
    H[0, 7] = dpred_dc * R[2, 0]
    return r, H


def euler_rate_matrix(R_ned_body: FloatArray) -> FloatArray:
    """E (3, 3) with d(roll, pitch, yaw) = E dtheta for a right (body-frame) attitude perturbation.

    Pitch is clamped away from +-90 deg so the matrix stays finite.
    """
    R = R_ned_body
    roll = math.atan2(R[2, 1], R[2, 2])
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    cp = max(math.cos(pitch), 1e-6)
    tp = math.sin(pitch) / cp
    sr, cr = math.sin(roll), math.cos(roll)
    return np.array([[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr / cp, cr / cp]])


def pose_covariance_xyz_rpy(R_ned_body: FloatArray, P_pose: FloatArray) -> FloatArray:
    """The MAVLink pose covariance (6, 6), order (x, y, z, roll, pitch, yaw), from the error-state (dp, dtheta)."""
    J = np.zeros((6, 6))
    J[:3, :3] = _I3
    J[3:, 3:] = euler_rate_matrix(R_ned_body)
    out: FloatArray = J @ P_pose @ J.T
    return 0.5 * (out + out.T)
