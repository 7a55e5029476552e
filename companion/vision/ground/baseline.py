"""A simple planar image-motion odometer, the comparison baseline of the benchmark.

GFTT corners tracked with pyramidal Lucas-Kanade, a similarity fitted by
`cv2.estimateAffinePartial2D` (RANSAC), its translation scaled by height / focal length; no
attitude compensation and no lens model (this is what the closed-form odometer improves on).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.geometry import frames


@dataclass(frozen=True)
class PlanarBaselineEstimate:
    """Accumulated NED pose of the baseline (metres, rad) and the tracked point count."""

    ok: bool
    x_m: float
    y_m: float
    yaw_rad: float
    num_tracked: int


class PlanarBaseline:
    """GFTT + Lucas-Kanade + similarity, translation scaled by height (default camera mount)."""

    def __init__(self, cam: PinholeCamera, T_body_cam: Any = None, max_corners: int = 300) -> None:
        self.cam = cam
        T = frames.default_T_body_cam() if T_body_cam is None else check_transform(T_body_cam, "T_body_cam")
        self._R_body_cam: FloatArray = T[:3, :3].copy()
        self._yaw_sign = 1.0 if self._R_body_cam[2, 2] >= 0 else -1.0
        self._max_corners = max_corners
        self._focal = 0.5 * (cam.fx + cam.fy)
        self.reset()

    def reset(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        self._x, self._y, self._yaw = float(x_m), float(y_m), float(yaw_rad)
        self._prev: np.ndarray[Any, Any] | None = None
        self._M: FloatArray = np.hstack([np.eye(2), np.zeros((2, 1))])

    def update(self, image: np.ndarray[Any, Any], height_m: float) -> PlanarBaselineEstimate:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        prev, self._prev = self._prev, gray
        if prev is None:
            return PlanarBaselineEstimate(True, self._x, self._y, self._yaw, 0)
        p0 = cv2.goodFeaturesToTrack(prev, self._max_corners, 0.01, 8)
        if p0 is None or len(p0) < 6:
            return PlanarBaselineEstimate(False, self._x, self._y, self._yaw, 0)
        # Constant-velocity guess: the previous frame's similarity applied again.
        guess = (p0.reshape(-1, 2) @ self._M[:, :2].T + self._M[:, 2]).astype(np.float32).reshape(-1, 1, 2)
        p1, status, _ = cv2.calcOpticalFlowPyrLK(
            prev, gray, p0, guess, winSize=(21, 21), maxLevel=3, flags=cv2.OPTFLOW_USE_INITIAL_FLOW
        )
        good = status.ravel() == 1
        if good.sum() < 6:
            return PlanarBaselineEstimate(False, self._x, self._y, self._yaw, int(good.sum()))
        M, _ = cv2.estimateAffinePartial2D(p0[good], p1[good], method=cv2.RANSAC, ransacReprojThreshold=2.0)
        if M is None:
            self._M = np.hstack([np.eye(2), np.zeros((2, 1))])
            return PlanarBaselineEstimate(False, self._x, self._y, self._yaw, int(good.sum()))
        self._M = M
        theta = math.atan2(M[1, 0], M[0, 0])
        # The ground point now under the image centre was at M^-1(c) in the previous frame.
        c = np.array([self.cam.cx, self.cam.cy])
        A, t = M[:, :2], M[:, 2]
        p_prev = np.linalg.solve(A, c - t)
        d_cam = np.array([*(p_prev - c) * height_m / self._focal, 0.0])
        d_body = self._R_body_cam @ d_cam
        cy, sy = math.cos(self._yaw), math.sin(self._yaw)
        self._x += cy * d_body[0] - sy * d_body[1]
        self._y += sy * d_body[0] + cy * d_body[1]
        self._yaw = float(frames.wrap_angle(self._yaw - self._yaw_sign * theta))
        return PlanarBaselineEstimate(True, self._x, self._y, self._yaw, int(good.sum()))
