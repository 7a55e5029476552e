"""Render a planar calibration board through a known `PinholeCamera` (with distortion), for tests.

Every output pixel is un-distorted to a ray (the camera's own model), intersected with the board
plane and looked up in the board's texture; 2x supersampling then an area downscale.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np

from companion.calibration_boards import BoardSpec
from companion.camera import PinholeCamera
from companion.geometry import so3

SUPERSAMPLE = 2


class BoardRenderer:
    """Images of `board` seen by `camera` at board poses `T_cam_board` (4x4, m)."""

    def __init__(self, board: BoardSpec, camera: PinholeCamera, px_per_square: int = 96) -> None:
        self.board = board
        self.camera = camera
        self.texture = board.image(px_per_square, margin_squares=1.0)
        self.m_per_px = board.square_m / px_per_square
        # texture pixel (centre convention) of the board origin, the first inner corner
        first = 2 * px_per_square if board.kind == "checkerboard" else px_per_square
        self.origin_px = first - 0.5
        if board.kind == "charuco":
            # OpenCV's ChArUco object points start at the board's outer corner (no inner offset):
            # the first inner corner is at (square, square) in the board frame
            self.origin_px = px_per_square - 0.5
        cam_ss = camera.scaled(SUPERSAMPLE)
        v, u = np.mgrid[0 : cam_ss.height, 0 : cam_ss.width]
        self.rays = cam_ss.unproject(np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64))
        self.shape_ss = (cam_ss.height, cam_ss.width)

    def render(self, T_cam_board: Any, rng: np.random.Generator, noise_gray: float = 1.0) -> np.ndarray:
        R = T_cam_board[:3, :3]
        t = T_cam_board[:3, 3]
        o_b = -R.T @ t
        d_b = self.rays @ R  # R^T ray for every ray
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -o_b[2] / d_b[:, 2]
        p = o_b[None, :] + s[:, None] * d_b
        map_x = (self.origin_px + p[:, 0] / self.m_per_px).astype(np.float32)
        map_y = (self.origin_px + p[:, 1] / self.m_per_px).astype(np.float32)
        bad = ~(s > 0)
        map_x[bad] = -1e4
        map_y[bad] = -1e4
        hi = cv2.remap(self.texture, map_x.reshape(self.shape_ss), map_y.reshape(self.shape_ss),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=150)
        lo = cv2.resize(hi, (self.camera.width, self.camera.height), interpolation=cv2.INTER_AREA)
        noisy = lo.astype(np.float64) + rng.normal(0.0, noise_gray, lo.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def random_poses(board: BoardSpec, camera: PinholeCamera, rng: np.random.Generator, count: int,
                 distance_m: tuple[float, float], max_tilt_deg: float = 40.0) -> Iterator[np.ndarray]:
    """`count` poses T_cam_board, tilted up to `max_tilt_deg`, with every board corner in the image."""
    corners = board.object_points()
    centre = corners.mean(axis=0)
    made = 0
    while made < count:
        tilt = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, size=2))
        spin = np.radians(rng.uniform(-25.0, 25.0))
        R = so3.exp(np.array([tilt[0], tilt[1], 0.0])) @ so3.exp(np.array([0.0, 0.0, spin]))
        z = rng.uniform(*distance_m)
        # aim the board centre at a random point of the image
        uv = np.array([rng.uniform(0.15, 0.85) * camera.width, rng.uniform(0.15, 0.85) * camera.height])
        ray = camera.unproject(uv)
        t = ray / ray[2] * z - R @ centre
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = t
        p_cam = corners @ R.T + t
        if np.any(p_cam[:, 2] < 0.05):
            continue
        uv_all = camera.project(p_cam)
        if not np.all(camera.in_image(uv_all, margin_px=12.0)):
            continue
        made += 1
        yield T
