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

import contextlib
from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray, check_transform
from companion.errors import InputError, TrackingError
from companion.geometry import se3
from companion.vision.rack.along_rescale import MIN_TEXTURE_POINTS, AlongLedger
from companion.vision.rack.gap_scan import scan_gaps
from companion.vision.rack.limbs import occluded
from companion.vision.rack.motion import gated_residual_variance
from companion.vision.rack.texture import TextureMap, track_points
from companion.vision.rack.texture_check import TextureCheck, valley_step_rad
from companion.vision.rack.tracker_config import RackEstimate, RackTrackerConfig, _positive, _readonly
from companion.vision.rack.tracker_health import JUMP_SIGMA, TrackerHealth
from companion.vision.rack.tracker_maps import TrackerMaps
from companion.vision.rack.tracker_solve import TrackerSolve

RESCAN_MIN_CHANGE_M = 0.01  # a second first-frame scan that moves no gap by more than this changes nothing

__all__ = ["RackEstimate", "RackTracker", "RackTrackerConfig"]


class RackTracker(TrackerSolve, TrackerMaps, TrackerHealth):
    """Stateful tracker; call `reset(T_rack_cam)` then `track(image, stamp_s)` for each frame.

    Split by concern: settings and result in `tracker_config.py`, state in `tracker_state.py`, the
    per-frame solve in `tracker_solve.py`, the maps carried between frames in `tracker_maps.py`, the
    health checks and the second try of a refused frame in `tracker_health.py`.
    """

    def reset(
        self, T_rack_cam: Any, cumulative_gaps: Any = None, position_std_m: float | None = None,
        rotation_std_rad: float | None = None, keep_appearance: bool = False,
    ) -> None:
        """Re-initialize at pose `T_rack_cam` (4x4, camera in rack frame); forget texture and (unless kept) polarity.

        `position_std_m` / `rotation_std_rad`: how far off that pose may be (1 sigma, m / rad; default
        the config's `reset_prior_*`); they set the first frame's prior and its search range.
        `keep_appearance`: a re-seed of a tracker that was locked on this scene (e.g. after a gap in the
        frames): the limbs' polarity and edge profiles it learnt are the scene's and are kept, so the first
        frame solves once with them instead of trying the four polarity hypotheses.
        """
        self._T = check_transform(T_rack_cam, "T_rack_cam").copy()
        cfg = self.config
        self._start_std = (_positive(position_std_m, "position_std_m", cfg.reset_prior_translation_m),
                           _positive(rotation_std_rad, "rotation_std_rad", cfg.reset_prior_rotation_rad))
        self._lost_frames = 0
        self._residual_px = 0.0
        self._last_clear = False
        self._along_moved = False
        self._along_ledger = AlongLedger()
        self._relocking = False
        self._along_std_m = self._start_std[0]
        if cumulative_gaps is not None:
            g = np.asarray(cumulative_gaps, dtype=np.float64).ravel()
            if g.size != self._n_gaps:
                raise InputError(f"cumulative_gaps: expected {self._n_gaps} values, got {g.size}")
            self._gaps = g.copy()
        else:
            self._gaps = self.model.cumulative_gaps.copy()
        self._gaps_var = np.full(self._n_gaps, np.inf)
        self._edge_bias = np.zeros(2)
        self._scale2 = 0.5
        self._scale2_measured = False
        self._up_rack = None
        self._texture_check = TextureCheck()  # its frame indices restart with `_frames`
        ground = (self._z_g, self._z_g_var, self._zf, self._zf_var, self._zf_rejected, self._zf_across)
        self._reset_ground()
        if cfg.ground_height_kept_on_reset:
            # The ground does not move when the tracker is re-seeded: starting its height from the rough first
            # guess again scaled the along-pipe motion by the guess's error (`companion sim --appearance field`,
            # seed 3: a re-seed mid-pass put z_g 1.2 m low and the estimate ran 1 m ahead within 4 s).
            self._z_g, self._z_g_var, self._zf, self._zf_var, self._zf_rejected, self._zf_across = ground
        self._appearance_kept = bool(keep_appearance) and bool(np.any(self._polarity_known))
        if not self._appearance_kept:
            self._polarity[:] = 0.0
            self._polarity_known[:] = False
            self._profiles[:] = 0.0
        self._texture = TextureMap.empty(self._ref_patch_size())
        self._prev_gray = None
        self._prev_gray_mean = None
        self._velocity = np.zeros(6)
        self._velocity_known = False
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

    @property
    def along_pipe_std_m(self) -> float:
        """Standard deviation (m) of the last pose's position along the pipes (see `along_pipe.py`)."""
        return float(self._along_std_m)

    def _scan_gaps(self, T: FloatArray, gaps: FloatArray, img_raw: np.ndarray[Any, np.dtype[np.float32]]) -> FloatArray:
        """The first frame's gap scan (`gap_scan.scan_gaps`) from pose T and cumulative gaps (m): the new gaps."""
        pipes = self._pipe_arrays(gaps)
        return scan_gaps(T, self.camera, pipes, gaps, img_raw, self.config.init_search_range_gaps_m).gaps

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
        if not np.isfinite(stamp_s):
            # a NaN stamp would turn off the motion prediction for every later frame, silently
            raise InputError(f"stamp_s: must be a finite time in seconds, got {stamp_s}")
        self._gray_mean = None
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
        T_old, last_accepted = self._T, self._lost_frames == 0
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
            gaps = self._scan_gaps(T, gaps, img_raw)
            self._gaps_scanned = True
        pipes = self._pipe_arrays(gaps)
        if not first:
            # a crossing pipe in view after drifting along the pipes; a refused frame keeps the move too
            T = T_pred = self._scan_along(T, pipes, img_raw)
        # ---- texture points: LK from the previous image, seeded by the predicted projection
        tex_uv = np.zeros((0, 2))
        tex_ok = np.zeros(0, dtype=bool)
        ground_in = self._ground_lk_inputs(gray, T)
        ground_out: tuple[FloatArray, Any] | None = None
        if len(self._texture) and self._prev_gray is not None and cfg.max_texture_points > 0:
            p_rack = self._texture.points_rack(pipes)
            p_cam = (p_rack - T[:3, 3]) @ T[:3, :3]
            guess = cam.project(p_cam)
            vis = np.isfinite(guess).all(axis=1) & cam.in_image(guess, 8.0)
            vis &= ~occluded(T[:3, 3], p_rack, self._texture.pipe, pipes, 0.0)
            guess = np.where(vis[:, None], guess, self._texture.uv_last)
            if ground_in is not None and ground_in[3] is gray:
                # One Lucas-Kanade call for the texture and the ground points (the same two images; the
                # image pyramids and gradients are built once instead of twice).
                k = len(self._texture)
                uv_all, ok_all = track_points(self._prev_gray, gray, np.vstack([self._texture.uv_last, ground_in[0]]),
                                              np.vstack([guess, ground_in[1]]), cfg.lk_window_px, cfg.lk_levels)
                tex_uv, tex_ok = uv_all[:k], ok_all[:k]
                ground_out = (uv_all[k:], ok_all[k:])
            else:
                tex_uv, tex_ok = track_points(self._prev_gray, gray, self._texture.uv_last, guess,
                                              cfg.lk_window_px, cfg.lk_levels)
            tex_ok &= vis & cam.in_image(tex_uv, 4.0)
            if cfg.texture_templates:
                tex_uv, tex_ok = self._align_to_references(img_raw, T, pipes, p_rack, tex_uv, tex_ok)
            self._texture.keep(tex_ok)
            if self._stale_ref.size == tex_ok.size:
                self._stale_ref = self._stale_ref[tex_ok]
            tex_uv = tex_uv[tex_ok]
        ground = self._track_ground(gray, T, ground_in, ground_out)
        # ---- iterations (first frame: try the four limb-polarity hypotheses, keep the best)
        if first:
            last = self._solve_first(T, gaps, img_raw, img_f, tex_uv)
            if self._gaps_scanned:
                # The scan ran at the start pose, whose error (1 cm / 0.5 deg) moves the outer pipes' limbs by
                # centimetres; from the pose the pipes it placed give, a second scan finds a pipe the first
                # one missed. Its solve is kept only if at least as many edge samples agree
                # (`bench/rack_gap_scan.py`, docs/rack.md "Sixteenth session on #14").
                rescan = self._scan_gaps(last["T"], last["gaps"], img_raw)
                if float(np.max(np.abs(rescan - last["gaps"]))) > RESCAN_MIN_CHANGE_M:
                    again = self._solve_first(last["T"], rescan, img_raw, img_f, tex_uv)
                    if again["n_agree"] >= last["n_agree"]:
                        last = again
        else:
            pol_t = self._known_polarity()
            last = self._solve(T, gaps, img_raw, img_f, tex_uv, False, pol_t, ground)
        status, n_tex, cond = self._status(last, T_pred, tex_uv.shape[0])
        after_clear = not status and cfg.retry_marginal and self._last_clear
        jumped = after_clear and self._jump_sigma(last["T"], T_pred) > JUMP_SIGMA
        marginal = after_clear and (jumped or not self._clear_retry(last))
        if not first and cfg.retry_refused and (status or marginal):
            # A shaking camera: solve again from starts that do not extrapolate the last turn (`tracker_health.py`).
            # A solve that passes only marginally right after a clear frame may have settled beside the limbs as
            # well (field loop seed 24: 55 % agreeing at 2.8 px, 6 cm off, then one pipe over); a retry that passes
            # clearly with a fifth more edge samples agreeing replaces it (`_better_retry`). A scene that stays
            # marginal (a wrong model, clutter) is not solved twice on every frame.
            first_try = last
            for T_try in self._retry_starts(T_pred, None if prior is None else prior[0]):
                again = self._solve(T_try, gaps, img_raw, img_f, tex_uv, False, pol_t, ground)
                retried = self._status(again, T_pred, tex_uv.shape[0])
                if not retried[0] and (self._better_retry(again, first_try, T_pred, jumped) if marginal
                                       else self._clear_retry(again)):
                    last, (status, n_tex, cond) = again, retried
                    break
        T, gaps, pipes, it_done = last["T"], last["gaps"], last["pipes"], last["iterations"]
        x = last["x"]
        r_post = last["r_post"]
        w = last["w"]
        agree = last["agree"]
        n_samples = int(last["samples"].uv.shape[0])
        n_agree = int(last["n_agree"])
        residual_px = float(last["residual_px"])
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
        cov_carry = cov_full  # the gaps': with their own anchor (see `_solve`)
        if np.any(last["carry_info"] > 0):
            with contextlib.suppress(np.linalg.LinAlgError):  # singular: keep cov_full
                cov_carry = np.linalg.inv(last["H"] + np.diag(last["carry_info"])) * scale2 * cfg.covariance_inflation
        n_gap = self._n_gaps if cfg.estimate_gaps else 0
        gap_std = np.sqrt(np.maximum(np.diag(cov_carry)[6 : 6 + n_gap], 0.0)) if n_gap else np.zeros(self._n_gaps)
        # ---- state update
        dt_s = None if self._last_stamp is None else float(stamp_s) - self._last_stamp
        if ok and not first and cfg.texture_check_deg > 0.0 and cfg.max_texture_points > 0:
            self._check_texture(last, T)
        if ok:
            # Only from an accepted or a coasted last pose: the step from a held one, or to a relocked pose, is no
            # motion (a 12 cm relock taken for 3 m/s had the next three frames refused).
            if dt_s is not None and 0.0 < dt_s <= 0.5 and not first and self._lost_frames <= cfg.coast_refused_frames:
                velocity = se3.log_one(se3.inverse(self._T) @ T) / dt_s
                n_ground = 0 if last.get("ground_uv") is None else int(last["ground_uv"].shape[0])
                if cfg.unobserved_velocity_tau_s > 0 and n_tex + n_ground < 3:
                    # Along the pipes the pose only followed the prediction: keep the last observed
                    # speed there, fading, instead of re-deriving it from itself.
                    u = T[:3, :3][1, :]  # the rack's +y in the camera frame
                    decay = float(np.exp(-dt_s / cfg.unobserved_velocity_tau_s))
                    velocity[:3] += (decay * float(self._velocity[:3] @ u) - float(velocity[:3] @ u)) * u
                    self._velocity_known = False  # along the pipes: a guess
                else:
                    self._velocity_known = cfg.velocity_prediction
                self._velocity = velocity
            else:
                self._velocity = np.zeros(6)
                self._velocity_known = False
            self._T = T
            self._gaps = gaps
            if n_gap:
                self._gaps_var = np.maximum(np.diag(cov_carry)[6 : 6 + n_gap], 1e-10) + cfg.gap_walk_m**2
            self._edge_bias = last["bias"]
            # The next frames weigh their attitude prior with this scale: on a first frame its wide gate let
            # in outliers that doubled it or more (the covariance keeps them, conservatively), so only the
            # rows within the tracking gate count here (every row with weight on later frames).
            self._scale2 = gated_residual_variance(w[:n_rows], last["r"][:n_rows], r_post[:n_rows], cfg.gate_px,
                                                   x.size)
            self._scale2_measured = True
            if self._gravity is not None:
                self._up_rack = T[:3, :3] @ self._gravity[0][2, :]
            self._initialized = True
            self._relocking = False
            self._lost_frames = 0
            self._residual_px = residual_px
            self._last_clear = self._clear_retry(last)
            self._update_polarity(last["samples"], last["meas"].sign, agree)
            self._update_profiles(last["samples"], last["meas"].inner, agree)
            self._update_texture(gray, img_raw, T, pipes, tex_uv, last["samples"])
            self._update_ground(gray, T, last, cov_full, n_tex < MIN_TEXTURE_POINTS)
            if not first:
                self._T = self._feed_edge_pitch(last, T, pipes)  # the limbs' own pitch, slowly (edge_pitch.py)
                if cfg.along_rescale and last_accepted:
                    self._rescale_along(last, T_old, n_tex)
        else:
            self._T = T_pred
            self._last_clear = False
            if self._lost_frames >= cfg.coast_refused_frames:
                self._velocity = np.zeros(6)
            self._velocity_known = False
            self._lost_frames += 1
            if self._initialized and not cfg.estimate_gaps and 0 < cfg.relock_after_frames <= self._lost_frames:
                # Rejected for a while: search wide again from the last pose, as after a rough reset (without
                # it one lost stretch loses the rack for good). Not with estimated gaps: on a wrong model the
                # wide search locks onto grating bars and shadows and runs away (stress bench, 2026-11-24).
                self._initialized = False
                self._relocking = True
                self._along_ledger = AlongLedger()
                self._start_std = (cfg.relock_prior_translation_m, cfg.relock_prior_rotation_rad)
            self._ground_uv = np.zeros((0, 2))
            self._ground_age = np.zeros(0)
            if len(self._texture):
                self._texture.uv_last = tex_uv
            cov = cov + np.diag([0.05**2] * 3 + [0.02**2] * 3)
        cov = self._along_pipe_covariance(cov, last, ok, dt_s, n_tex)
        self._prev_gray = gray.copy()
        self._prev_gray_mean = self._gray_mean
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

    def _check_texture(self, last: dict[str, Any], T: FloatArray) -> None:
        """Fold this accepted frame into the texture check (`texture_check.py`); drop the texture points when
        it mutes them (they are the ones that carried the pose off; new ones are found and tracked without
        weight meanwhile)."""
        n_edge, n_et = int(last["n_edge"]), int(last["n_et"])
        n_ground = 0 if last.get("ground_uv") is None else 2 * int(last["ground_uv"].shape[0])
        rows = np.r_[0:n_edge, n_et : n_et + n_ground]
        step = valley_step_rad(last["A"], last["w"], last["r_post"], rows, T[:3, :3])
        if self._texture_check.update(step, self._frames, float(np.radians(self.config.texture_check_deg))):
            self._texture.keep(np.zeros(len(self._texture), dtype=bool))
            self._stale_ref = np.zeros(0, dtype=bool)

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
