"""Texture point detection: no points on plain, noisy cladding when a corner-strength floor is set."""

from __future__ import annotations

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import se3
from companion.vision.rack import RackModel
from companion.vision.rack.texture import detect_points

CAM = PinholeCamera(width=360, height=240, fx=315.0, fy=315.0, cx=180.0, cy=120.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def test_corner_floor_keeps_spots_and_drops_noise() -> None:
    model = RackModel.parallel(radii=[0.3], gaps=[], length=10.0)
    T = se3.make(R_DOWN, [0.3, 5.0, 2.0])  # above the pipe's axis: it fills the image's middle band
    rng = np.random.default_rng(0)
    plain = np.clip(170.0 + 6.0 * rng.standard_normal((240, 360)), 0, 255).astype(np.float32)
    spotted = plain.copy()
    spots = [(150, 80), (200, 160)]
    for u, v in spots:
        cv2.circle(spotted, (u, v), 6, 60.0, -1)
    poly = [np.array([[120.0, 10.0], [240.0, 10.0], [240.0, 230.0], [120.0, 230.0]])]

    def detect(img: np.ndarray, ratio: float) -> np.ndarray:
        gray = np.asarray(cv2.GaussianBlur(img, (0, 0), 0.7)).astype(np.uint8)
        args = (gray, T, CAM, model.pipe_arrays(), poly, np.zeros((0, 2)), 20, 10.0, 0.4)
        return detect_points(*args, min_corner_ratio=ratio)[2]

    # Relative quality alone: with no spot in view, noise corners fill the budget; the floor drops them.
    assert detect(plain, 0.0).shape[0] >= 10
    assert detect(plain, 10.0).shape[0] == 0
    uv = detect(spotted, 10.0)
    assert 1 <= uv.shape[0] <= 2 * len(spots)
    assert all(np.min(np.linalg.norm(np.array(spots) - q, axis=1)) < 9.0 for q in uv)
