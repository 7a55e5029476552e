"""The rack tracker's state and its small helpers (base of the solver and the maps mixins)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.errors import InputError
from companion.vision.rack.along_pipe import along_pipe_std, edge_information_along, edges_see_along, widen_along
from companion.vision.rack.along_rescale import (
    MIN_TEXTURE_POINTS,
    AlongLedger,
    after_shift,
    clear_correction_m,
    filter_correction_m,
    record_height,
    record_step,
)
from companion.vision.rack.along_scan import scan_along
from companion.vision.rack.limbs import LimbLines, limb_lines
from companion.vision.rack.model import PipeArrays, RackModel
from companion.vision.rack.texture import TextureMap
from companion.vision.rack.texture_check import TextureCheck
from companion.vision.rack.tracker_config import RackTrackerConfig

ALONG_SCAN_MIN_SCORE = 3.0  # grey levels per 2 px, both limbs (as `gap_scan`'s): below it no crossing pipe is seen
ALONG_SCAN_MAX_RUNNER_UP = 0.5  # a second place scoring above this fraction of the best: which is the pipe?


class TrackerState:
    """State of a `RackTracker` (see `__init__`), shared by the solver and map-upkeep mixins."""

    _ground_o: FloatArray  # set by `_reset_ground`
    _anchor_o: FloatArray

    def _known_polarity(self) -> FloatArray:
        """Per limb, the sign of its learnt polarity where it is known and clear (|p| >= 0.5), else 0 (open)."""
        known = self._polarity_known & (np.abs(self._polarity) >= 0.5)
        return np.where(known, np.sign(self._polarity), 0.0)

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
        # Variance (m^2) of each cumulative gap carried to the next frame (inf: not estimated yet).
        self._gaps_var = np.full(self._n_gaps, np.inf)
        self._edge_bias = np.zeros(2)
        self._polarity = np.zeros(n_limbs)
        self._polarity_known = np.zeros(n_limbs, dtype=bool)
        self._appearance_kept = False  # the last reset kept the polarity (`RackTracker.reset(keep_appearance)`)
        # Learned inner edge profile of each limb (zero rows: none yet); see `search_edges`.
        self._profiles = np.zeros((n_limbs, self.config.edge_profile_px))
        self._texture = TextureMap.empty(self._ref_patch_size())
        self._prev_gray: np.ndarray[Any, np.dtype[np.uint8]] | None = None
        # Mean grey level of every 8th pixel of `_prev_gray` when its frame computed it (`_ground_lk_inputs`),
        # and of this frame's image: the next frame's exposure check then does not recompute it.
        self._prev_gray_mean: float | None = None
        self._gray_mean: float | None = None
        self._velocity = np.zeros(6)
        # The prediction carries a measured motion (a velocity from two accepted frames in a row): until then
        # a frame's first iteration weighs its residuals with the paper's weights (see `_solve`).
        self._velocity_known = False
        self._last_stamp: float | None = None
        self._frames = 0
        self._initialized = False
        # Standard deviations (m, rad) of the pose the wide first-frame search starts from: the reset
        # pose's (`reset_prior_*` or the caller's), or the re-lock prior's after rejected frames.
        self._start_std = (self.config.reset_prior_translation_m, self.config.reset_prior_rotation_rad)
        self._lost_frames = 0
        self._residual_px = 0.0  # the last accepted frame's robust edge residual (px)
        self._last_clear = False  # the last frame was accepted clearly (`TrackerHealth._clear_retry`)
        self._along_std_m = self._start_std[0]  # std of the position along the pipes (`along_pipe.py`)
        self._relocking = False  # the wide search runs again after lost frames (`relock_after_frames`)
        self._gaps_scanned = False  # this frame's gaps come from `scan_gaps` (the first search stays narrow)
        self._along_moved = False  # this frame's prediction was moved by `_scan_along`
        self._along_ledger = AlongLedger()  # the ground-held along-pipe stretch (`along_rescale.py`)
        self._since_detect = 0
        self._detect_short = False
        self._pipes_key: bytes | None = None
        self._pipes_cached: PipeArrays | None = None
        # The last limb lines (camera centre bytes, pipes, lines): the predicted pose's serve both the
        # ground mask and the solve's first iteration.
        self._lines_cache: tuple[bytes, PipeArrays, LimbLines] | None = None
        self._weights_cache: dict[tuple[bool, int, tuple[float, float]], tuple[FloatArray, FloatArray]] = {}
        self._stale_ref = np.zeros(0, dtype=bool)
        # Weighted residual variance of the last accepted frame (px^2 in the IRLS weights' units):
        # converts an attitude prior's standard deviation into the solver's information scale.
        self._scale2 = 0.5
        # False from a reset until a frame is accepted: 0.5 is then a guess, and the solve measures the
        # scale on the frame itself before it weighs an attitude prior with it (`_solve`).
        self._scale2_measured = False
        self._gravity: tuple[FloatArray, float] | None = None
        # Filtered gravity ("up") of the attitude priors, carried in the rack frame through the
        # estimated attitude (see `_fuse_gravity`), and its variance (rad^2).
        self._up_rack: FloatArray | None = None
        self._up_var = 0.0
        # The texture against the edges and ground in the along-pipe / pitch valley (`texture_check.py`).
        self._texture_check = TextureCheck()
        self._reset_ground()

    def _pipe_arrays(self, gaps: FloatArray) -> PipeArrays:
        """`model.pipe_arrays(gaps)`, cached for the last gaps (read-only arrays, shared)."""
        key = np.asarray(gaps, dtype=np.float64).tobytes()
        if key != self._pipes_key or self._pipes_cached is None:
            pipes = self.model.pipe_arrays(gaps)
            for a in (pipes.starts, pipes.directions, pipes.radii, pipes.lengths, pipes.gap_index):
                a.flags.writeable = False
            self._pipes_key, self._pipes_cached = key, pipes
        return self._pipes_cached

    def _limb_lines(self, o_rack: FloatArray, pipes: PipeArrays) -> LimbLines:
        """`limb_lines(o_rack, pipes)`, reused when called again with the same centre and pipes (the
        cached, read-only `_pipe_arrays` object: the same object means the same values)."""
        key = o_rack.tobytes()
        cached = self._lines_cache
        if cached is not None and cached[0] == key and cached[1] is pipes:
            return cached[2]
        lines = limb_lines(o_rack, pipes)
        self._lines_cache = (key, pipes, lines)
        return lines

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

    def _check_prior(self, R_prior: Any, std_rad: float | None) -> tuple[FloatArray, float] | None:
        """The attitude prior as (R (3, 3), std (rad)), or None; raises InputError naming the bad argument."""
        if R_prior is None and std_rad is None:
            return None
        if R_prior is None or std_rad is None:
            raise InputError("R_prior: give both R_prior and R_prior_std_rad, or neither")
        R = np.asarray(R_prior, dtype=np.float64)
        if R.shape != (3, 3):
            raise InputError(f"R_prior: expected a 3x3 rotation matrix, got shape {R.shape}")
        if not np.all(np.isfinite(R)):
            raise InputError("R_prior: contains NaN or infinite values")
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise InputError(f"R_prior: not a rotation (|R^T R - I| = {np.abs(R.T @ R - np.eye(3)).max():.2g}, "
                             f"det {np.linalg.det(R):.3g})")
        std = float(std_rad)
        if not np.isfinite(std) or std <= 0.0:
            raise InputError(f"R_prior_std_rad: must be positive, got {std_rad}")
        return R, std

    def _along_pipe_covariance(self, cov: FloatArray, last: dict[str, Any], ok: bool, dt_s: float | None,
                               n_tex: int) -> FloatArray:
        """This frame's covariance (6x6, camera frame) with the along-pipe standard deviation carried
        across frames (`along_pipe.py`); updates that standard deviation."""
        cfg = self.config
        if cfg.along_pipe_unobserved_speed_m_s <= 0.0 or self._T is None:
            return cov
        e = self._T[:3, :3][1, :]  # the rack's +y (the pipes' direction) in the camera frame
        dt = 0.0 if dt_s is None or not 0.0 < dt_s <= 0.5 else float(dt_s)
        edge_var = float("inf")
        held = False
        if ok:
            n_edge = int(last["n_edge"])
            info = edge_information_along(last["A"][:n_edge, :3], last["w"][:n_edge], e)
            # Edges across the pipes (a crossing pipe, an end) correct the along-pipe position only when
            # it was known to within the edge search: further off they were matched to other structures.
            if info > 0.0 and self._along_px(self._T, self._along_std_m) <= 0.5 * cfg.search_range_px:
                edge_var = self._scale2 * cfg.covariance_inflation / info
            n_ground = 0 if last.get("ground_uv") is None else int(last["ground_uv"].shape[0])
            held = n_tex + n_ground >= 3
        moved = dt * float(self._velocity[:3] @ e)
        self._along_std_m = along_pipe_std(self._along_std_m, dt, moved, held, edge_var,
                                           cfg.along_pipe_unobserved_speed_m_s, cfg.along_pipe_points_drift)
        return widen_along(cov, e, self._along_std_m) if cfg.along_pipe_widen_covariance else cov

    def _along_px(self, T: FloatArray, along_m: float) -> float:
        """`along_m` (m) along the pipes seen from pose `T` (px): at the camera's height above the support plane,
        which stands in for the depth of what crosses the pipes (a crossing pipe lies nearer)."""
        return along_m * self.camera.fx / max(float(T[2, 3]), 0.1)

    def _scan_along(
        self, T: FloatArray, pipes: PipeArrays, img_raw: np.ndarray[Any, np.dtype[np.float32]]
    ) -> FloatArray:
        """The predicted pose `T` moved along the pipes to where a crossing pipe's limbs are (`along_scan.py`), when
        the along-pipe position is known worse than the edge search reaches, the last frame was accepted and the
        scan's best place is clear.

        What was placed from the drifted poses follows: the last pose (so that the velocity does not take the
        move for motion) and the ground points' rays move with it; texture points, placed along their pipes, are
        dropped and found again. The reported along-pipe standard deviation is left as it is. After a frame that
        was moved itself, the last pose sat on the crossing pipe: the error is the velocity's, and only the
        prediction moves (the velocity then takes the move back).
        """
        cfg = self.config
        last_moved, self._along_moved = self._along_moved, False
        # Not while frames are refused or barely pass: the pose may then be off in every direction, and a move
        # along the pipes that fits the crossing pipe's limbs from a wrong height or attitude is no better (field
        # loop, seed 9: 82 -> 210 cm RMS with the scan after frames at 2.9 px of edge residual).
        if cfg.along_scan_range_m <= 0.0 or self._T is None or self._lost_frames > 0 \
                or self._residual_px > 0.5 * cfg.max_residual_px \
                or self._along_px(T, self._along_std_m) <= 0.5 * cfg.search_range_px:
            return T
        scan = scan_along(T, self.camera, pipes, img_raw, cfg.along_scan_range_m)
        # Within the edge search the solve's own edges take it there, and a move that small may be the attitude's
        # error instead (1 deg of pitch moves the crossing pipe by 3 cm at 1.7 m; field loop, seed 14): a move is
        # made, and the texture dropped, only beyond it (measured at the camera's height, which the crossing pipe
        # lies above: this errs towards leaving a move to the solve).
        if self._along_px(T, abs(scan.shift_m)) <= cfg.search_range_px \
                or scan.at_edge or scan.score < ALONG_SCAN_MIN_SCORE \
                or scan.score < cfg.along_scan_min_gain * scan.score_at_zero \
                or scan.runner_up > ALONG_SCAN_MAX_RUNNER_UP * scan.score:
            return T
        shift = np.array([0.0, scan.shift_m, 0.0])
        T = T.copy()
        T[:3, 3] += shift
        self._along_moved = True
        if not last_moved:
            # Moving the last pose on every frame kept a velocity error alive: a prediction 20 cm ahead was moved
            # back and the last pose 20 cm behind with it, frame after frame (field loop seed 2, 2026-11-28).
            self._move_last_along(shift)
        self._texture.keep(np.zeros(len(self._texture), dtype=bool))
        self._stale_ref = np.zeros(0, dtype=bool)
        self._along_ledger = AlongLedger()  # an absolute along-pipe fix
        return T

    def _rescale_along(self, last: dict[str, Any], T_old: FloatArray, n_tex: int) -> None:
        """Book this accepted frame's along-pipe step in the ground-held stretch and rescale the stretch's travel
        to the long-baseline height once that is sure (`filter_correction_m`), or to the ground height fitted now
        that texture points measure the travel (`clear_correction_m`; `along_rescale.py`).

        `T_old` is the last accepted pose (the step is from it). A crossing pipe (edges that see along the pipes)
        fixes the along-pipe position absolutely and closes the stretch. A shift moves what was placed from the
        drifted poses with the pose: the texture points and their reference centres, the ground points' rays.
        """
        if self._T is None:
            return
        n_edge = int(last["n_edge"])
        if n_edge and edges_see_along(last["A"][:n_edge, :3], last["w"][:n_edge], self._T[:3, :3]):
            self._along_ledger = AlongLedger()
            return
        z_g = last.get("z_g")
        if z_g is None or int(last["i_z"]) < 0:
            return
        n_ground = 0 if last.get("ground_uv") is None else int(last["ground_uv"].shape[0])
        if n_tex < MIN_TEXTURE_POINTS:
            if n_ground < 3:
                return
            # the frame's solve used its own ground height for this step
            self._along_ledger = record_step(self._along_ledger, float(self._T[1, 3] - T_old[1, 3]),
                                             float(self._T[2, 3]), float(z_g))
            if self._zf is None or self.config.ground_height_m is not None:
                return
            shift_m = filter_correction_m(self._along_ledger, self._zf, float(np.sqrt(self._zf_var)))
        else:
            if not self._along_ledger.frames or self._z_g is None:
                return
            self._along_ledger = record_height(self._along_ledger, self._z_g)
            shift_m = clear_correction_m(self._along_ledger)
        if shift_m == 0.0:
            return
        self._along_ledger = after_shift(self._along_ledger, shift_m)
        shift = np.array([0.0, shift_m, 0.0])
        self._move_last_along(shift)
        self._texture.offset_rack = self._texture.offset_rack + shift
        self._texture.ref_o = self._texture.ref_o + shift

    def _move_last_along(self, shift: FloatArray) -> None:
        """The last pose and the ground points' rays (camera centre and long-baseline anchors) moved by `shift`
        (3,), rack frame (m): what was placed from a pose found off along the pipes."""
        assert self._T is not None
        self._T = self._T.copy()
        self._T[:3, 3] += shift
        self._ground_o = self._ground_o + shift
        self._anchor_o = self._anchor_o + shift

    def _reset_ground(self) -> None:
        # pipes' silhouettes at this frame's prediction and the ground mask they give (`ground.ground_mask`)
        self._silhouettes_pred: tuple[list[FloatArray], np.ndarray[Any, Any]] | None = None
        self._ground_uv = np.zeros((0, 2))  # pixels in the previous image
        self._ground_o = np.zeros(3)  # previous accepted camera centre (rack frame)
        self._ground_d = np.zeros((0, 3))  # their rays from it (rack frame)
        self._ground_age = np.zeros(0)  # frames each has fitted the ground plane (see `ground_trust_frames`)
        self._z_g: float | None = None
        self._z_g_var = 0.0
        # Long-baseline rays of the ground points (`ground_height.py`): anchor camera centres (K, 3), rays (K, 3)
        # and frames since anchored (K,), in step with `_ground_uv`; this frame's tracked ones; the height filter.
        self._anchor_o = np.zeros((0, 3))
        self._anchor_d = np.zeros((0, 3))
        self._anchor_age = np.zeros(0)
        self._anchor_tracked: tuple[FloatArray, FloatArray, FloatArray] | None = None
        self._zf: float | None = None
        self._zf_var = 0.0
        self._zf_rejected = 0
        self._zf_across = False  # an across-the-pipes fit has been made (vertical fits alone hand it on less)

    def _ref_patch_size(self) -> int:
        """Side of the stored reference patches: room for the window scaled by up to ~1.6."""
        half = int(np.ceil(1.6 * (self.config.template_half_px + 1))) + 1
        return 2 * half + 1
