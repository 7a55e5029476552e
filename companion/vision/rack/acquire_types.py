"""Rack acquisition: its inputs, tuning and results (frozen dataclasses).

Frames: `rack` (the paper's P, z up, pipes along +y), `cam` (OpenCV optical), `body` (FRD),
`ned`. `T_rack_cam` is the camera pose in the rack frame. Covariances are those of a right
perturbation in the camera frame, twist (v, w) in (m, rad), as `RackEstimate.covariance`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.geometry import frames


@dataclass(frozen=True)
class AcquisitionConfig:
    """Tuning of `acquire_rack` (pixels at full resolution, metres, radians).

    Lines: `line_scale` the image scale LSD and the edge profile run at; `min_segment_px` the
    shortest segment kept; `min_contrast` grey levels across a segment; `direction_tol_rad` how
    far a segment's plane may miss the pipe direction; `merge_px` segments closer than this (at
    the image centre) form one limb; `max_directions` pipe-direction candidates tried.
    Pairing (`acquire_match`): `match_px` how far an observed limb may lie from a predicted one;
    `min_limb_px` the shortest predicted limb counted; `alpha_std_rad` the attitude error about
    the pipe axis; `max_section_hypotheses` kept per direction. Sweep (`acquire_profile`):
    `profile_bin_px` the angle bin of the edge profile, `sweep_step_m` the lateral grid,
    `sweep_tol_px` how far a limb may lie from a profile bin, `max_swept_hypotheses` kept per
    direction. Verification (`acquire_verify`): at most `max_checked` proposals are checked,
    those whose profile score reaches `check_score_ratio` times the best's, one refinement
    iteration per entry of `check_ranges_px` (edge search ranges), and the contenders get the
    further iterations `polish_ranges_px`; on the iterations whose search range is at most
    `silhouette_range_px` (0 = never) each gradient-peak edge is moved to the silhouette of the fitted
    limb profile, as the tracker does (`edges.refine_silhouette`, kept at the peak where the fit's rms
    exceeds `silhouette_max_rms` of the profile's range): the peak of a shaded limb lies 1-2 px inside
    it; only with the camera at least `silhouette_min_height_m` above the rack's support plane (on the
    deck a limb's shading spans tens of pixels, beyond the fit's windows, and the fit chose a confident
    pose one pipe over), the peaks elsewhere; `samples_per_limb`, `edge_threshold`, `inlier_px` as the
    tracker's; `margin_px` the image border; `attitude_std_rad` the roll / pitch error and
    `edge_noise_px` the noise of one edge sample, which weigh the autopilot's tilt and height against
    the edges. Decision: a hypothesis is credible when at least `min_agree_fraction` of its limb
    samples agree, its residual is below `max_residual_px`, `min_pipes` pipes have both limbs in view
    with at least `min_pipe_agree` of each limb's samples agreeing (and a run of consecutive agreeing
    samples over at least `min_limb_run` of the limb), no pipe with both limbs in view has less than
    `missing_pipe_agree` of its samples agreeing, its height
    is within `height_gate_sigma` standard deviations of the measured one and its tilt within
    `tilt_gate_sigma` attitude standard deviations of the autopilot's; hypotheses further
    than `yaw_gate_sigma` standard deviations from a supplied heading are not proposed. The
    best is `confident` when its score reaches `min_score` (most of its limbs seen, and most of the
    image's pipe-like lines explained, or most of those over the rack's footprint: between its
    outermost limbs widened by `footprint_pitches` pipe pitches each side, if no other contender
    comes within `ambiguity_ratio` of it there), its height and tilt are within `confident_sigma`
    standard deviations of the autopilot's, and every other credible hypothesis (another pipe
    assignment or direction, or a pose more than `distinct_m` / `distinct_rad` away) scores at
    most `ambiguity_ratio` times its score, nor does any checked pose that failed credibility
    (a near miss of the truth is a reason for doubt, not a reason to trust the other).
    `covariance_inflation` as the tracker's.
    """

    line_scale: float = 0.4
    min_segment_px: float = 40.0
    min_contrast: float = 10.0
    direction_tol_rad: float = 0.04
    merge_px: float = 4.0
    max_directions: int = 2
    match_px: float = 8.0
    min_limb_px: float = 40.0
    alpha_std_rad: float = 0.0175
    max_section_hypotheses: int = 3
    profile_bin_px: float = 2.0
    sweep_step_m: float = 0.02
    sweep_tol_px: float = 4.0
    max_swept_hypotheses: int = 6
    check_ranges_px: tuple[int, ...] = (10, 5, 3)
    polish_ranges_px: tuple[int, ...] = (4, 3, 3, 3)
    silhouette_range_px: int = 3
    silhouette_max_rms: float = 0.08
    silhouette_min_height_m: float = 1.5
    samples_per_limb: int = 24
    edge_threshold: float = 8.0
    inlier_px: float = 1.5
    margin_px: float = 6.0
    max_checked: int = 4
    check_score_ratio: float = 0.5
    min_agree_fraction: float = 0.5
    min_score: float = 0.35
    footprint_pitches: float = 1.5
    max_residual_px: float = 1.0
    min_pipes: int = 2
    min_pipe_agree: float = 0.5
    missing_pipe_agree: float = 0.2
    min_limb_run: float = 0.5
    ambiguity_ratio: float = 0.8
    distinct_m: float = 0.05
    distinct_rad: float = 0.035
    yaw_gate_sigma: float = 3.0
    height_gate_sigma: float = 3.0
    tilt_gate_sigma: float = 3.0
    confident_sigma: float = 2.5
    attitude_std_rad: float = 0.0175
    edge_noise_px: float = 0.5
    covariance_inflation: float = 4.0

    def __post_init__(self) -> None:
        if not 0.1 <= self.line_scale <= 1.0:
            raise InputError(f"line_scale: must be in [0.1, 1], got {self.line_scale}")
        for name in ("min_segment_px", "direction_tol_rad", "merge_px", "match_px", "alpha_std_rad", "inlier_px",
                     "covariance_inflation", "yaw_gate_sigma"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name}: must be positive, got {getattr(self, name)}")
        for name in ("min_pipe_agree", "min_limb_run"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise InputError(f"{name}: must be in (0, 1], got {getattr(self, name)}")
        for name in ("profile_bin_px", "sweep_step_m", "sweep_tol_px"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name}: must be positive, got {getattr(self, name)}")
        for name in ("max_directions", "max_section_hypotheses", "samples_per_limb", "max_checked", "min_pipes",
                     "max_swept_hypotheses"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if int(self.silhouette_range_px) < 0:
            raise InputError(f"silhouette_range_px: must be >= 0 (0 = off), got {self.silhouette_range_px}")
        if not (np.isfinite(self.silhouette_max_rms) and self.silhouette_max_rms >= 0.0):
            raise InputError(f"silhouette_max_rms: must be >= 0 (0 = any fit), got {self.silhouette_max_rms}")
        if not np.isfinite(self.silhouette_min_height_m):
            raise InputError(f"silhouette_min_height_m: must be finite, got {self.silhouette_min_height_m}")
        if not self.check_ranges_px or min(self.check_ranges_px) < 1:
            raise InputError(f"check_ranges_px: expected ranges >= 1 px, got {self.check_ranges_px}")


def _finite(value: Any, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a number, got {value!r}") from exc
    if not np.isfinite(v):
        raise InputError(f"{name}: must be finite, got {v}")
    return v


@dataclass(frozen=True)
class AcquisitionPrior:
    """What is known without the image.

    `roll_rad`, `pitch_rad`: the autopilot's attitude (body FRD in NED, ZYX Euler); `height_m`:
    height of the camera's optical centre above the rack's support plane (rack z, m) with standard
    deviation `height_std_m` (rangefinder or baro minus the rack's elevation); `y_m`, `y_std_m`:
    the along-pipe position of the camera (rack y, m) from the filter, the mission start or the
    last lock, used when no crossing pipe is in view; `yaw_rad`, `yaw_std_rad`: optional heading
    (body in NED, rad) that rules out the opposite direction of travel when its error is well
    below 90 deg; `T_body_cam`, `T_ned_rack`: the mount and the rack alignment (4x4, None = the
    defaults of `companion.geometry.frames`).
    """

    roll_rad: float
    pitch_rad: float
    height_m: float
    height_std_m: float
    y_m: float = 0.0
    y_std_m: float = 3.0
    yaw_rad: float | None = None
    yaw_std_rad: float = 0.35
    T_body_cam: FloatArray | None = field(default=None, compare=False)
    T_ned_rack: FloatArray | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        for name in ("roll_rad", "pitch_rad", "height_m", "height_std_m", "y_m", "y_std_m", "yaw_std_rad"):
            object.__setattr__(self, name, _finite(getattr(self, name), name))
        for name in ("height_m", "height_std_m", "y_std_m", "yaw_std_rad"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name}: must be positive, got {getattr(self, name)}")
        if self.yaw_rad is not None:
            object.__setattr__(self, "yaw_rad", _finite(self.yaw_rad, "yaw_rad"))
        T_bc = frames.default_T_body_cam() if self.T_body_cam is None else check_transform(self.T_body_cam,
                                                                                           "T_body_cam")
        T_nr = frames.default_T_ned_rack() if self.T_ned_rack is None else check_transform(self.T_ned_rack,
                                                                                           "T_ned_rack")
        object.__setattr__(self, "T_body_cam", T_bc)
        object.__setattr__(self, "T_ned_rack", T_nr)

    def R_rack_cam(self, yaw_rad: float) -> FloatArray:
        """Camera orientation in the rack frame for this roll, pitch and the given yaw (rad)."""
        assert self.T_body_cam is not None and self.T_ned_rack is not None
        R_ned_body = frames.rotation_from_euler_zyx(self.roll_rad, self.pitch_rad, yaw_rad)
        return np.asarray(self.T_ned_rack[:3, :3].T @ R_ned_body @ self.T_body_cam[:3, :3])


@dataclass(frozen=True)
class RackHypothesis:
    """One candidate camera pose.

    `T_rack_cam` (4x4) camera in the rack frame; `covariance` (6x6) right perturbation in the
    camera frame, (v, w) in (m, rad); `score` in [0, 1]: the fraction of the predicted limb samples
    that agree times the fraction of the observed limb length the hypothesis explains; `pipes`
    the parallel pipes (0-based model indices) whose limbs agree, in image left-to-right order;
    `reversed` true when the camera's travel is along rack -y (image left-to-right is rack -x);
    `y_observed` true when y comes from a crossing pipe, false when it
    is the prior's (its variance is then the prior's); `residual_px` robust std of the agreeing
    edge residuals; `num_samples` limb samples predicted in view.
    """

    T_rack_cam: FloatArray
    covariance: FloatArray
    score: float
    pipes: tuple[int, ...]
    reversed: bool
    y_observed: bool
    residual_px: float
    num_samples: int


@dataclass(frozen=True)
class AcquisitionResult:
    """`hypotheses` ranked best first (credible ones only); `confident` true only when the best is
    unambiguous; `status` "" when confident, else why not; `num_segments` line segments found;
    `num_limbs` limbs found along the chosen pipe direction."""

    hypotheses: tuple[RackHypothesis, ...]
    confident: bool
    status: str
    num_segments: int
    num_limbs: int

    @property
    def best(self) -> RackHypothesis | None:
        return self.hypotheses[0] if self.hypotheses else None
