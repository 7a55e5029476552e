"""The ground odometer's state: the per-frame records (level-frame ground points and rays, metres), the
keyframe anchors with their raw NED poses, the reset and the cached Kalman prediction."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.geometry import frames
from companion.vision.ground import kalman, tilt_bias
from companion.vision.ground.config import GroundOdometerConfig
from companion.vision.ground.features import FeatureExtractor, Features
from companion.vision.ground.matching import Matcher


@dataclass(frozen=True)
class _Frame:
    features: Features
    q_level_m: FloatArray  # (N, 2) ground points in the frame's level frame
    valid: np.ndarray[Any, np.dtype[np.bool_]]
    stamp_s: float
    height_m: float
    nadir_level_m: FloatArray  # (2,) the camera centre's horizontal position in the level frame
    gray: np.ndarray[Any, Any]
    roll_rad: float
    pitch_rad: float
    rays_level: FloatArray  # (N, 3) the features' rays in the level frame at unit depth
    R_L_cam: FloatArray  # (3, 3) camera to level frame at this frame's roll/pitch


@dataclass(frozen=True)
class _Anchor:
    """A frame with its raw (unfiltered) NED pose (x, y, yaw); keyframe bookkeeping."""

    frame: _Frame
    pose: tuple[float, float, float]
    first_inliers: int
    age: int


def _check_scalar(value: Any, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a number, got {type(value).__name__}") from exc
    if not math.isfinite(v):
        raise InputError(f"{name}: must be finite, got {v}")
    return v


class GroundOdometerState:
    """State of a `GroundOdometer` (see `__init__`), the base of its frame-handling and pair-solve mixins."""

    def __init__(
        self,
        cam: PinholeCamera,
        config: GroundOdometerConfig | None = None,
        T_body_cam: Any = None,
    ) -> None:
        self.cam = cam
        self.config = config if config is not None else GroundOdometerConfig()
        self.T_body_cam = (
            frames.default_T_body_cam() if T_body_cam is None else check_transform(T_body_cam, "T_body_cam").copy()
        )
        self._extractor = FeatureExtractor(self.config)
        self._matcher = Matcher(self._extractor.binary, self.config.ratio)
        self._focal_px = 0.5 * (cam.fx + cam.fy)
        self._height_scale = 1.0
        self._height_rel_std = (0.01, 0.01)
        self._jerk_psd = np.array(
            [self.config.kalman_accel_psd, self.config.kalman_accel_psd, self.config.kalman_yaw_accel_psd]
        )
        cfg = self.config
        self._min_measurement_var = (
            np.array([cfg.min_measurement_std_m, cfg.min_measurement_std_m, cfg.min_measurement_std_rad]) ** 2
        )
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """Restart at the given NED pose; the next frame only initializes."""
        self._x = _check_scalar(x_m, "x_m")
        self._y = _check_scalar(y_m, "y_m")
        self._yaw = float(frames.wrap_angle(_check_scalar(yaw_rad, "yaw_rad")))
        self._raw = (self._x, self._y, self._yaw)  # unfiltered chain pose (keyframes hang on it)
        self._anchor: _Anchor | None = None  # current keyframe
        self._prev: _Anchor | None = None  # last good frame
        self._prev_rel_cov = np.zeros((3, 3))
        self._kf: kalman.KalmanState | None = None
        # The filter's prediction to a frame's stamp, computed once per frame (speed gate and update).
        self._kf_pred: tuple[kalman.KalmanState, float, kalman.KalmanState] | None = None
        self._tilt: tilt_bias.TiltState | None = None  # slow tilt bias + white errors of the last good frame
        self._pending_tilt: tilt_bias.TiltState | None = None
        self._last_stamp_s: float | None = None
        self._rng = np.random.default_rng(self.config.seed)
        self._extractor.reset()

    def _predicted(self, kf: kalman.KalmanState, stamp: float) -> kalman.KalmanState:
        """`kalman.predict(kf, stamp)`, cached for the last (state, stamp) pair."""
        cached = self._kf_pred
        if cached is not None and cached[0] is kf and cached[1] == stamp:
            return cached[2]
        pred = kalman.predict(kf, stamp, self._jerk_psd)
        self._kf_pred = (kf, stamp, pred)
        return pred
