"""Configuration of the downward ground odometer (all lengths in metres, angles in radians)."""

from __future__ import annotations

from dataclasses import dataclass

from companion.errors import ConfigError

DETECTORS = ("orb", "fast-orb", "gftt-orb", "sift", "akaze", "brisk")
SOLVERS = ("gen", "sma")
ROBUST = ("ransac", "mad", "none")


@dataclass(frozen=True)
class GroundOdometerConfig:
    """Switches and parameters of every stage of the odometer (paper Fig. 7).

    detector:        feature detector/descriptor pair, one of `DETECTORS`.
    solver:          closed form, "gen" (eq. 20, cos/sin separately) or "sma" (eq. 25, small angle).
    refine:          Levenberg-Marquardt refinement of (dx, dy, dyaw) (eq. 26).
    subpixel:        beyond the paper: refine each match to sub-pixel precision with one
                     Lucas-Kanade step from the detected position (ORB/FAST keypoints are integer
                     pixels; their rounding biases the increments by ~0.05 px per frame).
    estimate_tilt:   beyond the paper: the refinement also fits, as nuisance parameters with a
                     Gaussian prior (`attitude_std_rad`, `height_std_m`), the non-rigid warps that
                     roll/pitch and height input errors of both frames cause (see
                     `refine.refine_with_tilt`), so IMU attitude noise leaks less into dyaw.
                     Needs refine = True.
    estimate_tilt_bias: beyond the paper: with `estimate_tilt`, also track the slowly varying part of
                     the roll/pitch input error (first-order Gauss-Markov, `tilt_bias_std_rad`,
                     `tilt_bias_tau_s`) across frames with a small Kalman state (`tilt_bias`): it is
                     shared by both frames of every pair, weakly visible in one pair, and otherwise
                     leaks into the yaw and translation increments and accumulates.
    tilt_bias_std_rad: stationary standard deviation of that slow roll/pitch error (rad; 0.25 deg);
                     0 switches the bias estimate off (as estimate_tilt_bias = False).
    tilt_bias_tau_s: its correlation time (s).
    kalman:          constant-acceleration Kalman filter on the increments (eq. 27).
    keyframes:       beyond the paper: match each frame against a keyframe (not only the previous
                     frame) while at least `keyframe_min_inlier_fraction` of the keyframe's first
                     inlier count still matches and for at most `keyframe_max_frames` frames, so
                     per-frame noise does not accumulate between keyframes. EXPERIMENTAL: with IMU
                     attitude noise it diverged in bench/ground_loops.py (docs/ground.md); False =
                     the paper's frame-to-frame odometer.
    robust:          outlier rejection on ground-plane residuals: "ransac" (2-point rigid hypotheses),
                     "mad" (iterative median-absolute-deviation trimming) or "none".
    max_features:    features detected per frame.
    pyramid_levels:  pyramid levels of ORB-family detectors (ORB scale factor `pyramid_scale`);
                     1 by default: consecutive frames of a downward camera differ little in scale
                     and every level costs detection time.
    fast_threshold:  initial and largest FAST threshold (intensity levels) of orb / fast-orb; the
                     threshold adapts per frame down to `fast_threshold_min` when a frame yields
                     fewer than `max_features` features (low-contrast floors), and back up.
    ratio:           nearest / second-nearest descriptor distance ratio test (Lowe).
    max_speed_m_s:   horizontal speed the vehicle cannot exceed; matches implying more are dropped.
    max_yaw_rate_rad_s: same for the yaw rate.
    gate_margin_m:   slack added to the speed gate (ground metres).
    inlier_threshold_px: robust threshold on ground-plane residuals, expressed in image pixels
                     (converted to metres with height / focal length).
    min_inliers:     fewer inliers than this -> ok = False and the pose is held.
    min_inlier_ratio: fewer inliers / gated matches than this -> ok = False.
    ransac_hypotheses: number of 2-point hypotheses (vectorized).
    lm_iterations:   maximum LM iterations (paper: 5-10 are enough).
    kalman_accel_psd: white-jerk spectral density of the Kalman filter, x/y ((m/s^3)^2 / Hz).
    kalman_yaw_accel_psd: same for yaw ((rad/s^3)^2 / Hz).
    min_measurement_std_m / min_measurement_std_rad: floor of the increment standard deviations
                     fed to the Kalman filter.
    attitude_std_rad: standard deviation of the frame-to-frame (white) part of the roll/pitch input
                     error (IMU attitude error, default 0.5 deg).
                     A tilt error moves every ground point by about height * error, unevenly across
                     the image, so it widens the inlier threshold (+ 2 * height * std) and enters the
                     increment covariance (2 (height * std)^2 per axis: both frames' errors).
    feature_std_px:  standard deviation of a feature's image position (pixels), the data weight of the
                     tilt-aware refinement (with `estimate_tilt_bias`: of its first pass; the second
                     pass weighs each pair by the scatter of its own residuals, at least
                     `feature_std_min_px`).
    height_std_m:    standard deviation of the height input (rangefinder), for the covariance.
    seed:            seed of the RANSAC sampler (deterministic output).
    """

    detector: str = "orb"
    solver: str = "gen"
    refine: bool = True
    subpixel: bool = True
    estimate_tilt: bool = True
    estimate_tilt_bias: bool = True
    tilt_bias_std_rad: float = 0.0044
    tilt_bias_tau_s: float = 20.0
    kalman: bool = True
    keyframes: bool = False
    keyframe_min_inlier_fraction: float = 0.5
    keyframe_max_frames: int = 40
    robust: str = "ransac"
    max_features: int = 260
    pyramid_levels: int = 1
    pyramid_scale: float = 1.2
    fast_threshold: int = 40
    fast_threshold_min: int = 8
    ratio: float = 0.8
    max_speed_m_s: float = 3.0
    max_yaw_rate_rad_s: float = 2.0
    gate_margin_m: float = 0.02
    inlier_threshold_px: float = 2.0
    min_inliers: int = 12
    min_inlier_ratio: float = 0.2
    ransac_hypotheses: int = 48
    lm_iterations: int = 8
    kalman_accel_psd: float = 50.0
    kalman_yaw_accel_psd: float = 50.0
    min_measurement_std_m: float = 1e-4
    min_measurement_std_rad: float = 1e-4
    attitude_std_rad: float = 0.0087
    feature_std_px: float = 0.5
    feature_std_min_px: float = 0.05
    height_std_m: float = 0.01
    seed: int = 0

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise ConfigError(f"detector: expected one of {DETECTORS}, got {self.detector!r}")
        if self.solver not in SOLVERS:
            raise ConfigError(f"solver: expected one of {SOLVERS}, got {self.solver!r}")
        if self.robust not in ROBUST:
            raise ConfigError(f"robust: expected one of {ROBUST}, got {self.robust!r}")
        positive = {
            "max_features": self.max_features,
            "pyramid_levels": self.pyramid_levels,
            "max_speed_m_s": self.max_speed_m_s,
            "max_yaw_rate_rad_s": self.max_yaw_rate_rad_s,
            "inlier_threshold_px": self.inlier_threshold_px,
            "ransac_hypotheses": self.ransac_hypotheses,
            "lm_iterations": self.lm_iterations,
            "feature_std_px": self.feature_std_px,
            "feature_std_min_px": self.feature_std_min_px,
            "kalman_accel_psd": self.kalman_accel_psd,
            "kalman_yaw_accel_psd": self.kalman_yaw_accel_psd,
            "min_measurement_std_m": self.min_measurement_std_m,
            "min_measurement_std_rad": self.min_measurement_std_rad,
            "tilt_bias_tau_s": self.tilt_bias_tau_s,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ConfigError(f"{name}: must be positive, got {value}")
        if not 0.0 <= self.keyframe_min_inlier_fraction <= 1.0:
            raise ConfigError(
                f"keyframe_min_inlier_fraction: must be in [0, 1], got {self.keyframe_min_inlier_fraction}"
            )
        if self.keyframe_max_frames < 1:
            raise ConfigError(f"keyframe_max_frames: must be >= 1, got {self.keyframe_max_frames}")
        if not 0.0 < self.ratio <= 1.0:
            raise ConfigError(f"ratio: must be in (0, 1], got {self.ratio}")
        if not self.pyramid_scale > 1.0:
            raise ConfigError(f"pyramid_scale: must be > 1, got {self.pyramid_scale}")
        if self.attitude_std_rad < 0 or self.height_std_m < 0 or self.tilt_bias_std_rad < 0:
            raise ConfigError("attitude_std_rad / height_std_m / tilt_bias_std_rad: must be >= 0")
        if self.gate_margin_m < 0:
            raise ConfigError(f"gate_margin_m: must be >= 0, got {self.gate_margin_m}")
        if self.min_inliers < 3:
            raise ConfigError(f"min_inliers: must be >= 3 (three parameters), got {self.min_inliers}")
        if not 0.0 <= self.min_inlier_ratio <= 1.0:
            raise ConfigError(f"min_inlier_ratio: must be in [0, 1], got {self.min_inlier_ratio}")
        if not 0 < self.fast_threshold < 255:
            raise ConfigError(f"fast_threshold: must be in (0, 255), got {self.fast_threshold}")
        if not 0 < self.fast_threshold_min <= self.fast_threshold:
            raise ConfigError(f"fast_threshold_min: must be in (0, fast_threshold], got {self.fast_threshold_min}")
