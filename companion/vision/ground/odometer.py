"""The downward ground visual odometer (Ortiz et al., Sec. 5, Fig. 7) in the project frames.

Per frame: detect features once; back-project them to the ground with the frame's height and
roll/pitch (`backproject`); match against the previous good frame (ratio test); drop matches
incompatible with the vehicle's speed; reject outliers on ground-plane residuals (RANSAC/MAD);
solve the closed form (GEN or SMA); refine with LM; smooth with the constant-acceleration Kalman
filter; accumulate the NED pose.

`GroundOdometer` is assembled from `odometer_state` (the state, the frame records, the reset),
`odometer_frames` (image to level-frame ground points) and `odometer_solve` (the motion between two
frames); this module keeps the main entry `update` (keyframes, Kalman filter, NED pose) and the output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError
from companion.geometry import frames
from companion.vision.ground import kalman
from companion.vision.ground.odometer_solve import GroundOdometerSolve
from companion.vision.ground.odometer_state import _Anchor, _check_scalar

MAX_HEIGHT_M = 100.0
MAX_TILT_RAD = math.radians(60.0)


@dataclass(frozen=True)
class GroundEstimate:
    """Output of one `GroundOdometer.update`.

    ok:            the frame was used (first frame: True, zero increment); False -> pose held,
                   zero increment, covariance zeros (ignore it).
    x_m, y_m:      accumulated body position in NED (north, east), metres.
    yaw_rad:       accumulated heading about NED down, (-pi, pi].
    dx_m, dy_m, dyaw_rad: the increment applied at this frame (NED metres, rad).
    covariance:    (3, 3) covariance of (dx_m, dy_m, dyaw_rad) in NED (m^2, m rad, rad^2): from the
                   LM normal matrix scaled by the residual variance, and after the Kalman filter
                   when it is enabled (then it is the filter's posterior of the increment).
    num_matches:   matches passing the ratio test; num_inliers: matches supporting the motion.
    stamp_s:       the frame's time; dt_s: the time spanned by the increment (0 on the first frame).
    rms_residual_m: RMS ground-plane residual of the inliers, metres.
    """

    ok: bool
    x_m: float
    y_m: float
    yaw_rad: float
    dx_m: float
    dy_m: float
    dyaw_rad: float
    covariance: FloatArray
    num_matches: int
    num_inliers: int
    stamp_s: float = 0.0
    dt_s: float = 0.0
    rms_residual_m: float = 0.0


class GroundOdometer(GroundOdometerSolve):
    """Downward visual odometer: x, y, yaw in NED from a ground-looking camera.

    `cam`: the calibrated camera; `T_body_cam`: 4x4 with p_body = T_body_cam @ p_cam (None: the
    default mount of `frames.default_T_body_cam()`).
    """

    @property
    def tilt_bias_rad(self) -> tuple[float, float]:
        """Current estimate of the slow roll/pitch input bias (roll, pitch), rad, small-angle:
        the measured attitude minus the true one (zero until estimated; `estimate_tilt_bias`)."""
        if self._tilt is None:
            return (0.0, 0.0)
        # The refinement corrects measured points by + coefficient * field: roll error -> -field 0
        # coefficient, pitch error -> +field 1 (tilt_fields), so the correction is their negative.
        beta = self._tilt.bias_rad
        return (float(beta[0]), -float(beta[1]))

    # ------------------------------------------------------------------ main entry
    def update(self, image: Any, stamp_s: float, height_m: float, roll_rad: float, pitch_rad: float) -> GroundEstimate:
        """Process one frame taken at `stamp_s` (s) with the camera `height_m` above the ground
        and body `roll_rad`, `pitch_rad` (R_ned_body = Rz(yaw) Ry(pitch) Rx(roll))."""
        stamp = _check_scalar(stamp_s, "stamp_s")
        h = _check_scalar(height_m, "height_m")
        roll = _check_scalar(roll_rad, "roll_rad")
        pitch = _check_scalar(pitch_rad, "pitch_rad")
        if not 0.0 < h <= MAX_HEIGHT_M:
            raise InputError(f"height_m: must be in (0, {MAX_HEIGHT_M}] m, got {h}")
        if abs(roll) > MAX_TILT_RAD:
            raise InputError(f"roll_rad: |roll| must be <= 60 deg, got {math.degrees(roll):.1f} deg")
        if abs(pitch) > MAX_TILT_RAD:
            raise InputError(f"pitch_rad: |pitch| must be <= 60 deg, got {math.degrees(pitch):.1f} deg")
        if self._last_stamp_s is not None and not stamp > self._last_stamp_s:
            raise InputError(f"stamp_s: must increase, got {stamp} after {self._last_stamp_s}")
        gray = self._gray(image)
        self._last_stamp_s = stamp

        feats = self._extractor.extract(gray)
        frame = self._backproject(gray, feats, stamp, h, roll, pitch)
        cfg = self.config
        if self._anchor is None or self._prev is None:
            self._anchor = self._prev = _Anchor(frame, self._raw, 0, 0)
            self._prev_rel_cov = np.zeros((3, 3))
            self._kf = kalman.initial_state(stamp)
            return self._estimate(True, np.zeros(3), np.zeros((3, 3)), 0, 0, stamp, 0.0, 0.0)

        anchor, prev = self._anchor, self._prev
        result, num_matches, num_inliers = self._relative(anchor, frame)
        used = anchor
        if result is None and prev is not anchor:
            # The keyframe went stale: fall back to the previous good frame.
            result, num_matches, num_inliers = self._relative(prev, frame)
            used = prev
        if result is None:
            # Keep a reference that still has texture: a blank or blurred frame must not replace it.
            if feats.count >= cfg.min_inliers:
                self._anchor = self._prev = _Anchor(frame, self._raw, 0, 0)
                self._prev_rel_cov = np.zeros((3, 3))
            return self._estimate(False, np.zeros(3), np.zeros((3, 3)), num_matches, num_inliers, stamp, 0.0, 0.0)

        if self._pending_tilt is not None:
            self._tilt = self._pending_tilt
        rel = result.increment
        raw_new = (used.pose[0] + float(rel[0]), used.pose[1] + float(rel[1]), used.pose[2] + float(rel[2]))
        increment = np.array(
            [raw_new[0] - self._raw[0], raw_new[1] - self._raw[1], math.remainder(raw_new[2] - self._raw[2], math.tau)]
        )
        # Increment = rel(k) - rel(k-1) when both hang on the same keyframe: bound its covariance by the sum.
        covariance = result.covariance + (self._prev_rel_cov if used is anchor else 0.0)
        dt = stamp - prev.frame.stamp_s
        if cfg.kalman:
            assert self._kf is not None
            var = np.maximum(np.diag(covariance), self._min_measurement_var)
            kf = kalman.update(self._predicted(self._kf, stamp), increment, var, dt)
            self._kf = kf
            increment, inc_var = kalman.increment_of(kf, dt)
            covariance = np.diag(inc_var)
        self._x += float(increment[0])
        self._y += float(increment[1])
        self._yaw = float(frames.wrap_angle(self._yaw + float(increment[2])))
        self._raw = raw_new

        # Keyframe policy: keep matching against the keyframe while it still shares enough inliers.
        age = used.age + 1
        first = used.first_inliers if used.first_inliers > 0 else num_inliers
        keep = (
            cfg.keyframes
            and used is anchor
            and age < cfg.keyframe_max_frames
            and num_inliers >= cfg.keyframe_min_inlier_fraction * first
        )
        current = _Anchor(frame, raw_new, 0, 0)
        if keep:
            self._anchor = _Anchor(anchor.frame, anchor.pose, first, age)
            self._prev_rel_cov = result.covariance
        else:
            self._anchor = current
            self._prev_rel_cov = np.zeros((3, 3))
        self._prev = current
        return self._estimate(True, increment, covariance, num_matches, num_inliers, stamp, dt, result.rms_m)

    def _estimate(
        self,
        ok: bool,
        increment: FloatArray,
        covariance: FloatArray,
        num_matches: int,
        num_inliers: int,
        stamp: float,
        dt: float,
        rms: float,
    ) -> GroundEstimate:
        return GroundEstimate(
            ok=ok,
            x_m=self._x,
            y_m=self._y,
            yaw_rad=self._yaw,
            dx_m=float(increment[0]),
            dy_m=float(increment[1]),
            dyaw_rad=float(increment[2]),
            covariance=np.array(covariance, dtype=np.float64),
            num_matches=num_matches,
            num_inliers=num_inliers,
            stamp_s=stamp,
            dt_s=dt,
            rms_residual_m=rms,
        )
