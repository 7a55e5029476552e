"""The ground odometer's per-pair solve: match two frames, gate, reject outliers, closed form and refinement,
giving the increment (dx, dy, dyaw) NED-aligned (metres, rad) with its covariance."""

from __future__ import annotations

import math

import numpy as np

from companion.checks import FloatArray
from companion.vision.ground import tilt_bias
from companion.vision.ground.closed_form import gen_to_increment, solve_gen, solve_sma
from companion.vision.ground.matching import speed_gate
from companion.vision.ground.odometer_frames import GroundOdometerFrames
from companion.vision.ground.odometer_state import _Anchor, _Frame
from companion.vision.ground.refine_exact_tilt import refine_tilt_exact
from companion.vision.ground.refine_rigid import RefineResult, evaluate, refine
from companion.vision.ground.refine_tilt_fields import refine_with_tilt, tilt_fields
from companion.vision.ground.robust import mad_trim, ransac_rigid, residual_norms


class GroundOdometerSolve(GroundOdometerFrames):
    """Motion between two frames of a `GroundOdometer` (`_relative`) and its stages."""

    # ------------------------------------------------------------------ stages
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
