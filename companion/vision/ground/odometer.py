"""The downward ground visual odometer (Ortiz et al., Sec. 5, Fig. 7) in the project frames.

Per frame: detect features once; back-project them to the ground with the frame's height and
roll/pitch (`backproject`); match against the previous good frame (ratio test); drop matches
incompatible with the vehicle's speed; reject outliers on ground-plane residuals (RANSAC/MAD);
solve the closed form (GEN or SMA); refine with LM; smooth with the constant-acceleration Kalman
filter; accumulate the NED pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.geometry import frames
from companion.vision.ground import kalman, tilt_bias
from companion.vision.ground.backproject import level_camera, rays_from_pixels, rays_to_level
from companion.vision.ground.closed_form import gen_to_increment, solve_gen, solve_sma
from companion.vision.ground.config import GroundOdometerConfig
from companion.vision.ground.features import FeatureExtractor, Features
from companion.vision.ground.matching import Matcher, speed_gate
from companion.vision.ground.refine import (
    RefineResult,
    evaluate,
    refine,
    refine_tilt_exact,
    refine_with_tilt,
    tilt_fields,
)
from companion.vision.ground.robust import mad_trim, ransac_rigid, residual_norms

MAX_HEIGHT_M = 100.0
_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.01)
_LK_MAX_CORRECTION_PX = 2.0
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


class GroundOdometer:
    """Downward visual odometer: x, y, yaw in NED from a ground-looking camera.

    `cam`: the calibrated camera; `T_body_cam`: 4x4 with p_body = T_body_cam @ p_cam (None: the
    default mount of `frames.default_T_body_cam()`).
    """

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

    def _predicted(self, kf: kalman.KalmanState, stamp: float) -> kalman.KalmanState:
        """`kalman.predict(kf, stamp)`, cached for the last (state, stamp) pair."""
        cached = self._kf_pred
        if cached is not None and cached[0] is kf and cached[1] == stamp:
            return cached[2]
        pred = kalman.predict(kf, stamp, self._jerk_psd)
        self._kf_pred = (kf, stamp, pred)
        return pred

    def _relative(self, ref: _Anchor, cur: _Frame) -> tuple[RefineResult | None, int, int]:
        """Motion from `ref` to `cur` (NED-aligned with the ref's raw yaw), match and inlier counts."""
        i_prev, i_cur = self._matcher.match(ref.frame.features, cur.features)
        valid = ref.frame.valid[i_prev] & cur.valid[i_cur]
        if self.config.subpixel and i_prev.size > 0:
            q_b, valid_b, rays_b = self._subpixel(ref.frame, cur, i_prev, i_cur)
            valid &= valid_b
            q_b, rays_b = q_b[valid], rays_b[valid]
        else:
            i_cur_valid = i_cur[valid]
            q_b = cur.q_level_m[i_cur_valid]
            rays_b = cur.rays_level[i_cur_valid]
        i_prev_valid = i_prev[valid]
        dt = cur.stamp_s - ref.frame.stamp_s
        self._pending_tilt = None
        result, num_inliers = self._solve(
            ref.frame,
            cur,
            ref.frame.q_level_m[i_prev_valid],
            q_b,
            ref.frame.rays_level[i_prev_valid],
            rays_b,
            dt,
            ref.pose[2],
        )
        if num_inliers < self.config.min_inliers:
            result = None
        if result is None:
            self._pending_tilt = None
        return result, int(i_prev.size), num_inliers

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

    def _solve(
        self,
        ref: _Frame,
        cur: _Frame,
        q_a: FloatArray,
        q_b: FloatArray,
        rays_a: FloatArray,
        rays_b: FloatArray,
        dt: float,
        yaw_ref: float,
    ) -> tuple[RefineResult | None, int]:
        """Gate, reject outliers, solve and refine for matched level-frame ground points (and rays)."""
        cfg = self.config
        if q_a.shape[0] < cfg.min_inliers:
            return None, int(q_a.shape[0])
        c, s = math.cos(yaw_ref), math.sin(yaw_ref)
        R = np.array([[c, -s], [s, c]])
        a = q_a @ R.T
        b = q_b @ R.T

        # Speed gate, centred on the Kalman prediction when the filter is running.
        pred = np.zeros(3)
        if cfg.kalman and self._kf is not None and self._kf.P[0, 0, 0] < 1.0:
            pred = self._predicted(self._kf, cur.stamp_s).x @ np.array([dt, -0.5 * dt * dt])
        gate = speed_gate(
            a, b, pred[:2], float(pred[2]), cfg.max_speed_m_s * dt + cfg.gate_margin_m, cfg.max_yaw_rate_rad_s * dt
        )
        i_gated = np.flatnonzero(gate)
        a, b = a[i_gated], b[i_gated]
        n_gated = a.shape[0]
        if n_gated < cfg.min_inliers:
            return None, n_gated

        h_max = max(ref.height_m, cur.height_m)
        self._height_scale = h_max
        self._height_rel_std = (cfg.height_std_m / ref.height_m, cfg.height_std_m / cur.height_m)
        threshold_m = cfg.inlier_threshold_px * h_max / self._focal_px + 2.0 * cfg.attitude_std_rad * h_max
        if cfg.robust == "ransac":
            inl = ransac_rigid(a, b, threshold_m, cfg.ransac_hypotheses, self._rng)
        elif cfg.robust == "mad":
            inl = mad_trim(a, b, threshold_m)
        else:
            inl = np.ones(n_gated, dtype=bool)
        n_inl = int(np.count_nonzero(inl))
        if n_inl < cfg.min_inliers or n_inl < cfg.min_inlier_ratio * n_gated:
            return None, n_inl

        if cfg.robust != "none":
            # Re-select inliers around the least-squares motion of the consensus set (GEN, cheap).
            inl = residual_norms(a, b, gen_to_increment(solve_gen(a[inl], b[inl]))) <= threshold_m
            n_inl = int(np.count_nonzero(inl))
            if n_inl < cfg.min_inliers or n_inl < cfg.min_inlier_ratio * n_gated:
                return None, n_inl
        i_inl = np.flatnonzero(inl)
        a, b, i_src = a[i_inl], b[i_inl], i_gated[i_inl]
        result = self._fit(a, b, q_a[i_src], q_b[i_src], rays_a[i_src], rays_b[i_src], R, ref, cur)
        return self._with_input_noise(result, a, b, ref.height_m, cur.height_m), int(i_inl.size)

    def _with_input_noise(
        self, result: RefineResult, a: FloatArray, b: FloatArray, h0: float, h1: float
    ) -> RefineResult:
        """Add the attitude and height input errors to the increment covariance.

        A roll/pitch error e moves the ground points of its frame by about h e; both frames
        contribute. A relative height error scales the points about the camera nadir, which moves
        the fitted translation by the centroid times that error.
        """
        cfg = self.config
        att_var = (cfg.attitude_std_rad * h0) ** 2 + (cfg.attitude_std_rad * h1) ** 2
        # Means as sum / n (what ndarray.mean computes, without its Python overhead).
        ca, cb = a.sum(axis=0) / a.shape[0], b.sum(axis=0) / b.shape[0]
        h_var = (cfg.height_std_m / h0) ** 2 * float(ca @ ca) + (cfg.height_std_m / h1) ** 2 * float(cb @ cb)
        cov = result.covariance.copy()
        cov[0, 0] += att_var + h_var
        cov[1, 1] += att_var + h_var
        return RefineResult(result.increment, cov, result.rms_m, result.iterations)

    def _fit(
        self,
        a: FloatArray,
        b: FloatArray,
        q_a: FloatArray,
        q_b: FloatArray,
        rays_a: FloatArray,
        rays_b: FloatArray,
        R: FloatArray,
        ref: _Frame,
        cur: _Frame,
    ) -> RefineResult:
        """Closed form + refinement. `a`, `b`: NED-aligned points (level points `q_a`, `q_b` rotated
        by `R` = R(yaw_ref)); `rays_a`, `rays_b`: their level-frame rays (exact tilt model)."""
        cfg = self.config
        initial = gen_to_increment(solve_gen(a, b)) if cfg.solver == "gen" else solve_sma(a, b)
        if cfg.refine and cfg.estimate_tilt and cfg.estimate_tilt_bias and cfg.tilt_bias_std_rad > 0:
            data_std_m = cfg.feature_std_px * self._height_scale / self._focal_px
            z0, Pz = tilt_bias.pair_prior(
                self._tilt,
                ref.stamp_s,
                cur.stamp_s,
                cfg.tilt_bias_std_rad,
                cfg.tilt_bias_tau_s,
                cfg.attitude_std_rad,
                self._height_rel_std[0],
                self._height_rel_std[1],
            )
            # Solve in the reference frame's level frame (the rays' frame), rotate d back to NED.
            initial_level = np.array([*(R.T @ initial[:2]), initial[2]])

            # The bias evidence is weak per pair: after the first step each pair is weighed by its own
            # point scatter (blurred or badly matched frames scatter far more than the nominal
            # feature_std_px, sharp ones less), at least feature_std_min_px.
            out = refine_tilt_exact(
                rays_a,
                ref.height_m,
                ref.nadir_level_m,
                rays_b,
                cur.height_m,
                cur.nadir_level_m,
                initial_level,
                data_std_m,
                z0,
                Pz,
                tilt_bias.MAP_B,
                tilt_bias.MAP_A,
                cfg.lm_iterations,
                data_std_floor_m=cfg.feature_std_min_px * self._height_scale / self._focal_px,
            )
            self._pending_tilt = tilt_bias.state_after(out.nuisance_mean, out.nuisance_cov, cur.stamp_s)
            T = np.eye(3)
            T[:2, :2] = R
            res = out.result
            return RefineResult(T @ res.increment, T @ res.covariance @ T.T, res.rms_m, res.iterations)
        if cfg.refine and cfg.estimate_tilt:
            fields_b = tilt_fields(q_b, cur.nadir_level_m, cur.height_m) @ R.T
            fields_a = tilt_fields(q_a, ref.nadir_level_m, ref.height_m) @ R.T
            data_std_m = cfg.feature_std_px * self._height_scale / self._focal_px
            att = cfg.attitude_std_rad
            prior_std = np.array([att, att, self._height_rel_std[1], att, att, self._height_rel_std[0]])
            return refine_with_tilt(a, b, fields_b, fields_a, initial, data_std_m, prior_std, cfg.lm_iterations)
        if cfg.refine:
            return refine(a, b, initial, cfg.lm_iterations)
        return evaluate(a, b, initial)

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
