"""Rack acquisition: the camera pose over a pipe-rack from one image, without a start pose.

`acquire_rack(image, model, camera, prior)` finds straight edges (LSD), the pipes' direction
(vote under the autopilot's roll and pitch), pairs limbs into pipes by the width the model
predicts at the measured height, matches any subset of the model's parallel pipes in either
direction of travel (`acquire_match`), refines and scores every hypothesis with the tracker's own
edge measurement (`acquire_verify`), takes the along-pipe position y from a crossing pipe when
one is in view and from the prior otherwise, and returns the ranked hypotheses. `confident` is
true only when the best one is unambiguous: a wrong lock is worse than no lock.

Frames: `rack` (the paper's P, z up, pipes along +y), `cam` (OpenCV optical), `body` (FRD),
`ned`. `T_rack_cam` is the camera pose in the rack frame. Covariances are those of a right
perturbation in the camera frame, twist (v, w) in (m, rad), as `RackEstimate.covariance`.
Pure: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.geometry import frames, se3
from companion.vision.rack.acquire_lines import (
    detect_segments,
    direction_candidates,
    image_theta_range,
    limb_clusters,
    refine_direction,
    visible_length_px,
)
from companion.vision.rack.acquire_match import SectionHypothesis, section_hypotheses
from companion.vision.rack.acquire_verify import (
    EdgeCheck,
    check_pose,
    crossing_y_candidates,
    pose_covariance,
    subset_pipes,
)
from companion.vision.rack.model import RackModel


@dataclass(frozen=True)
class AcquisitionConfig:
    """Tuning of `acquire_rack` (pixels at full resolution, metres, radians).

    Lines: `line_scale` image scale LSD runs at; `min_segment_px` shortest segment kept;
    `min_contrast` grey levels across a segment; `direction_tol_rad` how far a segment's plane
    may miss the pipe direction; `merge_px` segments closer than this (at the image centre) form
    one limb; `max_directions` pipe-direction candidates tried. Matching: `match_px` how far an
    observed limb may lie from a predicted one; `min_limb_px` shortest predicted limb counted;
    `alpha_std_rad` the attitude error about the pipe axis; `max_section_hypotheses` kept per
    direction. Verification: `check_ranges_px` the edge search ranges of the refinement
    iterations; `samples_per_limb`, `edge_threshold`, `inlier_px` as the tracker's; `margin_px`
    image border; at most `max_checked` hypotheses are checked, those whose line score reaches
    `check_score_ratio` times the best's. Decision: a hypothesis is `credible` when at
    least `min_agree_fraction` of its limb samples agree, its residual is below
    `max_residual_px` and `min_pipes` pipes have at least `min_pipe_agree` of their samples
    agreeing; the best is `confident` when it is credible and every other credible hypothesis
    (another pipe assignment or direction, or a pose more than `distinct_m` / `distinct_rad`
    away) scores at most `ambiguity_ratio` times its score. `yaw_gate_sigma`: hypotheses further
    than this many yaw standard deviations from a supplied heading are dropped.
    `attitude_std_rad`: the roll / pitch error, which holds the refined tilt against
    `edge_noise_px`, the noise of one edge sample.
    `covariance_inflation` as the tracker's.
    """

    line_scale: float = 0.5
    min_segment_px: float = 40.0
    min_contrast: float = 10.0
    direction_tol_rad: float = 0.04
    merge_px: float = 4.0
    max_directions: int = 2
    match_px: float = 8.0
    min_limb_px: float = 40.0
    alpha_std_rad: float = 0.0175
    max_section_hypotheses: int = 6
    check_ranges_px: tuple[int, ...] = (10, 5, 3)
    samples_per_limb: int = 24
    edge_threshold: float = 8.0
    inlier_px: float = 1.5
    margin_px: float = 6.0
    max_checked: int = 5
    check_score_ratio: float = 0.5
    min_agree_fraction: float = 0.6
    max_residual_px: float = 1.2
    min_pipes: int = 2
    min_pipe_agree: float = 0.5
    ambiguity_ratio: float = 0.8
    distinct_m: float = 0.05
    distinct_rad: float = 0.035
    yaw_gate_sigma: float = 3.0
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
        for name in ("max_directions", "max_section_hypotheses", "samples_per_limb", "max_checked", "min_pipes"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
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


def _gray(image: Any, camera: PinholeCamera) -> np.ndarray[Any, np.dtype[np.uint8]]:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise InputError(f"image: expected uint8, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] in (1, 3):
        img = img[:, :, 0] if img.shape[2] == 1 else (img @ np.array([0.114, 0.587, 0.299])).astype(np.uint8)
    if img.ndim != 2:
        raise InputError(f"image: expected (H, W) or (H, W, 3), got {img.shape}")
    if img.shape != (camera.height, camera.width):
        raise InputError(f"image: size {img.shape[1]}x{img.shape[0]} does not match the camera "
                         f"{camera.width}x{camera.height}")
    return np.ascontiguousarray(img)


def _pose_from_section(h: SectionHypothesis, d_cam: FloatArray, e_x: FloatArray, e_z: FloatArray,
                       y_m: float) -> FloatArray:
    """T_rack_cam from a cross-section hypothesis: rack axes in the camera frame, camera at (x, y, z)."""
    ca, sa = np.cos(h.alpha_rad), np.sin(h.alpha_rad)
    ex = ca * e_x + sa * e_z
    ez = -sa * e_x + ca * e_z
    R_cam_rack = np.column_stack([h.sign * ex, h.sign * d_cam, ez])
    U, _, Vt = np.linalg.svd(R_cam_rack)
    return se3.make((U @ Vt).T, np.array([h.x_m, y_m, h.z_m]))


def acquire_rack(
    image: Any, model: RackModel, camera: PinholeCamera, prior: AcquisitionPrior,
    config: AcquisitionConfig | None = None,
) -> AcquisitionResult:
    """Camera pose hypotheses over `model` from one `image` ((H, W) uint8 gray or (H, W, 3) BGR)."""
    if not isinstance(model, RackModel):
        raise InputError(f"model: expected RackModel, got {type(model).__name__}")
    if not isinstance(prior, AcquisitionPrior):
        raise InputError(f"prior: expected AcquisitionPrior, got {type(prior).__name__}")
    cfg = config or AcquisitionConfig()
    gray = _gray(image, camera)
    f_px = float(np.sqrt(camera.fx * camera.fy))
    seg = detect_segments(gray, camera, cfg.line_scale, cfg.min_segment_px, cfg.min_contrast)
    R0 = prior.R_rack_cam(0.0 if prior.yaw_rad is None else prior.yaw_rad)
    up_cam = R0[2, :]  # rack +z in the camera frame (independent of yaw for a level rack)
    pipes_all = model.pipe_arrays()
    n_par = model.num_parallel
    par = subset_pipes(pipes_all, np.arange(n_par))
    x_axes, radii = par.starts[:, 0], par.radii
    img_f = gray.astype(np.float32)
    cand: list[tuple[SectionHypothesis, FloatArray]] = []
    num_limbs = 0
    for d0 in direction_candidates(seg, up_cam, np.deg2rad(1.0), cfg.max_directions, np.deg2rad(15.0)):
        d, inl = refine_direction(seg, d0, up_cam, cfg.direction_tol_rad)
        limbs = limb_clusters(seg, inl, d, up_cam, camera, cfg.merge_px / f_px)
        num_limbs = max(num_limbs, int(limbs.theta.size))
        if limbs.theta.size < 2:
            continue
        signs: tuple[int, ...] = (1, -1)
        if prior.yaw_rad is not None:
            # Keep the direction(s) of travel within the gate of the heading.
            y_cam_prior = R0[1, :]  # rack +y in the camera frame at the prior heading
            ang = float(np.arccos(np.clip(abs(d @ y_cam_prior) / np.linalg.norm(d[:3]), -1.0, 1.0)))
            ok_sign = 1 if d @ y_cam_prior >= 0 else -1
            gate = cfg.yaw_gate_sigma * prior.yaw_std_rad
            if ang > gate:
                continue
            signs = (ok_sign,) if gate < np.pi / 2 else (1, -1)
        th_range = image_theta_range(camera, limbs)
        # Visible limb length as a function of the angle, tabulated once per direction.
        grid = np.linspace(th_range[0], th_range[1], 181)
        table = visible_length_px(camera, limbs, grid)
        hyps = section_hypotheses(
            limbs, x_axes, radii, prior.height_m, prior.height_std_m, signs, th_range,
            lambda th, g=grid, t=table: np.interp(th, g, t), cfg.match_px / f_px, cfg.min_limb_px,
            cfg.alpha_std_rad, cfg.max_section_hypotheses, cfg.distinct_m,
        )
        cand.extend((h, _pose_from_section(h, d, limbs.e_x, limbs.e_z, prior.y_m)) for h in hyps)
    if not cand:
        return AcquisitionResult((), False, "no pipe pattern found", int(seg.length_px.size), num_limbs)
    cand.sort(key=lambda c: -c[0].score)
    damping = np.array([1.0 / 0.05**2] * 3 + [1.0 / 0.02**2] * 3)
    # The autopilot's tilt against the edges: edge rows count 1 / (edge_noise² × inflation) each.
    up_weight = cfg.covariance_inflation * (cfg.edge_noise_px / cfg.attitude_std_rad) ** 2
    checked: list[tuple[SectionHypothesis, EdgeCheck]] = []
    top = cand[0][0].score
    for h, T in cand[: cfg.max_checked]:
        if h.score < cfg.check_score_ratio * top:
            break
        # Tracker polarity: +1 when the intensity increases outward from the pipe.
        chk = check_pose(img_f, camera, par, T, np.full(n_par, -float(h.polarity)), cfg.check_ranges_px,
                         cfg.samples_per_limb, cfg.edge_threshold, cfg.inlier_px, cfg.margin_px, damping,
                         up_cam, up_weight)
        checked.append((h, chk))
    hyps_out = [_finish(h, chk, seg, img_f, camera, pipes_all, n_par, prior, cfg, damping, up_cam, up_weight)
                for h, chk in checked if _credible(chk, cfg)]
    hyps_out.sort(key=lambda x: -x.score)
    hyps_out = _distinct(hyps_out, cfg)
    if not hyps_out:
        return AcquisitionResult((), False, "no hypothesis agrees with the image edges", int(seg.length_px.size),
                                 num_limbs)
    best = hyps_out[0]
    status = ""
    if len(hyps_out) > 1 and hyps_out[1].score > cfg.ambiguity_ratio * best.score:
        status = f"ambiguous: {len(hyps_out)} hypotheses score alike"
    return AcquisitionResult(tuple(hyps_out), status == "", status, int(seg.length_px.size), num_limbs)


def _credible(chk: EdgeCheck, cfg: AcquisitionConfig) -> bool:
    per_pipe = chk.pipe_agree / np.maximum(chk.pipe_samples, 1.0)
    good_pipes = int(np.count_nonzero((per_pipe >= cfg.min_pipe_agree) & (chk.pipe_samples >= cfg.samples_per_limb)))
    return (chk.agree_fraction >= cfg.min_agree_fraction and chk.residual_px <= cfg.max_residual_px
            and good_pipes >= cfg.min_pipes)


def _distinct(hyps: list[RackHypothesis], cfg: AcquisitionConfig) -> list[RackHypothesis]:
    """Drop hypotheses that are the same pose as a better one (same assignment, close pose)."""
    out: list[RackHypothesis] = []
    for h in hyps:
        same = False
        for b in out:
            dT = se3.inverse(b.T_rack_cam) @ h.T_rack_cam
            rot = float(np.linalg.norm(se3.log(dT)[3:]))
            d_rack = h.T_rack_cam[:3, 3] - b.T_rack_cam[:3, 3]
            dx = float(np.hypot(d_rack[0], d_rack[2]))
            if h.reversed == b.reversed and dx < cfg.distinct_m and rot < cfg.distinct_rad:
                same = True
                break
        if not same:
            out.append(h)
    return out


def _finish(
    h: SectionHypothesis, chk: EdgeCheck, seg: Any, img_f: Any, camera: PinholeCamera, pipes_all: Any, n_par: int,
    prior: AcquisitionPrior, cfg: AcquisitionConfig, damping: FloatArray, up_cam: FloatArray, up_weight: float,
) -> RackHypothesis:
    """Along-pipe y (crossing pipe or prior), covariance and the public hypothesis."""
    T = chk.T_rack_cam.copy()
    T[1, 3] = prior.y_m
    final = chk
    y_observed = False
    n_all = pipes_all.radii.size
    if n_all > n_par:
        span = 4.0 * prior.y_std_m
        ys = crossing_y_candidates(seg, T, pipes_all, np.arange(n_par, n_all), prior.y_m - span, prior.y_m + span,
                                   cfg.direction_tol_rad, 0.03, 3)
        passed: list[tuple[float, EdgeCheck]] = []
        for y in ys:
            Ty = T.copy()
            Ty[1, 3] = y
            pol = np.zeros(n_all)
            pol[:n_par] = -float(h.polarity)
            c = check_pose(img_f, camera, pipes_all, Ty, pol, cfg.check_ranges_px,
                           cfg.samples_per_limb, cfg.edge_threshold, cfg.inlier_px, cfg.margin_px, damping,
                           up_cam, up_weight)
            # Both limbs of a crossing pipe must agree: one limb alone fits many positions.
            ls, la = c.limb_samples[2 * n_par:], c.limb_agree[2 * n_par:]
            seen = ls >= cfg.samples_per_limb / 2
            limb_ok = seen & (la >= cfg.min_pipe_agree * ls)
            if np.count_nonzero(limb_ok) >= 2 and np.all(limb_ok[seen]):
                passed.append((float(np.min(la[seen] / ls[seen])), c))
        passed.sort(key=lambda pc: -pc[0])
        # Two different positions that both fit leave y unobserved.
        if passed and (len(passed) == 1 or passed[1][0] < cfg.ambiguity_ratio * passed[0][0]):
            final, y_observed = passed[0][1], True
        if not y_observed:
            T = chk.T_rack_cam.copy()
            T[1, 3] = prior.y_m
    T_out = final.T_rack_cam if y_observed else T
    cov = pose_covariance(final, cfg.covariance_inflation, None if y_observed else prior.y_std_m,
                          np.full(6, 1e-6))
    T_ro = np.array(T_out, copy=True)
    T_ro.flags.writeable = False
    cov.flags.writeable = False
    per_pipe = chk.pipe_agree[:n_par] / np.maximum(chk.pipe_samples[:n_par], 1.0)
    good = np.flatnonzero((per_pipe >= cfg.min_pipe_agree) & (chk.pipe_samples[:n_par] >= cfg.samples_per_limb))
    ordered = tuple(int(m) for m in (good[::-1] if h.sign < 0 else good))
    return RackHypothesis(T_rack_cam=T_ro, covariance=cov, score=chk.agree_fraction * h.coverage, pipes=ordered,
                          reversed=h.sign < 0, y_observed=y_observed, residual_px=chk.residual_px,
                          num_samples=chk.num_samples)
