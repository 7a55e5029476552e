"""Image features -> ground plane, in the gravity-aligned, yaw-free body frame (paper eqs. 1-11).

The paper writes the camera as a chain of Euler rotations with the optical axis on the vehicle's
z axis. Here the same ray-plane intersection is written in the project frames:

    level frame L: origin at the body origin, z along NED down, x/y = body forward/right rotated
                   by -roll/-pitch only (yaw-free), i.e. R_ned_L = Rz(yaw), R_L_body = Ry(pitch) Rx(roll)
    ray in L:      r_L = R_L_body R_body_cam r_cam  (r_cam: undistorted unit ray, OpenCV optical frame)
    ground point:  p_L = R_L_body t_body_cam + (h / r_L.z) r_L   with h = camera height above ground

so a ground point g (NED, horizontal) seen at time k satisfies g = t_k + R(yaw_k) q_k with
q_k = p_L[:2], which is the paper's eq. 11 with (alpha, beta) = q_k.
"""

from __future__ import annotations

import numpy as np

from companion.checks import FloatArray
from companion.geometry.frames import rotation_from_euler_zyx
from companion.vision.ground.matching import BoolArray

# Rays closer to the horizon than this (cosine of the angle to the vertical) are not used.
MIN_RAY_DOWN_COS = 0.1


def level_from_body(roll_rad: float, pitch_rad: float) -> FloatArray:
    """R_L_body = Ry(pitch) Rx(roll): body FRD to the yaw-free gravity-aligned frame."""
    R: FloatArray = rotation_from_euler_zyx(roll_rad, pitch_rad, 0.0)
    return R


def ground_points_level(
    rays_cam: FloatArray,
    height_m: float,
    roll_rad: float,
    pitch_rad: float,
    T_body_cam: FloatArray,
) -> tuple[FloatArray, BoolArray]:
    """Horizontal ground points q (N, 2) in the level frame L (metres, relative to the body origin).

    `rays_cam` (N, 3): rays in the camera frame (any positive scale). `height_m`: height of the
    camera's optical centre above the ground. Returns q and a mask of rays that hit the ground in
    front of the camera (q is NaN elsewhere).
    """
    rays_L, offset, valid = ground_rays_level(rays_cam, roll_rad, pitch_rad, T_body_cam)
    q = rays_L[:, :2] * height_m + offset
    return q, valid


def ground_rays_level(
    rays_cam: FloatArray, roll_rad: float, pitch_rad: float, T_body_cam: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Rays in the level frame L scaled to unit depth along down (N, 3), (x/z, y/z, 1); the camera
    centre's horizontal offset from the body origin in L (2,), metres; and the mask of rays that
    hit the ground in front of the camera (NaN rays elsewhere). The ground point at camera height h
    is offset + h * ray[:2] (`ground_points_level`)."""
    R_L_cam, offset = level_camera(roll_rad, pitch_rad, T_body_cam)
    rays_L, valid = rays_to_level(rays_cam, R_L_cam)
    return rays_L, offset, valid


def level_camera(roll_rad: float, pitch_rad: float, T_body_cam: FloatArray) -> tuple[FloatArray, FloatArray]:
    """R_L_cam (3, 3), camera to level frame, and the camera centre's horizontal offset from the
    body origin in L (2,), metres: the per-frame part of `ground_rays_level` (compute once per frame)."""
    R_L_body = level_from_body(roll_rad, pitch_rad)
    R_L_cam: FloatArray = R_L_body @ T_body_cam[:3, :3]
    offset: FloatArray = (R_L_body @ T_body_cam[:3, 3])[:2]
    return R_L_cam, offset


def rays_to_level(rays_cam: FloatArray, R_L_cam: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Camera rays (N, 3) -> level-frame rays at unit depth (N, 3) and the ground-hit mask, for the
    rotation of `level_camera` (`ground_rays_level` without the per-frame part)."""
    r_L = rays_cam @ R_L_cam.T
    norm = np.sqrt(np.einsum("ij,ij->i", r_L, r_L))
    valid: BoolArray = r_L[:, 2] > MIN_RAY_DOWN_COS * norm
    scale = np.where(valid, 1.0 / np.where(valid, r_L[:, 2], 1.0), np.nan)
    rays_L: FloatArray = r_L * scale[:, None]
    return rays_L, valid


def rays_from_pixels(fx: float, fy: float, cx: float, cy: float, skew: float, uv_px: FloatArray) -> FloatArray:
    """Rays (N, 3) (x/z, y/z, 1) of pixels for a camera without distortion (fast path)."""
    out = np.empty((uv_px.shape[0], 3))
    y = (uv_px[:, 1] - cy) / fy
    out[:, 0] = (uv_px[:, 0] - cx - skew * y) / fx
    out[:, 1] = y
    out[:, 2] = 1.0
    return out
