"""Measurement models of the navigation filter: residual r and Jacobian H (r ~= H dx + noise) of each input.

Absolute pose T_ned_body (rack), planar NED increment (dx, dy in m, dyaw in rad) between the clone and
now (ground), downward slant range in m over flat ground (rangefinder).
"""

from __future__ import annotations

import math

import numpy as np

from companion.checks import FloatArray
from companion.estimation.model_so3 import left_jacobian_inverse_so3, log_so3
from companion.estimation.model_state import EP, ERROR_SIZE, ETH, ETHC, P_SL, clone_rotation, rotation


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
