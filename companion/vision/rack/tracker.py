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

from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray, check_transform
from companion.errors import InputError, TrackingError
from companion.geometry import se3
from companion.vision.rack.limbs import occluded
from companion.vision.rack.motion import information_condition
from companion.vision.rack.texture import TextureMap, track_points
from companion.vision.rack.tracker_config import RackEstimate, RackTrackerConfig, readonly
from companion.vision.rack.tracker_maps import TrackerMaps
from companion.vision.rack.tracker_solve import TrackerSolve

__all__ = ["RackEstimate", "RackTracker", "RackTrackerConfig"]


class RackTracker(TrackerSolve, TrackerMaps):
    """Stateful tracker; call `reset(T_rack_cam)` then `track(image, stamp_s)` for each frame."""

    # ------------------------------------------------------------------ public API
    def reset(
        self, T_rack_cam: Any, cumulative_gaps: Any = None, position_std_m: float | None = None,
        rotation_std_rad: float | None = None,
    ) -> None:
        """Re-initialize at pose `T_rack_cam` (4x4, camera in rack frame); forget texture and polarity.

        `position_std_m` / `rotation_std_rad`: how far off that pose may be (1 sigma; default the
        config's `reset_prior_*`); they set the first frame's prior and its search range.
        """
        self._T = check_transform(T_rack_cam, "T_rack_cam").copy()
        if cumulative_gaps is not None:
            g = np.asarray(cumulative_gaps, dtype=np.float64).ravel()
            if g.size != self._n_gaps:
                raise InputError(f"cumulative_gaps: expected {self._n_gaps} values, got {g.size}")
            self._gaps = g.copy()
        else:
            self._gaps = self.model.cumulative_gaps.copy()
        cfg = self.config
        self._start_std = (self._positive(position_std_m, "position_std_m", cfg.reset_prior_translation_m),
                           self._positive(rotation_std_rad, "rotation_std_rad", cfg.reset_prior_rotation_rad))
        self._lost_frames = 0
        self._relocking = False
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

    @staticmethod
    def _positive(value: float | None, name: str, default: float) -> float:
        if value is None:
            return default
        v = float(value)
        if not (np.isfinite(v) and v > 0.0):
            raise InputError(f"{name}: must be positive, got {value}")
        return v

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
        n_gap = self._n_gaps if self._gaps_solved() else 0
        gap_std = np.sqrt(np.maximum(np.diag(cov_full)[6 : 6 + n_gap], 0.0)) if n_gap else np.zeros(self._n_gaps)
        # ---- state update
        dt_s = None if self._last_stamp is None else float(stamp_s) - self._last_stamp
        if ok:
            if dt_s is not None and 0.0 < dt_s <= 0.5:
                self._velocity = se3.log(se3.inverse(self._T) @ T) / dt_s
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
            self._relocking = False
            self._update_polarity(last["samples"], last["meas"].sign, agree)
            self._update_profiles(last["samples"], last["meas"].inner, agree)
            self._update_texture(gray, img_raw, T, pipes, tex_uv, last["samples"])
            self._update_ground(gray, T, last, cov_full)
        else:
            self._T = T_pred
            self._velocity = np.zeros(6)
            self._lost_frames += 1
            if self._initialized and not cfg.estimate_gaps and 0 < cfg.relock_after_frames <= self._lost_frames:
                # Lost for a while: search wide again from the last pose, as after a rough reset. Not
                # with estimated gaps: with a wrong model (gaps confidently wrong, 2026-11-24 stress
                # bench) the wide search locks onto grating bars and shadows and runs away.
                self._initialized = False
                self._start_std = (cfg.relock_prior_translation_m, cfg.relock_prior_rotation_rad)
                self._relocking = True
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
            T_rack_cam=readonly(self._T),
            covariance=readonly(cov),
            gaps=readonly(self._gaps),
            gaps_std_m=readonly(gap_std),
            num_edge_points=n_agree,
            num_edge_samples=n_samples,
            num_texture_points=n_tex,
            residual_px=residual_px,
            iterations=it_done,
            status=status,
            condition=float(cond),
            edge_bias_px=readonly(self._edge_bias),
        )

