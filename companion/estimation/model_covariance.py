"""Pose covariance conversions of the navigation filter (6, 6): body-frame twist (v, w) to the error
state's (dp_ned, dtheta), and error state to MAVLink's (x, y, z, roll, pitch, yaw).
"""

from __future__ import annotations

import math

import numpy as np

from companion.checks import FloatArray
from companion.estimation.model_so3 import _I3


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
