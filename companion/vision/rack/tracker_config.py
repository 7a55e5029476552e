"""Settings and per-frame result of the rack tracker (`RackTracker`, `tracker.py`)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError

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
    random walk allowed to z_g; `ground_height_baseline_m` > 0 (0 = off) estimates z_g also from each
    ground point's ray since it was anchored, up to 25 frames back, once the camera has moved that far
    across the pipes (`ground_height.py`: the frame-to-frame z_g wanders by a metre, one frame's
    translation making as much flow as a few hundredths of a degree of rotation error), and hands it to the
    solver with a standard deviation of at least `ground_height_floor_m`; `ground_height_vertical_m` > 0
    (0 = off): on frames without that baseline whose along-pipe travel only the ground measured (fewer
    than 3 texture points), from the points whose anchor lies that far above or below the camera, with
    each anchor's along-pipe position free (`ground_height_vertical.py`; a height from such fits alone
    is handed to the solver only on those frames); `ground_trust_frames` the frames
    a new ground point's rows take to
    reach full weight (1 = at once); `ground_height_m` (rack z, m; None = estimated online from a rough
    first guess) the ground's height when known (the rack's support height above grade from its drawing,
    a survey, or a rangefinder), held on every frame with `ground_height_std_m`: flying along the pipes
    with no texture in view the ground's flow gives the speed over its depth only; `ground_height_kept_on_reset`
    keeps the estimated height (and its variance) across `reset` (the ground does not move when the tracker is
    re-seeded; False starts it again from the rough first guess, as before 2026-12-01); `edge_tangent_px` > 0
    averages each profile with two parallel ones that far along the limb (texture next to a straight limb
    averages out); `edge_distance_sigma_px` > 0 scales each candidate's score by a Gaussian of its
    distance from the rendered limb with this standard deviation (px), from each frame's second iteration
    on and at the tracking range only (0 = a Gaussian as wide as the range, nearly flat): a stronger ground
    or shadow edge a few pixels outside a limb then loses to the limb, while the first iteration still
    follows a motion the prediction missed (over a crossing pipe, along the pipes, edges move by several
    pixels); `edge_innermost_ratio` > 0: with the same timing, a sample whose limb has no learnt inner
    profile yet (the first frame after a reset, a limb just come into view) takes the innermost candidate
    scoring at least this fraction of its best instead of the best (`search_edges`; 0 = off): over a
    grating a shaded limb's step is weaker than the grating's next edge a few pixels out;
    `edge_strength_weight` > 0 weighs each edge row by (its gradient strength / the frame's median) to this
    power, clipped to 0.05-4 (`motion.strength_weights`; 0 = off): the bias a limb's edge takes from the
    brightness structure beside it scales with the inverse of its contrast, so weak limbs count less;
    `blur_sigma_px` an optional Gaussian pre-blur;
    `polarity_rate` the per-frame learning rate of each limb's edge polarity; `margin_px`
    image border kept free; `occlusion_margin_px` how far samples keep from occluding pipes.
    Estimation: `robust` "tukey" (Tukey's biweight, c = 4.685 x the residuals' MAD scale; the
    default since 2026-11-27: a one-sided cluster of edges 2-4 px off, a ground or shadow edge beside a
    limb, keeps weight under the paper's s = 1/(ν + |e|) and pulls the solve by a fraction of its
    offset, where the biweight gives it none; the paper's weights are used in a frame's first iteration
    while the prediction has no measured velocity and in a first frame's coarse search, see `_solve`),
    "paper" (eq. 29, the paper's) or "l2"; `nu_px` the paper's ν (with "tukey" half of it floors the
    MAD scale); `robust_max_scale_px` > 0 caps the edge rows' biweight scale at that (0 = no cap; tried on
    2026-12-02, not adopted: docs/rack.md); `gate_px` residuals beyond this are dropped after the first iteration;
    `max_iterations` / `min_iterations` per frame, stopping when the update is below
    `stop_translation_m` / `stop_rotation_rad` or moves the rendered edges by less than
    `stop_px` (median); `prior_*` the standard deviations of the per-iteration damping (a weak
    prior on the motion that holds unobservable directions); `reset_prior_*` the standard
    deviations of the pose given to `reset` (a prior on the first frame; raise them, e.g. to
    0.1 m / 0.05 rad, when the reset pose is rough) and `motion_prior_*`
    those of the constant-velocity prediction (a prior on every later frame): both only matter
    in weakly observed directions; after `relock_after_frames` consecutive rejected frames (0 =
    never) the wide first-frame search runs again from the last pose, with `relock_prior_*` in
    place of the reset prior (not with `estimate_gaps`), and a relocked pose further than
    `relock_max_jump_sigma` of those from the last pose is rejected; `estimate_gaps` solves the cumulative gaps too,
    each frame anchored at the last frame's gaps with their posterior variance plus a random walk of
    `gap_walk_m` per frame (the gaps are constants: without that memory a frame without the first pipe
    in view lets the gaps and the sideways position slide together);
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
    `texture_weight_crossing` (None = `texture_weight` everywhere) their weight instead in solve iterations whose
    edge rows observe the position along the pipes (a crossing pipe or a pipe's end in view,
    `along_pipe.edges_see_along`) when the gaps are held: the edges then hold the along-pipe / pitch valley
    themselves, and the texture points, placed from the pose of the frame they were found in, only add that pose's
    error (the stress bench's §V rack, 2026-11-28); not while gaps are estimated (the limbs' places are then
    uncertain, and the texture holds roll meanwhile: the wrong-gap cell got worse),
    `detect_every` frames between detections, `lk_window_px`, `lk_levels`,
    `texture_max_residual_px` drop threshold, `texture_refine_obs` the number of observations
    a point's 3-D position is averaged over (1 = keep the position from the first sighting: averaging
    re-places the points from poses that they themselves hold along the pipes, so a lag there feeds
    back into the map and grows; stress bench 2026-11-26),
    `texture_min_distance_px`, `texture_min_incidence_cos` (no grazing points),
    `texture_min_corner_ratio` (corner strength over the pipes' median: no points on noise, 0 = off),
    `texture_crossing_edge_fraction` (0 = off): no new point next to a straight edge across its pipe that steps
    the grey level over at least this fraction of the pipe's width (`crossing_edges.py`: an unmodelled
    occluder's outline, whose corners slide along the pipe; marks on the cladding are smaller than the pipe is
    wide), except near the pipe's ends and modelled crossing pipes (`texture._on_crossing_edges`);
    `texture_check_deg` (0 = off): when the rotation about the axis across the pipes that the edges and
    ground points alone ask for, averaged over frames, exceeds this, the texture is muted and its points
    are dropped for a while, then new points wait a few frames before they count (`texture_check.py`: a
    point at the wrong depth, a corner of an unmodelled beam, otherwise decides the along-pipe / pitch
    valley alone); `edge_pitch_gain` (0 = off): after each accepted vision-only frame with held gaps and no
    crossing pipe in view, that fraction of the pitch step the edges alone ask for is applied to the pose and
    to the texture and ground points placed from earlier poses (`edge_pitch.py`: those points otherwise keep
    the pitch error of the poses they were placed from, the start's for hundreds of frames);
    `texture_templates` refines every Lucas-Kanade result by aligning the point's reference
    patch (from the image it was found in), warped into the current view through the pipe's
    tangent plane, with a (2 `template_half_px` + 1)^2 window and `template_iterations`
    Gauss-Newton steps: frame-to-frame tracking alone drifts by pixels within seconds;
    points whose aligned patch correlates below `template_min_ncc` are dropped.
    Health: `min_edge_points` agreeing samples, `min_inlier_fraction`, `max_residual_px`
    robust residual std, `max_condition` of the normalised information matrix, `inlier_px`
    agreement threshold; `covariance_inflation` multiplies the covariance (edge samples along
    one limb are correlated). Along the pipes the reported covariance carries a standard deviation
    across frames (`along_pipe.py`): it grows by `along_pipe_unobserved_speed_m_s` (m/s) on frames
    where fewer than three texture/ground points hold the position there, by `along_pipe_points_drift`
    times the along-pipe distance moved where they do (frame-to-frame points carry the position, with
    drift, but never correct it), and shrinks only with edges that cross the pipes' direction (a crossing
    pipe, a pipe's end) or a `reset`; 0 = the solver's covariance alone (which conditions each frame on
    the previous pose and says ~1 cm after metres without texture). `along_pipe_widen_covariance`: whether
    that standard deviation widens the reported covariance (True) or is only kept for the tracker's own use,
    the along-pipe scan below and `RackTracker.along_pipe_std_m` (False: a consumer that fuses the pose with an
    IMU which cannot carry the position for seconds keeps following the held pose; tried in the daemon on
    2026-12-01 and not adopted, docs/rack.md).
    `along_scan_range_m` (0 = off): while that standard deviation is more than half the edge search at the
    pipes' depth and a crossing pipe shows both its limbs, the camera's position along the pipes is searched
    up to that far (m) by the crossing pipe's two limbs at once (`along_scan.py`); the prediction is moved to
    the best place when that lies beyond the edge search, scores at least `along_scan_min_gain` times the
    unmoved place and twice any other, and the last frame was accepted with a small edge residual.
    `along_rescale`: the along-pipe travel of a stretch the ground points alone carried (no texture, no crossing
    pipe) is rescaled to the ground height fitted once texture points on the pipes measure the travel again
    (`along_rescale.py`: the ground's image motion gives the travel over the ground's depth, and that depth
    was the first guess's); the pose, the texture points and the ground rays move together.
    `coast_refused_frames`: over up to this many refused frames in a row the prediction keeps the last velocity
    (then it holds the last pose): a camera that moves on while a marginal frame or two is refused is otherwise
    left behind beyond the edge search, and with estimated gaps, which never search wide again, for good (the
    stress bench's wrong-gap cell with the prior, 2026-12-02: 70 cm RMS from a 5 mm perturbation, 3.3 cm with it).
    `retry_refused`: a frame the health checks refuse is solved once more from the last pose's attitude
    and, given an attitude prior, from the prior's tilt (`tracker_health.py`: a shaking camera makes the
    motion prediction's attitude wrong by twice the last turn); the first start that passes is kept.
    `retry_marginal`: with `retry_refused`, a frame that passes but not clearly (an edge residual above half
    `max_residual_px` or fewer than 70 % of its edge samples agreeing) right after a frame that passed clearly is
    solved from the same starts too; the retry is kept only if it passes clearly with a fifth more edge samples
    agreeing (`tracker_health.py`).
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
    ground_height_kept_on_reset: bool = True
    ground_min_corner_ratio: float = 0.0
    ground_height_walk_m: float = 0.002
    ground_height_baseline_m: float = 0.1
    ground_height_floor_m: float = 0.5
    ground_height_vertical_m: float = 0.008
    ground_trust_frames: int = 10
    ground_height_m: float | None = None
    ground_height_std_m: float = 0.05
    edge_profile_rate: float = 0.1
    edge_tangent_px: float = 0.0
    edge_distance_sigma_px: float = 4.0
    edge_innermost_ratio: float = 0.6
    edge_strength_weight: float = 0.25
    blur_sigma_px: float = 0.0
    polarity_rate: float = 0.1
    margin_px: float = 6.0
    occlusion_margin_px: float = 3.0
    robust: str = "tukey"
    nu_px: float = 1.0
    robust_max_scale_px: float = 0.0
    gate_px: float = 4.0
    max_iterations: int = 3
    min_iterations: int = 2
    stop_translation_m: float = 5e-4
    stop_rotation_rad: float = 3e-4
    stop_px: float = 0.15
    prior_translation_m: float = 0.05
    prior_rotation_rad: float = 0.02
    prior_gap_m: float = 0.05
    gap_walk_m: float = 0.001
    reset_prior_translation_m: float = 0.01
    prior_rate_noise_rad: float = 1e-3
    reset_prior_rotation_rad: float = 0.002
    motion_prior_translation_m: float = 0.03
    motion_prior_rotation_rad: float = 0.01
    relock_after_frames: int = 3
    relock_prior_translation_m: float = 0.1
    relock_prior_rotation_rad: float = 0.02
    relock_max_jump_sigma: float = 5.0
    estimate_gaps: bool = False
    estimate_edge_bias: bool = True
    edge_bias_rate_px: float = 0.02
    velocity_prediction: bool = True
    unobserved_velocity_tau_s: float = 0.3
    max_texture_points: int = 50
    texture_weight: float = 4.0
    texture_weight_crossing: float | None = 2.0
    edge_pitch_gain: float = 0.01
    detect_every: int = 4
    lk_window_px: int = 11
    lk_levels: int = 2
    texture_max_residual_px: float = 2.5
    texture_refine_obs: int = 1
    texture_min_distance_px: float = 12.0
    texture_min_incidence_cos: float = 0.4
    along_pipe_unobserved_speed_m_s: float = 0.5
    along_pipe_points_drift: float = 0.2
    along_pipe_widen_covariance: bool = True
    along_scan_range_m: float = 0.4
    retry_refused: bool = True
    retry_marginal: bool = True
    along_scan_min_gain: float = 1.5
    along_rescale: bool = True
    coast_refused_frames: int = 3
    texture_min_corner_ratio: float = 10.0
    texture_crossing_edge_fraction: float = 0.5
    texture_check_deg: float = 0.3
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
        for f in fields(self):
            # a switch given as "yes" or 0 in a config file would otherwise read as on or off unnoticed
            if f.type == "bool" and not isinstance(getattr(self, f.name), (bool, np.bool_)):
                raise InputError(f"{f.name}: expected true or false, got {getattr(self, f.name)!r}")
        if self.robust not in _ROBUST_KINDS:
            raise InputError(f"robust: expected one of {_ROBUST_KINDS}, got {self.robust!r}")
        if self.coast_refused_frames < 0:
            raise InputError(f"coast_refused_frames: must be >= 0, got {self.coast_refused_frames}")
        for name in ("samples_per_limb", "search_range_px", "init_search_range_px", "max_iterations",
                     "init_iterations", "detect_every", "lk_window_px", "template_half_px", "template_iterations"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if self.relock_after_frames < 0:
            raise InputError(f"relock_after_frames: must be >= 0, got {self.relock_after_frames}")
        if self.ground_height_m is not None and not (np.isfinite(self.ground_height_m) and self.ground_height_m < 0.0):
            raise InputError(f"ground_height_m: the ground lies below the pipes' support plane (rack z < 0), "
                             f"got {self.ground_height_m}")
        if not (np.isfinite(self.edge_distance_sigma_px) and self.edge_distance_sigma_px >= 0.0):
            raise InputError(f"edge_distance_sigma_px: must be >= 0 (0 = off), got {self.edge_distance_sigma_px}")
        if not (np.isfinite(self.robust_max_scale_px) and self.robust_max_scale_px >= 0.0):
            raise InputError(f"robust_max_scale_px: must be >= 0 (0 = no cap), got {self.robust_max_scale_px}")
        if not (np.isfinite(self.edge_strength_weight) and 0.0 <= self.edge_strength_weight <= 4.0):
            raise InputError(f"edge_strength_weight: must be in [0, 4] (0 = off), got {self.edge_strength_weight}")
        if not (np.isfinite(self.edge_innermost_ratio) and 0.0 <= self.edge_innermost_ratio <= 1.0):
            raise InputError(f"edge_innermost_ratio: must be in [0, 1] (0 = off), got {self.edge_innermost_ratio}")
        if not (np.isfinite(self.ground_height_baseline_m) and self.ground_height_baseline_m >= 0.0):
            raise InputError(f"ground_height_baseline_m: must be >= 0 (0 = off), got {self.ground_height_baseline_m}")
        if not (np.isfinite(self.ground_height_vertical_m) and self.ground_height_vertical_m >= 0.0):
            raise InputError(f"ground_height_vertical_m: must be >= 0 (0 = off), got {self.ground_height_vertical_m}")
        if not (np.isfinite(self.ground_height_floor_m) and self.ground_height_floor_m >= 0.0):
            raise InputError(f"ground_height_floor_m: must be >= 0, got {self.ground_height_floor_m}")
        if self.ground_trust_frames < 1:
            raise InputError(f"ground_trust_frames: must be >= 1, got {self.ground_trust_frames}")
        if self.texture_weight_crossing is not None and not (
                np.isfinite(self.texture_weight_crossing) and self.texture_weight_crossing >= 0.0):
            raise InputError(f"texture_weight_crossing: must be >= 0 or None, got {self.texture_weight_crossing}")
        if not (np.isfinite(self.edge_pitch_gain) and 0.0 <= self.edge_pitch_gain <= 1.0):
            raise InputError(f"edge_pitch_gain: must be in [0, 1] (0 = off), got {self.edge_pitch_gain}")
        if not (np.isfinite(self.texture_check_deg) and self.texture_check_deg >= 0.0):
            raise InputError(f"texture_check_deg: must be >= 0 (0 = off), got {self.texture_check_deg}")
        if not (np.isfinite(self.along_scan_range_m) and self.along_scan_range_m >= 0.0):
            raise InputError(f"along_scan_range_m: must be >= 0 (0 = off), got {self.along_scan_range_m}")
        if not (np.isfinite(self.along_scan_min_gain) and self.along_scan_min_gain >= 1.0):
            raise InputError(f"along_scan_min_gain: must be >= 1, got {self.along_scan_min_gain}")
        if not (np.isfinite(self.texture_crossing_edge_fraction) and 0.0 <= self.texture_crossing_edge_fraction <= 1.0):
            raise InputError(f"texture_crossing_edge_fraction: must be in [0, 1] (0 = off), got "
                             f"{self.texture_crossing_edge_fraction}")
        if self.max_texture_points < 0:
            raise InputError(f"max_texture_points: must be >= 0, got {self.max_texture_points}")
        if not -1.0 <= self.template_min_ncc <= 1.0:
            raise InputError(f"template_min_ncc: must be in [-1, 1], got {self.template_min_ncc}")
        for name in ("nu_px", "gate_px", "prior_translation_m", "prior_rotation_rad", "prior_gap_m", "inlier_px",
                     "relock_prior_translation_m", "relock_prior_rotation_rad", "relock_max_jump_sigma", "gap_walk_m",
                     "ground_height_std_m"):
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
