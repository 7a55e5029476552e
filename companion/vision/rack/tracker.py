"""Model-based SE(3) tracker of a camera over a pipe-rack (Lippiello & Cacace, section III).

Per frame: predict the pose (constant velocity), track the texture points (Lucas-Kanade seeded
by their predicted projection, refined against each point's reference patch warped into the
current view so that the tracks do not drift), then iterate: render the visible limbs from the current
estimate (eq. 10-14), search the image edge along each sample's normal, stack the normal
components of the generators' motion fields (eq. 8-9, 15) for the edges and the full image
motion for the texture points, add the gap parameters' fields (eq. 23-26), solve the IRLS
normal equations (eq. 16-18, 27-29) with a weak prior that damps unobservable directions, and
update the pose through the exponential map (not its linear approximation). Health checks
decide `ok`; the covariance comes from the final normal matrix and the residual scale.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError, TrackingError
from companion.geometry import se3
from companion.vision.rack.edges import refine_silhouette, search_edges
from companion.vision.rack.gap_scan import scan_gaps
from companion.vision.rack.ground import (
    detect_ground_points,
    ground_mask,
    ground_rows,
    on_ground,
    pipe_silhouettes,
    plane_points,
)
from companion.vision.rack.limbs import LimbSamples, occluded, sample_limbs
from companion.vision.rack.model import PipeArrays, RackModel
from companion.vision.rack.motion import (
    gap_jacobian,
    gravity_rows,
    information_condition,
    median_1d,
    pose_jacobian,
    robust_weights,
    solve_normal_equations,
)
from companion.vision.rack.templates import align_templates, sample_patches, tangent_plane_warps
from companion.vision.rack.texture import TextureMap, detect_points, track_points

_ROBUST_KINDS = ("paper", "tukey", "l2")


@dataclass(frozen=True)
class RackTrackerConfig:
    """Tuning of `RackTracker` (pixels, metres, radians).

    Edges: `samples_per_limb` image-uniform samples per visible limb; `search_range_px` the
    half-length of the normal search while tracking; on the first frame after `reset` it starts
    at `init_search_range_m` at the limbs' median depth (widened to three standard deviations of
    the reset prior, and to `init_search_range_gaps_m` when the gaps are estimated; at most
    `init_search_range_px`) and
    shrinks by `init_shrink` per iteration over up to `init_iterations` (coarse to fine, on an
    image blurred in proportion); `gap_scan` (with `estimate_gaps`): on the first frame after
    `reset`, each pipe's shift within `init_search_range_gaps_m` is found first by its limb pair
    (`gap_scan.scan_gaps`), and the first search then covers `init_search_range_m` only; `edge_threshold`
    the minimum |I(k+1) - I(k-1)| (grey levels); `edge_profile_px` the length of each limb's
    learned inner edge profile that candidates are matched against (`search_edges`, 0 = off),
    `edge_profile_rate` its per-frame learning rate; `edge_silhouette_px` > 0 moves each found
    edge from its gradient peak to the silhouette of a fitted limb profile (`refine_silhouette`,
    that many px inside, one fewer outside; 0 = off) where the fit's rms residual is within
    `edge_silhouette_max_rms` of the profile's range (elsewhere the peak is kept: a grating or a
    beam next to the limb, which the limb model does not describe); `ground_points` the number of ground corners
    tracked frame to frame as a second reference (plane z = z_g, height estimated online; see
    `ground.py`; 0 = off), `ground_weight` their rows' weight relative to edge rows,
    `ground_along_only` lets them inform only the translation along the pipes (and z_g): the limbs
    alone then fix roll against sideways slide, which a frame-to-frame constraint can only hold
    (with a wrong z_g, bend) but never correct,
    `ground_min_corner_ratio` their corner-strength floor, `ground_height_walk_m` the per-frame
    random walk allowed to z_g; `edge_tangent_px` > 0 averages each
    profile with two parallel ones that far along the limb (texture next to a straight limb
    averages out); `blur_sigma_px` an optional Gaussian pre-blur;
    `polarity_rate` the per-frame learning rate of each limb's edge polarity; `margin_px`
    image border kept free; `occlusion_margin_px` how far samples keep from occluding pipes.
    Estimation: `robust` "paper" (s = 1/(ν + |e|), eq. 29), "tukey" or "l2"; `nu_px` the
    paper's ν; `gate_px` residuals beyond this are dropped after the first iteration;
    `max_iterations` / `min_iterations` per frame, stopping when the update is below
    `stop_translation_m` / `stop_rotation_rad` or moves the rendered edges by less than
    `stop_px` (median); `prior_*` the standard deviations of the per-iteration damping (a weak
    prior on the motion that holds unobservable directions); `reset_prior_*` the standard
    deviations of the pose given to `reset` (a prior on the first frame; raise them, e.g. to
    0.1 m / 0.05 rad, when the reset pose is rough) and `motion_prior_*`
    those of the constant-velocity prediction (a prior on every later frame): both only matter
    in weakly observed directions; after `relock_after_frames` consecutive rejected frames (0 =
    never) the wide first-frame search runs again from the last pose, with `relock_prior_*` in
    place of the reset prior (not with `estimate_gaps`); `estimate_gaps` solves the cumulative gaps too;
    `estimate_edge_bias` solves two slowly varying offsets (px, along the outward normal) of the
    measured edges, one per limb side, that absorb the systematic shift of gradient-peak edges
    next to shaded limbs (changing by about `edge_bias_rate_px` per frame);
    `velocity_prediction` enables the constant-velocity prediction; `unobserved_velocity_tau_s`
    (s, 0 = off) on frames where nothing observes the translation along the pipes (fewer than
    three texture and ground points) that component of the velocity is not taken from the pose
    change (which there is only the prediction itself, so an error would persist and integrate)
    but decays from its last value with this time constant. `prior_rate_noise_rad`: the
    per-frame random walk between the vision's attitude and the filtered attitude prior.
    Texture: `max_texture_points` (0 disables), `texture_weight` relative to edge rows,
    `detect_every` frames between detections, `lk_window_px`, `lk_levels`,
    `texture_max_residual_px` drop threshold, `texture_refine_obs` the number of observations
    a point's 3-D position is averaged over (1 = keep the position from the first sighting),
    `texture_min_distance_px`, `texture_min_incidence_cos` (no grazing points),
    `texture_min_corner_ratio` (corner strength over the pipes' median: no points on noise, 0 = off);
    `texture_templates` refines every Lucas-Kanade result by aligning the point's reference
    patch (from the image it was found in), warped into the current view through the pipe's
    tangent plane, with a (2 `template_half_px` + 1)^2 window and `template_iterations`
    Gauss-Newton steps: frame-to-frame tracking alone drifts by pixels within seconds;
    points whose aligned patch correlates below `template_min_ncc` are dropped.
    Health: `min_edge_points` agreeing samples, `min_inlier_fraction`, `max_residual_px`
    robust residual std, `max_condition` of the normalised information matrix, `inlier_px`
    agreement threshold; `covariance_inflation` multiplies the covariance (edge samples along
    one limb are correlated).
    """

    samples_per_limb: int = 32
    search_range_px: int = 12
    init_search_range_px: int = 128
    init_search_range_m: float = 0.04
    init_search_range_gaps_m: float = 0.25
    gap_scan: bool = True
    init_iterations: int = 16
    init_shrink: float = 0.8
    edge_threshold: float = 8.0
    edge_profile_px: int = 8
    edge_silhouette_px: int = 6
    edge_silhouette_max_rms: float = 0.08
    ground_points: int = 60
    ground_weight: float = 1.0
    ground_along_only: bool = False
    ground_min_corner_ratio: float = 0.0
    ground_height_walk_m: float = 0.002
    edge_profile_rate: float = 0.1
    edge_tangent_px: float = 0.0
    blur_sigma_px: float = 0.0
    polarity_rate: float = 0.1
    margin_px: float = 6.0
    occlusion_margin_px: float = 3.0
    robust: str = "paper"
    nu_px: float = 1.0
    gate_px: float = 4.0
    max_iterations: int = 3
    min_iterations: int = 2
    stop_translation_m: float = 5e-4
    stop_rotation_rad: float = 3e-4
    stop_px: float = 0.15
    prior_translation_m: float = 0.05
    prior_rotation_rad: float = 0.02
    prior_gap_m: float = 0.05
    reset_prior_translation_m: float = 0.01
    prior_rate_noise_rad: float = 1e-3
    reset_prior_rotation_rad: float = 0.002
    motion_prior_translation_m: float = 0.03
    motion_prior_rotation_rad: float = 0.01
    relock_after_frames: int = 3
    relock_prior_translation_m: float = 0.1
    relock_prior_rotation_rad: float = 0.02
    estimate_gaps: bool = False
    estimate_edge_bias: bool = True
    edge_bias_rate_px: float = 0.02
    velocity_prediction: bool = True
    unobserved_velocity_tau_s: float = 0.3
    max_texture_points: int = 50
    texture_weight: float = 2.0
    detect_every: int = 4
    lk_window_px: int = 11
    lk_levels: int = 2
    texture_max_residual_px: float = 2.5
    texture_refine_obs: int = 20
    texture_min_distance_px: float = 12.0
    texture_min_incidence_cos: float = 0.4
    texture_min_corner_ratio: float = 10.0
    texture_templates: bool = True
    template_half_px: int = 5
    template_iterations: int = 2
    template_min_ncc: float = 0.5
    min_edge_points: int = 20
    min_inlier_fraction: float = 0.35
    max_residual_px: float = 3.0
    max_condition: float = 1e7
    inlier_px: float = 2.0
    covariance_inflation: float = 4.0

    def __post_init__(self) -> None:
        if self.robust not in _ROBUST_KINDS:
            raise InputError(f"robust: expected one of {_ROBUST_KINDS}, got {self.robust!r}")
        for name in ("samples_per_limb", "search_range_px", "init_search_range_px", "max_iterations",
                     "init_iterations", "detect_every", "lk_window_px", "template_half_px", "template_iterations"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if self.relock_after_frames < 0:
            raise InputError(f"relock_after_frames: must be >= 0, got {self.relock_after_frames}")
        if self.max_texture_points < 0:
            raise InputError(f"max_texture_points: must be >= 0, got {self.max_texture_points}")
        if not -1.0 <= self.template_min_ncc <= 1.0:
            raise InputError(f"template_min_ncc: must be in [-1, 1], got {self.template_min_ncc}")
        for name in ("nu_px", "gate_px", "prior_translation_m", "prior_rotation_rad", "prior_gap_m", "inlier_px",
                     "relock_prior_translation_m", "relock_prior_rotation_rad"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name}: must be positive, got {getattr(self, name)}")


@dataclass(frozen=True)
class RackEstimate:
    """Result of `RackTracker.track` for one frame.

    `T_rack_cam` (4x4): camera (OpenCV optical frame) pose in the rack frame; the best pose even
    when `ok` is false (then it is the motion prediction). `covariance` (6x6): covariance of the
    pose error as a RIGHT perturbation in the camera frame, twist order (v, w) (m, rad):
    T_true = T_rack_cam @ se3.exp(delta), delta ~ N(0, covariance). `gaps` (n-1,): cumulative
    gaps d̄_1..d̄_{n-1} (m) in use (estimated when `estimate_gaps`), `gaps_std_m` their standard
    deviations (0 when not estimated). `num_edge_points`: edge samples that agree with the final
    pose (|residual| <= inlier_px); `num_edge_samples`: samples searched; `num_texture_points`:
    texture points used; `residual_px`: robust standard deviation of the final edge residuals;
    `iterations`: solver iterations; `status`: "" when ok, else the reason; `condition`: the
    condition number of the normalised information matrix; `edge_bias_px`: the estimated edge
    offsets of the two limb sides (px, along the outward normal).
    """

    stamp_s: float
    ok: bool
    T_rack_cam: FloatArray
    covariance: FloatArray
    gaps: FloatArray
    gaps_std_m: FloatArray
    num_edge_points: int
    num_edge_samples: int
    num_texture_points: int
    residual_px: float
    iterations: int
    status: str = ""
    condition: float = 0.0
    edge_bias_px: FloatArray = field(default_factory=lambda: np.zeros(2))


def _positive(value: float | None, name: str, default: float) -> float:
    """`value` as a positive finite float, or `default` for None; InputError naming `name` otherwise."""
    if value is None:
        return default
    v = float(value)
    if not (np.isfinite(v) and v > 0.0):
        raise InputError(f"{name}: must be positive, got {value}")
    return v


def _readonly(a: FloatArray) -> FloatArray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.flags.writeable = False
    return a


class RackTracker:
    """Stateful tracker; call `reset(T_rack_cam)` then `track(image, stamp_s)` for each frame."""

    def __init__(self, model: RackModel, camera: PinholeCamera, config: RackTrackerConfig | None = None) -> None:
        if not isinstance(model, RackModel):
            raise InputError(f"model: expected RackModel, got {type(model).__name__}")
        if not isinstance(camera, PinholeCamera):
            raise InputError(f"camera: expected PinholeCamera, got {type(camera).__name__}")
        self.model = model
        self.camera = camera
        self.config = config or RackTrackerConfig()
        n_limbs = 2 * model.num_pipes
        self._n_gaps = model.num_parallel - 1
        self._T: FloatArray | None = None
        self._gaps = model.cumulative_gaps.copy()
        self._edge_bias = np.zeros(2)
        self._polarity = np.zeros(n_limbs)
        self._polarity_known = np.zeros(n_limbs, dtype=bool)
        # Learned inner edge profile of each limb (zero rows: none yet); see `search_edges`.
        self._profiles = np.zeros((n_limbs, self.config.edge_profile_px))
        self._texture = TextureMap.empty(self._ref_patch_size())
        self._prev_gray: np.ndarray[Any, np.dtype[np.uint8]] | None = None
        self._velocity = np.zeros(6)
        self._last_stamp: float | None = None
        self._frames = 0
        self._initialized = False
        # Standard deviations (m, rad) of the pose the wide first-frame search starts from: the reset
        # pose's (`reset_prior_*` or the caller's), or the re-lock prior's after rejected frames.
        self._start_std = (self.config.reset_prior_translation_m, self.config.reset_prior_rotation_rad)
        self._lost_frames = 0
        self._gaps_scanned = False  # this frame's gaps come from `scan_gaps` (the first search stays narrow)
        self._since_detect = 0
        self._detect_short = False
        self._pipes_key: bytes | None = None
        self._pipes_cached: PipeArrays | None = None
        self._weights_cache: dict[tuple[bool, int, tuple[float, float]], tuple[FloatArray, FloatArray]] = {}
        self._stale_ref = np.zeros(0, dtype=bool)
        # Weighted residual variance of the last accepted frame (px^2 in the IRLS weights' units):
        # converts an attitude prior's standard deviation into the solver's information scale.
        self._scale2 = 0.5
        self._gravity: tuple[FloatArray, float] | None = None
        # Filtered gravity ("up") of the attitude priors, carried in the rack frame through the
        # estimated attitude (see `_fuse_gravity`), and its variance (rad^2).
        self._up_rack: FloatArray | None = None
        self._up_var = 0.0
        self._reset_ground()

    # ------------------------------------------------------------------ public API
    def reset(
        self, T_rack_cam: Any, cumulative_gaps: Any = None, position_std_m: float | None = None,
        rotation_std_rad: float | None = None,
    ) -> None:
        """Re-initialize at pose `T_rack_cam` (4x4, camera in rack frame); forget texture and polarity.

        `position_std_m` / `rotation_std_rad`: how far off that pose may be (1 sigma, m / rad; default
        the config's `reset_prior_*`); they set the first frame's prior and its search range.
        """
        self._T = check_transform(T_rack_cam, "T_rack_cam").copy()
        cfg = self.config
        self._start_std = (_positive(position_std_m, "position_std_m", cfg.reset_prior_translation_m),
                           _positive(rotation_std_rad, "rotation_std_rad", cfg.reset_prior_rotation_rad))
        self._lost_frames = 0
        if cumulative_gaps is not None:
            g = np.asarray(cumulative_gaps, dtype=np.float64).ravel()
            if g.size != self._n_gaps:
                raise InputError(f"cumulative_gaps: expected {self._n_gaps} values, got {g.size}")
            self._gaps = g.copy()
        else:
            self._gaps = self.model.cumulative_gaps.copy()
        self._edge_bias = np.zeros(2)
        self._scale2 = 0.5
        self._up_rack = None
        self._reset_ground()
        self._polarity[:] = 0.0
        self._polarity_known[:] = False
        self._profiles[:] = 0.0
        self._texture = TextureMap.empty(self._ref_patch_size())
        self._prev_gray = None
        self._velocity = np.zeros(6)
        self._last_stamp = None
        self._frames = 0
        self._initialized = False
        self._since_detect = 0
        self._detect_short = False

    @property
    def T_rack_cam(self) -> FloatArray:
        if self._T is None:
            raise TrackingError("RackTracker: call reset(T_rack_cam) before track()")
        return self._T.copy()

    def track(
        self, image: Any, stamp_s: float, R_prior: Any = None, R_prior_std_rad: float | None = None
    ) -> RackEstimate:
        """Track one frame: `image` (H, W) uint8 gray or (H, W, 3) uint8 BGR, `stamp_s` capture time (s).

        Optional attitude prior: `R_prior` (3x3) an estimate of R_rack_cam (e.g. the autopilot's
        attitude brought into the rack frame) and `R_prior_std_rad` its tilt error (rad, 1 sigma).
        Only its gravity direction is used (two tilt angles, not the heading); without it the
        tracker is vision only.
        """
        if self._T is None:
            raise TrackingError("RackTracker: call reset(T_rack_cam) before track()")
        gray = self._as_gray(image)
        prior = self._check_prior(R_prior, R_prior_std_rad)
        cfg = self.config
        cam = self.camera
        img_raw = gray.astype(np.float32)
        if cfg.blur_sigma_px > 0:
            k = 2 * int(np.ceil(2.5 * cfg.blur_sigma_px)) + 1
            img_f = cv2.GaussianBlur(gray, (k, k), cfg.blur_sigma_px).astype(np.float32)
        else:
            img_f = img_raw
        first = not self._initialized  # wide, coarse-to-fine search until a frame is accepted
        # ---- prediction
        T = self._T.copy()
        if cfg.velocity_prediction and self._last_stamp is not None:
            dt = float(stamp_s) - self._last_stamp
            if 0.0 < dt <= 0.5:
                T = T @ se3.exp_one(self._velocity * dt)
        T_pred = T.copy()
        self._gravity = None if prior is None else self._fuse_gravity(prior[0], prior[1], T_pred)
        gaps = self._gaps.copy()
        self._gaps_scanned = False
        if first and cfg.estimate_gaps and cfg.gap_scan and self._frames == 0 and gaps.size:
            gaps = scan_gaps(T, cam, self._pipe_arrays(gaps), gaps, img_raw, cfg.init_search_range_gaps_m).gaps
            self._gaps_scanned = True
        pipes = self._pipe_arrays(gaps)
        # ---- texture points: LK from the previous image, seeded by the predicted projection
        tex_uv = np.zeros((0, 2))
        tex_ok = np.zeros(0, dtype=bool)
        if len(self._texture) and self._prev_gray is not None and cfg.max_texture_points > 0:
            p_rack = self._texture.points_rack(pipes)
            p_cam = (p_rack - T[:3, 3]) @ T[:3, :3]
            guess = cam.project(p_cam)
            vis = np.all(np.isfinite(guess), axis=1) & cam.in_image(guess, 8.0)
            vis &= ~occluded(T[:3, 3], p_rack, self._texture.pipe, pipes, 0.0)
            guess = np.where(vis[:, None], guess, self._texture.uv_last)
            tex_uv, tex_ok = track_points(self._prev_gray, gray, self._texture.uv_last, guess,
                                          cfg.lk_window_px, cfg.lk_levels)
            tex_ok &= vis & cam.in_image(tex_uv, 4.0)
            if cfg.texture_templates:
                tex_uv, tex_ok = self._align_to_references(img_raw, T, pipes, p_rack, tex_uv, tex_ok)
            self._texture.keep(tex_ok)
            if self._stale_ref.size == tex_ok.size:
                self._stale_ref = self._stale_ref[tex_ok]
            tex_uv = tex_uv[tex_ok]
        ground = self._track_ground(gray, T)
        # ---- iterations (first frame: try the four limb-polarity hypotheses, keep the best)
        if first:
            n_p = self.model.num_parallel
            best: dict[str, Any] | None = None
            for hyp in ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)):
                pol_h = np.zeros(self._polarity.size)
                pol_h[0 : 2 * n_p : 2] = hyp[0]
                pol_h[1 : 2 * n_p : 2] = hyp[1]
                res = self._solve(T, gaps, img_raw, img_f, tex_uv, True, pol_h, None)
                if best is None or res["n_agree"] > best["n_agree"]:
                    best = res
            assert best is not None
            last = best
        else:
            pol_t = np.where(self._polarity_known & (np.abs(self._polarity) >= 0.5), np.sign(self._polarity), 0.0)
            last = self._solve(T, gaps, img_raw, img_f, tex_uv, False, pol_t, ground)
        T, gaps, pipes, it_done = last["T"], last["gaps"], last["pipes"], last["iterations"]
        # ---- health
        x = last["x"]
        r_post = last["r_post"]
        w = last["w"]
        n_samples = int(last["samples"].uv.shape[0])
        agree = last["agree"]
        n_agree = int(last["n_agree"])
        residual_px = float(last["residual_px"])
        H_data = last["H_data"]
        n_tex = int(tex_uv.shape[0])
        if n_tex >= 3:
            cond = information_condition(H_data[:6, :6])
        else:
            # Along-pipe translation is expected to be weak without texture: check the rest.
            e_y = np.zeros(6)
            e_y[:3] = T[:3, :3].T[:, 1]
            Q = np.linalg.svd(np.eye(6) - np.outer(e_y, e_y))[0][:, :5]
            cond = information_condition(H_data[:6, :6], Q)
        status = ""
        if n_samples == 0:
            status = "no visible limb"
        elif n_agree < cfg.min_edge_points:
            status = f"too few agreeing edge samples ({n_agree})"
        elif n_agree < cfg.min_inlier_fraction * n_samples:
            status = f"too few agreeing edge samples ({n_agree}/{n_samples})"
        elif residual_px > cfg.max_residual_px:
            status = f"edge residual too large ({residual_px:.2f} px)"
        elif not cond < cfg.max_condition:
            status = f"ill-conditioned ({cond:.3g})"
        ok = status == ""
        # ---- covariance from the final normal matrix and residual scale
        wpos = w > 0
        dof = max(int(wpos.sum()) - x.size, 1)
        n_rows = r_post.size - (3 if self._gravity is not None else 0)
        scale2 = float(np.sum(w[:n_rows] * r_post[:n_rows] ** 2) / dof)
        try:
            cov_full = np.linalg.inv(last["H"]) * scale2 * cfg.covariance_inflation
        except np.linalg.LinAlgError:
            cov_full = np.eye(x.size) * 1e6
        cov = 0.5 * (cov_full[:6, :6] + cov_full[:6, :6].T)
        n_gap = self._n_gaps if cfg.estimate_gaps else 0
        gap_std = np.sqrt(np.maximum(np.diag(cov_full)[6 : 6 + n_gap], 0.0)) if n_gap else np.zeros(self._n_gaps)
        # ---- state update
        dt_s = None if self._last_stamp is None else float(stamp_s) - self._last_stamp
        if ok:
            if dt_s is not None and 0.0 < dt_s <= 0.5:
                velocity = se3.log(se3.inverse(self._T) @ T) / dt_s
                n_ground = 0 if last.get("ground_uv") is None else int(last["ground_uv"].shape[0])
                if cfg.unobserved_velocity_tau_s > 0 and n_tex + n_ground < 3:
                    # Along the pipes the pose only followed the prediction: keep the last observed
                    # speed there, fading, instead of re-deriving it from itself.
                    u = T[:3, :3][1, :]  # the rack's +y in the camera frame
                    decay = float(np.exp(-dt_s / cfg.unobserved_velocity_tau_s))
                    velocity[:3] += (decay * float(self._velocity[:3] @ u) - float(velocity[:3] @ u)) * u
                self._velocity = velocity
            else:
                self._velocity = np.zeros(6)
            self._T = T
            self._gaps = gaps
            self._edge_bias = last["bias"]
            self._scale2 = scale2
            if self._gravity is not None:
                self._up_rack = T[:3, :3] @ self._gravity[0][2, :]
            self._initialized = True
            self._lost_frames = 0
            self._update_polarity(last["samples"], last["meas"].sign, agree)
            self._update_profiles(last["samples"], last["meas"].inner, agree)
            self._update_texture(gray, img_raw, T, pipes, tex_uv, last["samples"])
            self._update_ground(gray, T, last, cov_full)
        else:
            self._T = T_pred
            self._velocity = np.zeros(6)
            self._lost_frames += 1
            if self._initialized and not cfg.estimate_gaps and 0 < cfg.relock_after_frames <= self._lost_frames:
                # Rejected for a while: search wide again from the last pose, as after a rough reset (without
                # it one lost stretch loses the rack for good). Not with estimated gaps: on a wrong model the
                # wide search locks onto grating bars and shadows and runs away (stress bench, 2026-11-24).
                self._initialized = False
                self._start_std = (cfg.relock_prior_translation_m, cfg.relock_prior_rotation_rad)
            self._ground_uv = np.zeros((0, 2))
            if len(self._texture):
                self._texture.uv_last = tex_uv
            cov = cov + np.diag([0.05**2] * 3 + [0.02**2] * 3)
        self._prev_gray = gray.copy()
        self._last_stamp = float(stamp_s)
        self._frames += 1
        return RackEstimate(
            stamp_s=float(stamp_s),
            ok=ok,
            T_rack_cam=_readonly(self._T),
            covariance=_readonly(cov),
            gaps=_readonly(self._gaps),
            gaps_std_m=_readonly(gap_std),
            num_edge_points=n_agree,
            num_edge_samples=n_samples,
            num_texture_points=n_tex,
            residual_px=residual_px,
            iterations=it_done,
            status=status,
            condition=float(cond),
            edge_bias_px=_readonly(self._edge_bias),
        )

    # ------------------------------------------------------------------ internals
    def _fuse_gravity(self, R_prior: FloatArray, std_rad: float, T_pred: FloatArray) -> tuple[FloatArray, float]:
        """Filtered attitude prior for this frame as (R whose last row is the up direction, row weight).

        The up direction seen by the camera, g = R_rack_camᵀ e_z, is filtered over frames: the
        last fused g is carried to this frame through the vision's attitude (precise from frame
        to frame, with `prior_rate_noise_rad` of random walk per frame) and fused with this
        frame's prior (std `std_rad`) by a scalar Kalman update. Independent per-frame prior
        errors then average out while the vision's slow roll/slide error is still pulled back.
        """
        g_meas = R_prior[2, :]
        var_meas = std_rad**2
        if self._up_rack is None:
            g, var = g_meas, var_meas
        else:
            g_pred = T_pred[:3, :3].T @ self._up_rack
            var_p = self._up_var + self.config.prior_rate_noise_rad**2
            k = var_p / (var_p + var_meas)
            g = g_pred + k * (g_meas - g_pred)
            g = g / np.linalg.norm(g)
            var = (1.0 - k) * var_p
        self._up_var = var
        self._up_rack = T_pred[:3, :3] @ g
        R_eff = np.zeros((3, 3))
        R_eff[2, :] = g
        return R_eff, self._scale2 * self.config.covariance_inflation / var

    def _check_prior(self, R_prior: Any, std_rad: float | None) -> tuple[FloatArray, float] | None:
        """The attitude prior as (R (3, 3), std (rad)), or None; raises InputError naming the bad argument."""
        if R_prior is None and std_rad is None:
            return None
        if R_prior is None or std_rad is None:
            raise InputError("R_prior: give both R_prior and R_prior_std_rad, or neither")
        R = np.asarray(R_prior, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or np.abs(R.T @ R - np.eye(3)).max() > 1e-6 \
                or np.linalg.det(R) < 0:
            raise InputError(f"R_prior: expected a 3x3 rotation matrix, got shape {R.shape}")
        std = float(std_rad)
        if not np.isfinite(std) or std <= 0.0:
            raise InputError(f"R_prior_std_rad: must be positive, got {std_rad}")
        return R, std

    def _pipe_arrays(self, gaps: FloatArray) -> PipeArrays:
        """`model.pipe_arrays(gaps)`, cached for the last gaps (read-only arrays, shared)."""
        key = np.asarray(gaps, dtype=np.float64).tobytes()
        if key != self._pipes_key or self._pipes_cached is None:
            pipes = self.model.pipe_arrays(gaps)
            for a in (pipes.starts, pipes.directions, pipes.radii, pipes.lengths, pipes.gap_index):
                a.flags.writeable = False
            self._pipes_key, self._pipes_cached = key, pipes
        return self._pipes_cached

    def _solver_weights(self, first: bool, n_par: int, i_bias: int) -> tuple[FloatArray, FloatArray]:
        """Per-iteration damping and anchor information (n_par,) (depend only on the config and `first`)."""
        key = (first, n_par, self._start_std)
        cached = self._weights_cache.get(key)
        if cached is not None:
            return cached
        cfg = self.config
        prior = np.ones(n_par)
        prior[:3] = 1.0 / cfg.prior_translation_m**2
        prior[3:6] = 1.0 / cfg.prior_rotation_rad**2
        prior[6:i_bias] = 1.0 / cfg.prior_gap_m**2
        anchor_info = np.zeros(n_par)
        if first:
            anchor_info[:3] = 1.0 / self._start_std[0] ** 2
            anchor_info[3:6] = 1.0 / self._start_std[1] ** 2
            anchor_info[i_bias : i_bias + 2] = 1.0 / 0.3**2
        else:
            anchor_info[:3] = 1.0 / cfg.motion_prior_translation_m**2
            anchor_info[3:6] = 1.0 / cfg.motion_prior_rotation_rad**2
            anchor_info[i_bias : i_bias + 2] = 1.0 / cfg.edge_bias_rate_px**2
        prior.flags.writeable = False
        anchor_info.flags.writeable = False
        self._weights_cache[key] = (prior, anchor_info)
        return prior, anchor_info

    def _solve(
        self,
        T: FloatArray,
        gaps: FloatArray,
        img_raw: np.ndarray[Any, np.dtype[np.float32]],
        img_f: np.ndarray[Any, np.dtype[np.float32]],
        tex_uv: FloatArray,
        first: bool,
        polarity: FloatArray,
        ground: tuple[FloatArray, FloatArray, FloatArray] | None,
    ) -> dict[str, Any]:
        """Iterate render -> search -> IRLS -> exp update from pose T and gaps; returns the final state.

        `ground`: (ray origin (3,), ray directions (K, 3), current pixels (K, 2)) of the ground
        points (rack frame), or None; with them the ground height z_g is the last parameter.
        """
        cfg = self.config
        cam = self.camera
        n_iter = cfg.init_iterations if first else cfg.max_iterations
        n_gap = self._n_gaps if cfg.estimate_gaps else 0
        i_bias = 6 + n_gap  # index of the two edge-bias parameters (if estimated)
        n_par = i_bias + (2 if cfg.estimate_edge_bias else 0)
        has_ground = ground is not None and ground[1].shape[0] > 0 and self._z_g is not None
        i_z = n_par
        n_par += 1 if has_ground else 0
        prior, anchor_info = self._solver_weights(first, n_par, i_bias)
        if has_ground:
            prior, anchor_info = prior.copy(), anchor_info.copy()
            prior[i_z] = 1.0
            # In the solver's information scale (the posterior is inv(H) * scale2 * inflation, see the
            # covariance): with 1 / var here a frame that does not observe z_g multiplied its variance
            # by scale2 * inflation (~2-4 on textured grounds), and z_g wandered off by metres.
            anchor_info[i_z] = self._scale2 * cfg.covariance_inflation / self._z_g_var
        pipes = self._pipe_arrays(gaps)
        # Texture points in the rack frame: fixed during the iterations unless the gaps move them.
        tex_rack = self._texture.points_rack(pipes) if tex_uv.shape[0] else np.zeros((0, 3))
        bias = self._edge_bias.copy()
        moved = np.zeros(n_par)  # sum of this frame's increments (first order: the offset from the anchor)
        last: dict[str, Any] = {}
        it_done = 0
        init_px = float(cfg.init_search_range_px)
        if first:
            # The first search covers init_search_range_m at the pipes' depth (capped in pixels), or
            # three standard deviations of the reset pose if wider, or init_search_range_gaps_m when
            # the gaps are estimated (a wrong gap moves a pipe further than the pose is off).
            s0 = sample_limbs(T, cam, pipes, 4, cfg.margin_px, 12.0, 0.1, 0.0)
            if s0.p_cam.shape[0]:
                depth = median_1d(s0.p_cam[:, 2])
                range_m = max(cfg.init_search_range_m,
                              3.0 * (self._start_std[0] + self._start_std[1] * depth),
                              cfg.init_search_range_gaps_m if cfg.estimate_gaps and not self._gaps_scanned else 0.0)
                init_px = min(cam.fx * range_m / depth, float(cfg.init_search_range_px))
        for it in range(n_iter):
            it_done = it + 1
            if first:
                rng_px = max(cfg.search_range_px, round(init_px * cfg.init_shrink**it))
            else:
                rng_px = cfg.search_range_px
            samples = sample_limbs(T, cam, pipes, cfg.samples_per_limb, cfg.margin_px, 12.0, 0.1,
                                   cfg.occlusion_margin_px)
            pol = polarity[samples.limb]
            img_it = img_f
            thr = cfg.edge_threshold
            if first and rng_px > 2 * cfg.search_range_px:
                sigma = max(cfg.blur_sigma_px, rng_px / 16.0)
                img_it = np.asarray(cv2.GaussianBlur(img_raw, (0, 0), sigma), dtype=np.float32)
                thr = cfg.edge_threshold * min(1.0, 1.5 / sigma)  # blurred steps have weaker gradients
            meas = search_edges(img_it, samples.uv, samples.normal_px, pol, rng_px, thr,
                                tangent_offset_px=cfg.edge_tangent_px,
                                inner_ref=self._profiles[samples.limb] if cfg.edge_profile_px > 0 else None)
            offset_px = meas.offset_px
            if cfg.edge_silhouette_px > 0 and not (first and rng_px > 2 * cfg.search_range_px):
                offset_px = refine_silhouette(img_raw, samples.uv, samples.normal_px, offset_px,
                                              cfg.edge_silhouette_px, cfg.edge_silhouette_px - 1,
                                              max_rel_rms=cfg.edge_silhouette_max_rms)
            A_e, r_e, f = self._edge_rows(samples, offset_px, meas.found, T, gaps, n_par)
            if cfg.estimate_edge_bias:
                side = samples.limb[f] % 2
                A_e[np.arange(side.size), i_bias + side] = 1.0
                r_e = r_e - bias[side]
            A_t, r_t = self._texture_rows(T, pipes, tex_rack, tex_uv, n_par)
            A = np.vstack([A_e, A_t])
            r = np.concatenate([r_e, r_t])
            gate = None
            if it > 0:
                gate = max(cfg.gate_px, float(rng_px)) if first else cfg.gate_px
            n_et = r.size
            if has_ground:
                assert ground is not None and self._z_g is not None
                X, dXdz = plane_points(ground[0], ground[1], self._z_g + moved[i_z])
                A_g7, r_g = ground_rows(T, cam, X, dXdz, ground[2])
                A_g = np.zeros((r_g.size, n_par))
                A_g[:, :6] = A_g7[:, :6]
                if cfg.ground_along_only:
                    e_y = np.zeros(6)
                    e_y[:3] = T[:3, :3][1, :]  # the rack's +y in the camera frame (translation part)
                    A_g[:, :6] = np.outer(A_g[:, :6] @ e_y, e_y)
                A_g[:, i_z] = A_g7[:, 6]
                A = np.vstack([A, A_g])
                r = np.concatenate([r, r_g])
            w = robust_weights(r, cfg.robust, cfg.nu_px, gate)
            w[r_e.size : n_et] *= cfg.texture_weight
            w[n_et:] *= cfg.ground_weight
            if self._gravity is not None:
                # Gravity rows, not robustified: information 1/std^2 in the solver's scale (the
                # covariance is inv(H) * scale2 * inflation, so H_prior = scale2 * inflation / std^2).
                r_g, A_g6 = gravity_rows(T[:3, :3], self._gravity[0])
                A_g = np.zeros((3, n_par))
                A_g[:, :6] = A_g6
                A = np.vstack([A, A_g])
                r = np.concatenate([r, r_g])
                w = np.concatenate([w, np.full(3, self._gravity[1])])
            x, H_data, _ = solve_normal_equations(A, r, w, prior, anchor_info, -moved)
            moved += x
            T = T @ se3.exp_one(x[:6])
            if n_gap:
                gaps = gaps + x[6:i_bias]
                pipes = self._pipe_arrays(gaps)
                if tex_uv.shape[0]:
                    tex_rack = self._texture.points_rack(pipes)
            if cfg.estimate_edge_bias:
                bias = bias + x[i_bias : i_bias + 2]
            last = {"samples": samples, "meas": meas, "found": f, "A": A, "r": r, "w": w, "x": x,
                    "H_data": H_data, "H": H_data + np.diag(prior), "n_edge": r_e.size, "n_et": n_et,
                    "z_g": (self._z_g + moved[i_z]) if has_ground else self._z_g, "i_z": i_z if has_ground else -1,
                    "ground_uv": ground[2] if has_ground and ground is not None else None}
            small = bool(np.linalg.norm(x[:3]) < cfg.stop_translation_m
                         and np.linalg.norm(x[3:6]) < cfg.stop_rotation_rad)
            # Also stop when the update moves the rendered edges by less than stop_px (median).
            small = small or bool(r_e.size > 0 and median_1d(np.abs(A_e @ x)) < cfg.stop_px)
            small = small and it + 1 >= cfg.min_iterations
            if small and (not first or rng_px <= cfg.search_range_px):
                break
        r_post = last["r"] - last["A"] @ last["x"]
        n_edge = int(last["n_edge"])
        agree = np.zeros(last["samples"].uv.shape[0], dtype=bool)
        agree[np.flatnonzero(last["found"])] = np.abs(r_post[:n_edge]) <= cfg.inlier_px
        last.update(
            T=T, gaps=gaps, pipes=pipes, bias=bias, iterations=it_done, r_post=r_post, agree=agree,
            n_agree=int(agree.sum()),
            residual_px=1.4826 * median_1d(np.abs(r_post[:n_edge])) if n_edge else float("inf"),
        )
        return last

    def _as_gray(self, image: Any) -> np.ndarray[Any, np.dtype[np.uint8]]:
        img = np.asarray(image)
        if img.dtype != np.uint8:
            raise InputError(f"image: expected uint8, got {img.dtype}")
        if img.ndim == 3 and img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        if img.ndim != 2:
            raise InputError(f"image: expected (H, W) or (H, W, 3), got {img.shape}")
        if img.shape != (self.camera.height, self.camera.width):
            raise InputError(f"image: size {img.shape[1]}x{img.shape[0]} does not match the camera "
                             f"{self.camera.width}x{self.camera.height}")
        return np.ascontiguousarray(img)

    def _edge_rows(
        self, samples: LimbSamples, offset: FloatArray, found: Any, T: FloatArray, gaps: FloatArray, n_par: int
    ) -> tuple[FloatArray, FloatArray, Any]:
        f = np.asarray(found, dtype=bool)
        J6 = pose_jacobian(samples.J_uv_pcam[f], samples.p_cam[f])  # (n, 2, 6)
        nrm = samples.normal_px[f]
        A = np.zeros((int(f.sum()), n_par))
        A[:, :6] = np.einsum("nij,ni->nj", J6, nrm)  # σ = ξᵀ n (eq. 15)
        if self.config.estimate_gaps and self._n_gaps:
            gi = self._pipe_arrays(gaps).gap_index[samples.pipe[f]]
            has = gi >= 0
            Jg = gap_jacobian(samples.J_uv_pcam[f][has], T[:3, :3].T)
            A[np.flatnonzero(has), 6 + gi[has]] = np.einsum("ni,ni->n", Jg, nrm[has])
        return A, offset[f], f

    def _texture_rows(
        self, T: FloatArray, pipes: PipeArrays, p_rack: FloatArray, tex_uv: FloatArray, n_par: int
    ) -> tuple[FloatArray, FloatArray]:
        k = tex_uv.shape[0]
        if k == 0:
            return np.zeros((0, n_par)), np.zeros(0)
        p_cam = (p_rack - T[:3, 3]) @ T[:3, :3]
        uv, J = self.camera.project_with_jacobian(p_cam)
        A = np.zeros((2 * k, n_par))
        A[:, :6] = pose_jacobian(J, p_cam).reshape(2 * k, 6)
        if self.config.estimate_gaps and self._n_gaps:
            gi = pipes.gap_index[self._texture.pipe]
            Jg = gap_jacobian(J, T[:3, :3].T)  # (k, 2)
            for c in range(2):
                rows = 2 * np.arange(k) + c
                has = gi >= 0
                A[rows[has], 6 + gi[has]] = Jg[has, c]
        r = (tex_uv - uv).reshape(-1)
        return A, r

    def _update_polarity(self, samples: LimbSamples, sign: FloatArray, good: Any) -> None:
        g = np.asarray(good, dtype=bool)
        if not np.any(g):
            return
        limbs = samples.limb[g]
        n_l = self._polarity.size
        s = np.bincount(limbs, weights=sign[g], minlength=n_l)
        c = np.bincount(limbs, minlength=n_l)
        seen = c >= 3
        mean = np.where(seen, s / np.maximum(c, 1), 0.0)
        new = seen & ~self._polarity_known
        upd = seen & self._polarity_known
        rate = self.config.polarity_rate
        self._polarity[new] = mean[new]
        self._polarity[upd] = (1.0 - rate) * self._polarity[upd] + rate * mean[upd]
        self._polarity_known |= seen

    def _reset_ground(self) -> None:
        self._silhouettes_pred: list[FloatArray] | None = None  # pipes' silhouettes at this frame's prediction
        self._ground_uv = np.zeros((0, 2))  # pixels in the previous image
        self._ground_o = np.zeros(3)  # previous accepted camera centre (rack frame)
        self._ground_d = np.zeros((0, 3))  # their rays from it (rack frame)
        self._z_g: float | None = None
        self._z_g_var = 0.0

    def _track_ground(
        self, gray: np.ndarray[Any, np.dtype[np.uint8]], T_pred: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """Lucas-Kanade of last frame's ground points into this image, seeded by their predicted projection."""
        cfg = self.config
        if cfg.ground_points <= 0 or self._prev_gray is None or self._z_g is None or not self._ground_uv.shape[0]:
            return None
        X, _ = plane_points(self._ground_o, self._ground_d, self._z_g)
        fin = np.all(np.isfinite(X), axis=1)
        guess = self.camera.project((np.where(fin[:, None], X, 0.0) - T_pred[:3, 3]) @ T_pred[:3, :3])
        guess = np.where((fin & np.all(np.isfinite(guess), axis=1))[:, None], guess, self._ground_uv)
        # Exposure steps: bring this image to the previous one's mean level first (LK assumes constant brightness).
        m_prev = float(self._prev_gray[::8, ::8].mean())
        m_cur = float(gray[::8, ::8].mean())
        cur = gray
        if m_cur > 1.0 and abs(m_prev / m_cur - 1.0) > 0.03:
            cur = np.asarray(cv2.convertScaleAbs(gray, alpha=m_prev / m_cur), dtype=np.uint8)
        uv, ok = track_points(self._prev_gray, cur, self._ground_uv, guess, cfg.lk_window_px, cfg.lk_levels)
        ok &= fin & self.camera.in_image(uv, 4.0)
        # Points a pipe moves over between the frames (parallax; a pipe entering the view) would be
        # tracked on its cladding: keep those clear of the pipes at the predicted pose.
        polygons = pipe_silhouettes(T_pred, self.camera, self._pipe_arrays(self._gaps))
        self._silhouettes_pred = polygons
        ok &= on_ground(uv, ground_mask(gray.shape[:2], polygons, cfg.margin_px))
        return self._ground_o, self._ground_d[ok], uv[ok]

    def _update_ground(
        self, gray: np.ndarray[Any, np.dtype[np.uint8]], T: FloatArray, last: dict[str, Any], cov_full: FloatArray
    ) -> None:
        """Keep the ground points that fit, add new ones, store their rays from this (accepted) pose."""
        cfg = self.config
        if cfg.ground_points <= 0:
            return
        keep_uv = np.zeros((0, 2))
        i_z = int(last["i_z"])
        if i_z >= 0:
            # The ground lies below the pipes' support plane, and it does not move: a frame's estimate may
            # move z_g by at most half its standard deviation (a few bad ground points, or a roll / slide
            # error leaking into it, otherwise carry it metres within a second: stress bench, p3 fast).
            z_prev = float(self._z_g) if self._z_g is not None else float(last["z_g"])
            step = max(0.02, 0.5 * float(np.sqrt(self._z_g_var)))
            self._z_g = min(float(np.clip(float(last["z_g"]), z_prev - step, z_prev + step)), 0.0)
            # Posterior variance plus a small random walk (the ground is not flat everywhere).
            self._z_g_var = float(max(cov_full[i_z, i_z], 1e-6)) + cfg.ground_height_walk_m**2
            n_et = int(last["n_et"])
            r_g = last["r_post"][n_et : n_et + 2 * last["ground_uv"].shape[0]].reshape(-1, 2)
            ok = np.linalg.norm(r_g, axis=1) <= cfg.gate_px  # the same gate as the solver's rows
            ground_uv = last.get("ground_uv")
            if ground_uv is not None and ground_uv.shape[0] == ok.size:
                keep_uv = ground_uv[ok]
        # the predicted pose's silhouettes (computed for tracking) are close enough for the margin
        polygons = self._silhouettes_pred
        if polygons is None:
            polygons = pipe_silhouettes(T, self.camera, self._pipe_arrays(self._gaps))
        self._silhouettes_pred = None
        if keep_uv.shape[0]:
            # A pipe sweeps over the ground next to it as the camera moves (parallax): a ground point at
            # its limb is tracked onto the pipe's cladding and pulls z_g up towards the pipes. Drop
            # points that come within the margin of a pipe.
            keep_uv = keep_uv[on_ground(keep_uv, ground_mask(gray.shape[:2], polygons, cfg.margin_px))]
        if self._z_g is None:
            # First guess: the ground as far below the pipes' tops as the camera is above them (weak).
            top = 2.0 * float(np.max(self.model.radii))
            self._z_g = top - 2.0 * max(float(T[2, 3]) - top, 0.5)
            self._z_g_var = 2.0**2
        need = cfg.ground_points - keep_uv.shape[0]
        new = np.zeros((0, 2))
        # detection (a Shi-Tomasi pass over the image) every `detect_every` frames, unless half are gone
        due = self._frames % cfg.detect_every == 0 or keep_uv.shape[0] < cfg.ground_points // 2
        if need >= max(3, cfg.ground_points // 5) and due:
            new = detect_ground_points(gray, polygons, keep_uv, need,
                                       cfg.texture_min_distance_px, cfg.margin_px, cfg.ground_min_corner_ratio)
        uv = np.vstack([keep_uv, new])
        self._ground_uv = uv
        self._ground_o = T[:3, 3].copy()
        self._ground_d = self.camera.unproject(uv) @ T[:3, :3].T if uv.shape[0] else np.zeros((0, 3))

    def _pipe_polygons(self, samples: LimbSamples) -> list[FloatArray]:
        """Image quadrilaterals of the pipes between their two clipped limb segments."""
        polys = []
        seg_l = samples.segment_limb
        for pipe in np.unique(seg_l // 2):
            a = np.flatnonzero(seg_l == 2 * pipe)
            b = np.flatnonzero(seg_l == 2 * pipe + 1)
            if a.size and b.size:
                sa, sb = samples.segments_uv[a[0]], samples.segments_uv[b[0]]
                polys.append(np.array([sa[0], sa[1], sb[1], sb[0]]))
        return polys

    def _update_profiles(self, samples: LimbSamples, inner: FloatArray, good: Any) -> None:
        """Running mean of each limb's normalised inner profile over its agreeing samples."""
        g = np.asarray(good, dtype=bool)
        if self.config.edge_profile_px <= 0 or inner.shape[1] != self._profiles.shape[1] or not np.any(g):
            return
        limbs = samples.limb[g]
        n_l = self._profiles.shape[0]
        cnt = np.bincount(limbs, minlength=n_l)
        acc = np.zeros_like(self._profiles)
        np.add.at(acc, limbs, inner[g])
        seen = cnt >= 3
        mean = acc[seen] / cnt[seen, None]
        norm = np.linalg.norm(mean, axis=1, keepdims=True)
        mean = mean / np.maximum(norm, 1e-9)  # unit norm: the reference; a weak norm = inconsistent shapes
        fresh = seen & ~np.any(self._profiles != 0.0, axis=1)
        rate = np.where(fresh[seen], 1.0, self.config.edge_profile_rate)[:, None]
        upd = (1.0 - rate) * self._profiles[seen] + rate * mean * np.minimum(norm, 1.0)
        self._profiles[seen] = upd

    def _ref_patch_size(self) -> int:
        """Side of the stored reference patches: room for the window scaled by up to ~1.6."""
        half = int(np.ceil(1.6 * (self.config.template_half_px + 1))) + 1
        return 2 * half + 1

    def _align_to_references(
        self, img: np.ndarray[Any, np.dtype[np.float32]], T: FloatArray, pipes: PipeArrays, p_rack: FloatArray,
        uv: FloatArray, ok: Any,
    ) -> tuple[FloatArray, Any]:
        """Refine the Lucas-Kanade pixels `uv` (K, 2) of the points at `p_rack` (K, 3) on their
        warped references (pose T).

        Points whose reference no longer covers the warped window keep their Lucas-Kanade
        pixel and are marked for re-referencing (`_stale_ref`) once the frame's pose is known.
        """
        cfg = self.config
        tm = self._texture
        ok = np.asarray(ok, dtype=bool).copy()
        self._stale_ref = np.zeros(len(tm), dtype=bool)
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return uv, ok
        A = tangent_plane_warps(T, self.camera, uv[idx], p_rack[idx], tm.normals_rack(pipes)[idx],
                                tm.ref_R[idx], tm.ref_o[idx])
        res = align_templates(img, uv[idx], A, tm.ref_patch[idx], cfg.template_half_px, cfg.template_iterations)
        near = np.all(np.isfinite(res.uv), axis=1) & (np.linalg.norm(res.uv - uv[idx], axis=1) <= 3.0)
        good = res.inside & near & (res.ncc >= cfg.template_min_ncc)
        uv = uv.copy()
        uv[idx[good]] = res.uv[good]
        # Inside the reference but no match near the Lucas-Kanade pixel: not the same point.
        ok[idx[res.inside & ~good]] = False
        self._stale_ref[idx[~res.inside]] = True
        return uv, ok

    def _update_texture(
        self, gray: np.ndarray[Any, np.dtype[np.uint8]], img_f: np.ndarray[Any, np.dtype[np.float32]],
        T: FloatArray, pipes: PipeArrays, tex_uv: FloatArray, samples: LimbSamples,
    ) -> None:
        cfg = self.config
        if cfg.max_texture_points == 0:
            return
        tm = self._texture
        half_ref = (self._ref_patch_size() - 1) // 2
        if len(tm):
            if cfg.texture_templates and self._stale_ref.size == len(tm) and np.any(self._stale_ref):
                # The view changed too much for the stored patch: this image becomes the reference.
                st = np.flatnonzero(self._stale_ref)
                tm.ref_patch[st] = sample_patches(img_f, tex_uv[st], half_ref)
                tm.ref_R[st] = T[:3, :3]
                tm.ref_o[st] = T[:3, 3]
            p_cam = (tm.points_rack(pipes) - T[:3, 3]) @ T[:3, :3]
            uv = self.camera.project(p_cam)
            res = np.linalg.norm(tex_uv - uv, axis=1)
            keep = res <= cfg.texture_max_residual_px
            tm.uv_last = tex_uv
            tm.keep(keep)
            if cfg.texture_refine_obs > 1:
                tm.refine(T, self.camera, pipes, tm.uv_last, float(cfg.texture_refine_obs))
        self._since_detect += 1
        need = cfg.max_texture_points - len(tm)
        if need <= 0 or (len(tm) and need < max(3, cfg.max_texture_points // 5)):
            return
        # Wait detect_every frames between detections when the map is well filled, or when the last
        # detection found fewer points than asked (sparse spots: detecting every frame finds nothing new).
        if self._since_detect < cfg.detect_every and (len(tm) >= 0.6 * cfg.max_texture_points or self._detect_short):
            return
        self._since_detect = 0
        polys = self._pipe_polygons(samples)
        new_pipe, new_off, new_uv = detect_points(
            gray, T, self.camera, pipes, polys, tm.uv_last, need, cfg.texture_min_distance_px,
            cfg.texture_min_incidence_cos, cfg.texture_min_corner_ratio,
        )
        self._detect_short = new_pipe.size < need
        if new_pipe.size:
            tm.add(new_pipe, new_off, new_uv, sample_patches(img_f, new_uv, half_ref), T)
