"""The project's fixed frames and the conventions converted once, here.

Frames (see docs/CONVENTIONS.md):
    rack  pipes on z = 0, axes along +y, numbered with increasing x, z up
    cam   OpenCV optical: x right, y down, z forward
    body  FRD: x forward, y right, z down
    ned   autopilot local frame: x north, y east, z down

MAVLink quaternions are (w, x, y, z) and rotate body into NED (R_ned_body).
Euler angles are ZYX: R_ned_body = Rz(yaw) @ Ry(pitch) @ Rx(roll), radians.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from companion.checks import FloatArray, check_last_dim, check_last_two_dims
from companion.geometry import se3, so3

# Downward camera, image top toward the nose: x_cam = y_body, y_cam = -x_body, z_cam = z_body.
R_BODY_CAM_DEFAULT: FloatArray = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
# north = rack +y, east = rack +x, down = rack -z.
R_NED_RACK_DEFAULT: FloatArray = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# ENU <-> NED swaps x/y and flips z; the matrix is its own inverse.
R_ENU_NED: FloatArray = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def default_T_body_cam() -> FloatArray:
    """The default camera mount T_body_cam (camera at the body origin, looking down)."""
    return se3.make(R_BODY_CAM_DEFAULT, np.zeros(3))


def default_T_ned_rack() -> FloatArray:
    """The default rack-to-NED alignment T_ned_rack (origins coincide)."""
    return se3.make(R_NED_RACK_DEFAULT, np.zeros(3))


def ned_to_enu(p_ned: Any) -> FloatArray:
    """Vectors (..., 3) in NED to ENU."""
    return check_last_dim(p_ned, 3, "p_ned") @ R_ENU_NED.T


def enu_to_ned(p_enu: Any) -> FloatArray:
    """Vectors (..., 3) in ENU to NED."""
    return check_last_dim(p_enu, 3, "p_enu") @ R_ENU_NED.T


def rotation_from_quaternion_wxyz(q_wxyz: Any) -> FloatArray:
    """Rotation matrices (..., 3, 3) of MAVLink-order quaternions (w, x, y, z)."""
    return so3.matrix_from_quaternion(q_wxyz)


def quaternion_wxyz_from_rotation(R: Any) -> FloatArray:
    """MAVLink-order unit quaternions (w, x, y, z), w >= 0, of rotations (..., 3, 3)."""
    return so3.quaternion_from_matrix(R)


def rotation_from_euler_zyx(roll_rad: Any, pitch_rad: Any, yaw_rad: Any) -> FloatArray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (..., 3, 3): body FRD to NED for aircraft angles."""
    r = np.asarray(roll_rad, dtype=np.float64)
    p = np.asarray(pitch_rad, dtype=np.float64)
    y = np.asarray(yaw_rad, dtype=np.float64)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    shape = np.broadcast_shapes(r.shape, p.shape, y.shape)
    R = np.empty(shape + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def euler_zyx_from_rotation(R: Any) -> FloatArray:
    """(roll, pitch, yaw) rad (..., 3) with R = Rz(yaw) Ry(pitch) Rx(roll).

    pitch in [-pi/2, pi/2], roll and yaw in (-pi, pi]. At gimbal lock
    (|pitch| = pi/2) roll is set to 0 and yaw carries the whole rotation.
    """
    R = check_last_two_dims(R, 3, 3, "R")
    sp = np.clip(-R[..., 2, 0], -1.0, 1.0)
    pitch = np.arcsin(sp)
    # Use atan2 with the cos(pitch)-scaled entries: precise away from gimbal lock.
    cp = np.hypot(R[..., 0, 0], R[..., 1, 0])
    lock = cp < 1e-9
    roll = np.where(lock, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(lock, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    pitch = np.arctan2(sp, cp)
    return np.stack([roll, pitch, yaw], axis=-1)


def yaw_from_rotation(R: Any) -> FloatArray:
    """Heading (rad, about NED down) of body-to-NED rotations (..., 3, 3)."""
    return euler_zyx_from_rotation(R)[..., 2]


def wrap_angle(angle_rad: Any) -> FloatArray:
    """Angles wrapped to (-pi, pi]."""
    a = np.asarray(angle_rad, dtype=np.float64)
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def T_ned_body_from_T_rack_cam(T_rack_cam: Any, T_ned_rack: Any, T_body_cam: Any) -> FloatArray:
    """T_ned_body = T_ned_rack @ T_rack_cam @ inverse(T_body_cam)."""
    return check_last_two_dims(T_ned_rack, 4, 4, "T_ned_rack") @ check_last_two_dims(
        T_rack_cam, 4, 4, "T_rack_cam"
    ) @ se3.inverse(T_body_cam)


def T_rack_cam_from_T_ned_body(T_ned_body: Any, T_ned_rack: Any, T_body_cam: Any) -> FloatArray:
    """T_rack_cam = inverse(T_ned_rack) @ T_ned_body @ T_body_cam."""
    return se3.inverse(T_ned_rack) @ check_last_two_dims(T_ned_body, 4, 4, "T_ned_body") @ check_last_two_dims(
        T_body_cam, 4, 4, "T_body_cam"
    )
