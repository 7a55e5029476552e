"""The rack tracker's per-frame solve: render limbs, search edges, IRLS on SE(3) (and gaps, bias, z_g)."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.geometry import se3
from companion.vision.rack.along_pipe import edges_see_along
from companion.vision.rack.edges import refine_silhouette, search_edges
from companion.vision.rack.ground import (
    ground_rows,
    plane_points,
)
from companion.vision.rack.limbs import LimbSamples, sample_limbs
from companion.vision.rack.model import PipeArrays
from companion.vision.rack.motion import (
    gap_jacobian,
    gated_residual_variance,
    gravity_rows,
    median_1d,
    pose_jacobian,
    robust_weights,
    solve_normal_equations,
    strength_weights,
)
from companion.vision.rack.tracker_state import TrackerState


class TrackerSolve(TrackerState):
    """Iterated solve of one frame (eq. 8-18, 23-29 of the paper) and its rows."""

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

    def _solve_first(
        self,
        T: FloatArray,
        gaps: FloatArray,
        img_raw: np.ndarray[Any, np.dtype[np.float32]],
        img_f: np.ndarray[Any, np.dtype[np.float32]],
        tex_uv: FloatArray,
    ) -> dict[str, Any]:
        """A first frame's solve from pose T and cumulative gaps: the four limb-polarity hypotheses (each
        side of every pipe brighter or darker than what is beside it), the one with most agreeing edges.
        After a reset that kept the appearance, one solve with the polarity learnt before it: the four cost
        four times the time (85 against 23 ms at 360x240), and on a loaded companion computer that made the
        next frame late, which asked for the next re-seed (ArduCopter SITL tier, 2026-12-03)."""
        if self._appearance_kept:
            return self._solve(T, gaps, img_raw, img_f, tex_uv, True, self._known_polarity(), None)
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
        return best

    def _solve(
        self,
        T: FloatArray,
        gaps: FloatArray,
        img_raw: np.ndarray[Any, np.dtype[np.float32]],
        img_f: np.ndarray[Any, np.dtype[np.float32]],
        tex_uv: FloatArray,
        first: bool,
        polarity: FloatArray,
        ground: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None,
    ) -> dict[str, Any]:
        """Iterate render -> search -> IRLS -> exp update from pose T and gaps; returns the final state.

        `ground`: (ray origin (3,), ray directions (K, 3), current pixels (K, 2), frames fitted (K,)) of
        the ground points (rack frame), or None; with them the ground height z_g is the last parameter.
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
        if n_gap and not first and np.all(np.isfinite(self._gaps_var)):
            # The gaps are constants: anchor them at the last frame's, in the solver's information scale
            # (the posterior is inv(H) * scale2 * inflation), as z_g below.
            anchor_info = anchor_info.copy()
            anchor_info[6:i_bias] = self._scale2 * cfg.covariance_inflation / self._gaps_var
        if has_ground:
            prior, anchor_info = prior.copy(), anchor_info.copy()
            prior[i_z] = 1.0
            # In the solver's information scale (the posterior is inv(H) * scale2 * inflation, see the
            # covariance): with 1 / var here a frame that does not observe z_g multiplied its variance
            # by scale2 * inflation (~2-4 on textured grounds), and z_g wandered off by metres.
            anchor_info[i_z] = self._scale2 * cfg.covariance_inflation / self._z_g_var
        ground_trust = None  # per ground row, fixed over the iterations
        if has_ground and ground is not None and cfg.ground_trust_frames > 1 and \
                np.count_nonzero(ground[3] >= cfg.ground_trust_frames - 1) >= 3:
            # A new point earns its weight by fitting the plane for `ground_trust_frames` frames: corners
            # on an unmodelled structure nearer the camera (an overhead beam) move faster than the
            # ground's and, many at once as it comes into view, carried the along-pipe position with
            # them (stress bench, docs/rack.md). Only while three points have earned it: after a lost
            # stretch (all points new) holding them all back let the along-pipe position drift.
            ground_trust = np.repeat(np.minimum(1.0, (ground[3] + 1.0) / cfg.ground_trust_frames), 2)
        # Per texture row: 0 while the texture is muted, or for a new point on probation (`texture_check.py`).
        tex_factor = np.repeat(self._texture_check.point_weights(self._texture.age, self._frames), 2) \
            if tex_uv.shape[0] else np.zeros(0)
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
        dist_sigma = cfg.edge_distance_sigma_px if cfg.edge_distance_sigma_px > 0 else None
        for it in range(n_iter):
            it_done = it + 1
            if first:
                rng_px = max(cfg.search_range_px, round(init_px * cfg.init_shrink**it))
            else:
                rng_px = cfg.search_range_px
            samples = sample_limbs(T, cam, pipes, cfg.samples_per_limb, cfg.margin_px, 12.0, 0.1,
                                   cfg.occlusion_margin_px, self._limb_lines(T[:3, 3], pipes))
            pol = polarity[samples.limb]
            img_it = img_f
            thr = cfg.edge_threshold
            coarse = first and rng_px > 2 * cfg.search_range_px
            if coarse:
                sigma = max(cfg.blur_sigma_px, rng_px / 16.0)
                img_it = np.asarray(cv2.GaussianBlur(img_raw, (0, 0), sigma), dtype=np.float32)
                thr = cfg.edge_threshold * min(1.0, 1.5 / sigma)  # blurred steps have weaker gradients
            near = it > 0 and rng_px <= cfg.search_range_px  # the tracking range, from the second iteration
            meas = search_edges(img_it, samples.uv, samples.normal_px, pol, rng_px, thr,
                                prior_sigma_px=dist_sigma if near else None,
                                innermost_ratio=cfg.edge_innermost_ratio if near else 0.0,
                                tangent_offset_px=cfg.edge_tangent_px,
                                inner_ref=self._profiles[samples.limb] if cfg.edge_profile_px > 0 else None)
            offset_px = meas.offset_px
            if cfg.edge_silhouette_px > 0 and not coarse:
                offset_px = refine_silhouette(img_raw, samples.uv, samples.normal_px, offset_px,
                                              cfg.edge_silhouette_px, cfg.edge_silhouette_px - 1,
                                              max_rel_rms=cfg.edge_silhouette_max_rms)
            # Every row (edges, texture, ground, gravity) in one array, filled in place: no stacking copies.
            f = np.asarray(meas.found, dtype=bool)
            n_edge = int(f.sum())
            n_et = n_edge + 2 * tex_uv.shape[0]
            n_w = n_et + (2 * ground[1].shape[0] if has_ground and ground is not None else 0)
            n_rows = n_w + (3 if self._gravity is not None else 0)
            A = np.zeros((n_rows, n_par))
            r = np.empty(n_rows)
            A_e = A[:n_edge]
            self._edge_rows(samples, offset_px, f, T, gaps, A_e, r[:n_edge])
            if cfg.estimate_edge_bias:
                side = samples.limb[f] % 2
                A_e[np.arange(side.size), i_bias + side] = 1.0
                r[:n_edge] -= bias[side]
            self._texture_rows(T, pipes, tex_rack, tex_uv, A[n_edge:n_et], r[n_edge:n_et])
            gate = None
            if it > 0:
                gate = max(cfg.gate_px, float(rng_px)) if first else cfg.gate_px
            if has_ground:
                assert ground is not None and self._z_g is not None
                X, dXdz = plane_points(ground[0], ground[1], self._z_g + moved[i_z])
                A_g7, r_g = ground_rows(T, cam, X, dXdz, ground[2])
                A_g = A[n_et:n_w]
                A_g[:, :6] = A_g7[:, :6]
                if cfg.ground_along_only:
                    e_y = np.zeros(6)
                    e_y[:3] = T[:3, :3][1, :]  # the rack's +y in the camera frame (translation part)
                    A_g[:, :6] = np.outer(A_g[:, :6] @ e_y, e_y)
                A_g[:, i_z] = A_g7[:, 6]
                r[n_et:n_w] = r_g
            w = np.empty(n_rows)
            kind = cfg.robust
            if kind == "tukey" and (coarse if first else it == 0 and not self._velocity_known):
                # Without a measured velocity the prediction misses any motion, which then shows as a minority
                # of large residuals (a crossing pipe's limbs when the drone sets off along the pipes) that
                # must still pull: the biweight would give them none, and the position along the pipes would
                # stay behind for good. The paper's weights do, in this first iteration. The same in a first
                # frame's coarse search: there the biweight locked onto whichever edges agreed first and ran
                # away by metres from a relock 12 cm off (tests/rack/test_tracker_relock.py).
                kind = "paper"
            w[:n_w] = robust_weights(r[:n_w], kind, cfg.nu_px, gate)
            if kind == "tukey" and cfg.robust_max_scale_px > 0.0 and n_edge:
                # The edge rows with the scale capped (the texture and ground rows keep the frame's scale).
                w[:n_edge] = robust_weights(r[:n_w], kind, cfg.nu_px, gate, cfg.robust_max_scale_px)[:n_edge]
            if cfg.edge_strength_weight > 0.0 and n_edge:
                w[:n_edge] *= strength_weights(meas.strength[f], cfg.edge_strength_weight)
            texture_weight = cfg.texture_weight
            if cfg.texture_weight_crossing is not None and not cfg.estimate_gaps and n_edge and n_et > n_edge \
                    and edges_see_along(A[:n_edge, :3], w[:n_edge], T[:3, :3]):
                texture_weight = cfg.texture_weight_crossing  # the edges hold the valley (config docstring)
            w[n_edge:n_et] *= texture_weight * tex_factor
            w[n_et:n_w] *= cfg.ground_weight
            if ground_trust is not None:
                w[n_et:n_w] *= ground_trust
            if self._gravity is not None:
                # Gravity rows, not robustified: information 1/std^2 in the solver's scale (the
                # covariance is inv(H) * scale2 * inflation, so H_prior = scale2 * inflation / std^2).
                r[n_w:], A[n_w:, :6] = gravity_rows(T[:3, :3], self._gravity[0])
                w[n_w:] = self._gravity[1]
                if not self._scale2_measured:
                    # No frame accepted since the reset: its scale (0.5) is a guess, several times the
                    # ~0.1 of a converged solve, and it made the prior outweigh the limbs on the first
                    # frame (a 1 deg prior error pulled roll and slide off: bench/rack_acquire_ceiling.py).
                    # Weigh the prior with this frame's own weighted residual variance instead, over the
                    # rows within the tracking gate (the first frame's wide search lets in far outliers).
                    r_d = r[:n_w]
                    w[n_w:] *= gated_residual_variance(w[:n_w], r_d, r_d, cfg.gate_px, 6) / self._scale2
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
                    "H_data": H_data, "n_edge": n_edge, "n_et": n_et,
                    "z_g": (self._z_g + moved[i_z]) if has_ground else self._z_g, "i_z": i_z if has_ground else -1,
                    "ground_uv": ground[2] if has_ground and ground is not None else None,
                    "ground_age": ground[3] if has_ground and ground is not None else None,
                    "n_tex_weighted": int(np.count_nonzero(tex_factor)) // 2}
            # |x[:3]| and |x[3:6]| as np.linalg.norm computes them (sqrt of the dot product).
            x_v, x_w = x[:3], x[3:6]
            small = bool(math.sqrt(x_v.dot(x_v)) < cfg.stop_translation_m
                         and math.sqrt(x_w.dot(x_w)) < cfg.stop_rotation_rad)
            # Also stop when the update moves the rendered edges by less than stop_px (median).
            small = small or bool(n_edge > 0 and median_1d(np.abs(A_e @ x)) < cfg.stop_px)
            small = small and it + 1 >= cfg.min_iterations
            if small and (not first or rng_px <= cfg.search_range_px):
                break
        last["H"] = last["H_data"] + np.diag(prior)  # the final normal matrix (only the last iteration's is used)
        # The gaps are carried by the tracker itself: their posterior must include their anchor, or each
        # frame's variance is that one frame's and the estimate never accumulates (the pose's covariance
        # leaves its motion prior out on purpose: it is a measurement for the daemon's filter). Not z_g:
        # accumulated, its variance shrank to centimetres at wrong heights (beams, the deck; stress bench
        # median cell 2.61 -> 4.55 cm, docs/rack.md), so it keeps each frame's variance plus its walk.
        carry = np.zeros(n_par)
        if n_gap and not first:
            carry[6:i_bias] = anchor_info[6:i_bias]
        last["carry_info"] = carry
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

    def _edge_rows(
        self, samples: LimbSamples, offset: FloatArray, f: Any, T: FloatArray, gaps: FloatArray,
        A: FloatArray, r: FloatArray,
    ) -> None:
        """Edge rows of the found samples `f` (n,) into `A` (n, n_par) (zero on entry) and residuals into `r` (n,)."""
        J6 = pose_jacobian(samples.J_uv_pcam[f], samples.p_cam[f])  # (n, 2, 6)
        nrm = samples.normal_px[f]
        A[:, :6] = np.einsum("nij,ni->nj", J6, nrm)  # σ = ξᵀ n (eq. 15)
        if self.config.estimate_gaps and self._n_gaps:
            gi = self._pipe_arrays(gaps).gap_index[samples.pipe[f]]
            has = gi >= 0
            Jg = gap_jacobian(samples.J_uv_pcam[f][has], T[:3, :3].T)
            A[np.flatnonzero(has), 6 + gi[has]] = np.einsum("ni,ni->n", Jg, nrm[has])
        r[:] = offset[f]

    def _texture_rows(
        self, T: FloatArray, pipes: PipeArrays, p_rack: FloatArray, tex_uv: FloatArray, A: FloatArray, r: FloatArray
    ) -> None:
        """Rows of the K texture points into `A` (2K, n_par) (zero on entry) and residuals into `r` (2K,).

        Points behind the camera get zero rows, as the ground's do: a first frame's solve with no limb in
        reach (a relock) can carry the pose far enough for that, and their NaN projection would otherwise
        poison the normal equations (docs/rack.md, "Twenty-first session").
        """
        k = tex_uv.shape[0]
        if k == 0:
            return
        p_cam = (p_rack - T[:3, 3]) @ T[:3, :3]
        front = p_cam[:, 2] > 1e-3
        if not front.all():
            p_cam = np.where(front[:, None], p_cam, np.array([0.0, 0.0, 1.0]))
        uv, J = self.camera.project_with_jacobian(p_cam)
        if not front.all():
            J[~front] = 0.0
            uv[~front] = tex_uv[~front]
        A[:, :6] = pose_jacobian(J, p_cam).reshape(2 * k, 6)
        if self.config.estimate_gaps and self._n_gaps:
            gi = pipes.gap_index[self._texture.pipe]
            Jg = gap_jacobian(J, T[:3, :3].T)  # (k, 2)
            for c in range(2):
                rows = 2 * np.arange(k) + c
                has = gi >= 0
                A[rows[has], 6 + gi[has]] = Jg[has, c]
        r[:] = (tex_uv - uv).reshape(-1)
