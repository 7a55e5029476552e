"""The ground odometer's frame handling: image checks, pixels to rays, back-projection of the features to
level-frame ground points (metres) and sub-pixel refinement of the matches."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError
from companion.vision.ground.backproject import level_camera, rays_from_pixels, rays_to_level
from companion.vision.ground.features import Features
from companion.vision.ground.odometer_state import GroundOdometerState, _Frame

_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.01)
_LK_MAX_CORRECTION_PX = 2.0


class GroundOdometerFrames(GroundOdometerState):
    """Frame handling of a `GroundOdometer`: from an image and its height and roll/pitch to a `_Frame`."""

    # ------------------------------------------------------------------ input checks
    def _gray(self, image: Any) -> np.ndarray[Any, Any]:
        if not isinstance(image, np.ndarray):
            raise InputError(f"image: expected a numpy array, got {type(image).__name__}")
        if image.dtype != np.uint8:
            raise InputError(f"image: expected dtype uint8, got {image.dtype}")
        if image.ndim == 3 and image.shape[2] == 3:
            gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        elif image.ndim == 2:
            gray = image
        else:
            raise InputError(f"image: expected shape (H, W) or (H, W, 3), got {image.shape}")
        if gray.shape != (self.cam.height, self.cam.width):
            raise InputError(
                f"image: size {gray.shape[1]}x{gray.shape[0]} does not match the camera "
                f"{self.cam.width}x{self.cam.height}"
            )
        return gray

    # ------------------------------------------------------------------ stages
    def _rays(self, uv: FloatArray) -> FloatArray:
        cam = self.cam
        if uv.shape[0] == 0:
            return np.zeros((0, 3))
        if cam.has_distortion:
            rays: FloatArray = cam.unproject(uv)
            return rays
        return rays_from_pixels(cam.fx, cam.fy, cam.cx, cam.cy, cam.skew, uv)

    def _backproject(
        self, gray: np.ndarray[Any, Any], feats: Features, stamp: float, h: float, roll: float, pitch: float
    ) -> _Frame:
        R_L_cam, nadir = level_camera(roll, pitch, self.T_body_cam)
        rays_L, valid = rays_to_level(self._rays(feats.uv_px), R_L_cam)
        q = rays_L[:, :2] * h + nadir
        return _Frame(feats, q, valid, stamp, h, nadir, gray, roll, pitch, rays_L, R_L_cam)

    def _subpixel(
        self,
        ref: _Frame,
        cur: _Frame,
        i_prev: np.ndarray[Any, np.dtype[np.intp]],
        i_cur: np.ndarray[Any, np.dtype[np.intp]],
    ) -> tuple[FloatArray, np.ndarray[Any, np.dtype[np.bool_]], FloatArray]:
        """Sub-pixel positions of the matches in `cur`: one Lucas-Kanade step from the detected
        position, tracking the reference keypoint's patch (detectors like ORB/FAST report integer
        pixels, whose rounding biases the increments). Returns their ground points, validity and
        level-frame rays."""
        uv_ref = ref.features.uv_px[i_prev].astype(np.float32).reshape(-1, 1, 2)
        uv0 = cur.features.uv_px[i_cur].astype(np.float32).reshape(-1, 1, 2)
        uv1, status, _ = cv2.calcOpticalFlowPyrLK(
            ref.gray,
            cur.gray,
            uv_ref,
            uv0.copy(),
            winSize=(9, 9),
            maxLevel=0,
            criteria=_LK_CRITERIA,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        uv = uv1.reshape(-1, 2).astype(np.float64)
        moved = np.abs(uv - uv0.reshape(-1, 2)).max(axis=1)
        good = (status.ravel() == 1) & (moved < _LK_MAX_CORRECTION_PX)
        uv = np.where(good[:, None], uv, uv0.reshape(-1, 2))
        rays_L, valid = rays_to_level(self._rays(uv), cur.R_L_cam)
        return rays_L[:, :2] * cur.height_m + cur.nadir_level_m, valid, rays_L
