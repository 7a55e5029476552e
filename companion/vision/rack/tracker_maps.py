"""Upkeep of what the rack tracker carries between frames: limb polarities and profiles, ground points, texture map."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.vision.rack.along_pipe import edges_see_along
from companion.vision.rack.edge_pitch import (
    edge_pitch_step_rad,
    rotate_about_centre,
    rotate_on_pipes,
    rotation_about_rack_x,
)
from companion.vision.rack.ground import (
    detect_ground_points,
    ground_mask,
    on_ground,
    pipe_silhouettes,
    plane_points,
)
from companion.vision.rack.ground_height import (
    ANCHOR_FRAMES,
    CONVERGED_STD_M,
    SETTLE_FRAMES,
    fit_ground_height,
    off_ground,
    update_ground_height,
)
from companion.vision.rack.ground_height_vertical import SETTLE_FRAMES_VERTICAL, fit_ground_height_vertical
from companion.vision.rack.limbs import LimbSamples
from companion.vision.rack.model import PipeArrays
from companion.vision.rack.templates import align_templates, sample_patches, tangent_plane_warps
from companion.vision.rack.texture import detect_points, track_points
from companion.vision.rack.tracker_state import TrackerState


class TrackerMaps(TrackerState):
    """Per-limb learning, the ground reference and the texture map, updated on accepted frames."""

    def _feed_edge_pitch(self, last: dict[str, Any], T: FloatArray, pipes: PipeArrays) -> FloatArray:
        """The accepted pose `T` after `edge_pitch_gain` of the edges' own pitch step (`edge_pitch.py`), with the
        texture points, their references and the ground rays and anchors rotated with it about the camera centre.

        Only on a vision-only frame (no attitude prior: the filtered gravity holds pitch absolutely, and better),
        with the gaps held (estimated gaps bias the limbs' pitch), and when the edges do not see along the pipes
        (with a crossing pipe in view the frame's own solve weighs the edges' pitch in full). Otherwise `T`.
        """
        cfg = self.config
        n_edge = int(last["n_edge"])
        if cfg.edge_pitch_gain <= 0.0 or n_edge == 0 or self._gravity is not None or cfg.estimate_gaps:
            return T
        A, w = last["A"], last["w"]
        if edges_see_along(A[:n_edge, :3], w[:n_edge], T[:3, :3]):
            return T
        step = edge_pitch_step_rad(A, w, last["r_post"], n_edge, T[:3, :3])
        if not np.isfinite(step):
            return T
        R = rotation_about_rack_x(cfg.edge_pitch_gain * step)
        c = T[:3, 3].copy()
        out = T.copy()
        out[:3, :3] = R @ T[:3, :3]
        tm = self._texture
        if len(tm):
            tm.offset_rack = rotate_on_pipes(tm.offset_rack, tm.pipe, pipes, c, R)
            tm.ref_R = np.einsum("ij,njk->nik", R, tm.ref_R)
            tm.ref_o = rotate_about_centre(tm.ref_o, c, R)
        self._ground_d = self._ground_d @ R.T  # rays from this camera centre (`_ground_o`)
        self._anchor_o = rotate_about_centre(self._anchor_o, c, R)
        self._anchor_d = self._anchor_d @ R.T
        return out

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

    def _ground_lk_inputs(
        self, gray: np.ndarray[Any, np.dtype[np.uint8]], T_pred: FloatArray
    ) -> tuple[FloatArray, FloatArray, Any, np.ndarray[Any, np.dtype[np.uint8]]] | None:
        """What Lucas-Kanade needs for last frame's ground points: (their pixels in the previous image (K, 2),
        the predicted pixels at pose `T_pred` (K, 2), which have a finite plane point (K,), the image to track
        into: `gray` itself unless brought to the previous image's mean level); None without ground points."""
        cfg = self.config
        if cfg.ground_points <= 0 or self._prev_gray is None or self._z_g is None or not self._ground_uv.shape[0]:
            return None
        X, _ = plane_points(self._ground_o, self._ground_d, self._z_g)
        fin = np.all(np.isfinite(X), axis=1)
        guess = self.camera.project((np.where(fin[:, None], X, 0.0) - T_pred[:3, 3]) @ T_pred[:3, :3])
        guess = np.where((fin & np.all(np.isfinite(guess), axis=1))[:, None], guess, self._ground_uv)
        # Exposure steps: bring this image to the previous one's mean level first (LK assumes constant brightness).
        m_prev = float(self._prev_gray[::8, ::8].mean()) if self._prev_gray_mean is None else self._prev_gray_mean
        m_cur = float(gray[::8, ::8].mean())
        self._gray_mean = m_cur  # `_prev_gray`'s mean next frame (it is a copy of `gray`)
        cur = gray
        if m_cur > 1.0 and abs(m_prev / m_cur - 1.0) > 0.03:
            cur = np.asarray(cv2.convertScaleAbs(gray, alpha=m_prev / m_cur), dtype=np.uint8)
        return self._ground_uv, guess, fin, cur

    def _track_ground(
        self, gray: np.ndarray[Any, np.dtype[np.uint8]], T_pred: FloatArray,
        lk_in: tuple[FloatArray, FloatArray, Any, np.ndarray[Any, np.dtype[np.uint8]]] | None,
        lk_out: tuple[FloatArray, Any] | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None:
        """Lucas-Kanade of last frame's ground points into this image, seeded by their predicted projection:
        (ray origin (3,), ray directions (K, 3), pixels (K, 2), frames each has fitted the plane (K,)).

        `lk_in` from `_ground_lk_inputs`; `lk_out` (pixels (K, 2), ok (K,)) when the caller already tracked
        them (in one call with the texture points: each point's result does not depend on the others).
        """
        self._anchor_tracked = None
        if lk_in is None or self._prev_gray is None:
            return None
        cfg = self.config
        uv_prev, guess, fin, cur = lk_in
        if lk_out is None:
            lk_out = track_points(self._prev_gray, cur, uv_prev, guess, cfg.lk_window_px, cfg.lk_levels)
        uv, ok = lk_out
        ok = ok & fin & self.camera.in_image(uv, 4.0)
        # Points a pipe moves over between the frames (parallax; a pipe entering the view) would be
        # tracked on its cladding: keep those clear of the pipes at the predicted pose.
        pipes = self._pipe_arrays(self._gaps)
        polygons = pipe_silhouettes(T_pred, self.camera, pipes, self._limb_lines(T_pred[:3, 3], pipes))
        mask = ground_mask(gray.shape[:2], polygons, cfg.margin_px)
        self._silhouettes_pred = (polygons, mask)
        ok &= on_ground(uv, mask)
        if self._anchor_o.shape[0] == ok.size:
            self._anchor_tracked = (self._anchor_o[ok], self._anchor_d[ok], self._anchor_age[ok])
        return self._ground_o, self._ground_d[ok], uv[ok], self._ground_age[ok]

    def _update_ground(
        self, gray: np.ndarray[Any, np.dtype[np.uint8]], T: FloatArray, last: dict[str, Any], cov_full: FloatArray,
        ground_held: bool,
    ) -> None:
        """Keep the ground points that fit, add new ones, store their rays from this (accepted) pose;
        `ground_held`: too few texture points measured this frame's along-pipe travel (the ground's flow did)."""
        cfg = self.config
        if cfg.ground_points <= 0:
            return
        keep_uv = np.zeros((0, 2))
        keep_age = np.zeros(0)
        anchors: tuple[FloatArray, FloatArray, FloatArray] | None = None
        i_z = int(last["i_z"])
        if i_z >= 0:
            # The ground lies below the pipes' support plane, and it does not move: a frame's estimate may
            # move z_g by at most half its standard deviation (a few bad ground points, or a roll / slide
            # error leaking into it, otherwise carry it metres within a second: stress bench, p3 fast).
            if cfg.ground_height_m is None:
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
                keep_age = last["ground_age"][ok] + 1.0
                if self._anchor_tracked is not None and self._anchor_tracked[0].shape[0] == ok.size:
                    a_o, a_d, a_age = (a[ok] for a in self._anchor_tracked)
                    on_plane = self._fuse_ground_height(T, keep_uv, a_o, a_d, ground_held)
                    keep_uv, keep_age = keep_uv[on_plane], keep_age[on_plane]
                    anchors = (a_o[on_plane], a_d[on_plane], a_age[on_plane])
        # the predicted pose's silhouettes and ground mask (computed for tracking) are close enough for the margin
        if self._silhouettes_pred is None:
            polygons = pipe_silhouettes(T, self.camera, self._pipe_arrays(self._gaps))
            mask = ground_mask(gray.shape[:2], polygons, cfg.margin_px)
        else:
            polygons, mask = self._silhouettes_pred
        self._silhouettes_pred = None
        if keep_uv.shape[0]:
            # A pipe sweeps over the ground next to it as the camera moves (parallax): a ground point at
            # its limb is tracked onto the pipe's cladding and pulls z_g up towards the pipes. Drop
            # points that come within the margin of a pipe.
            on = on_ground(keep_uv, mask)
            keep_uv, keep_age = keep_uv[on], keep_age[on]
            if anchors is not None:
                anchors = (anchors[0][on], anchors[1][on], anchors[2][on])
        if cfg.ground_height_m is not None:
            # A known ground height is a measurement on every frame, not a start: beams, a deck or
            # shadows at other depths would otherwise walk the estimate away from it.
            self._z_g, self._z_g_var = float(cfg.ground_height_m), float(cfg.ground_height_std_m) ** 2
        elif self._z_g is None:
            # First guess: the ground twice as far below the pipes' tops as the camera is above them (weak).
            top = 2.0 * float(np.max(self.model.radii))
            self._z_g = top - 2.0 * max(float(T[2, 3]) - top, 0.5)
            self._z_g_var = 2.0**2
        need = cfg.ground_points - keep_uv.shape[0]
        new = np.zeros((0, 2))
        # detection (a Shi-Tomasi pass over the image) every `detect_every` frames, unless half are gone
        due = self._frames % cfg.detect_every == 0 or keep_uv.shape[0] < cfg.ground_points // 2
        if need >= max(3, cfg.ground_points // 5) and due:
            new = detect_ground_points(gray, polygons, keep_uv, need,
                                       cfg.texture_min_distance_px, cfg.margin_px, cfg.ground_min_corner_ratio, mask)
        uv = np.vstack([keep_uv, new])
        self._ground_uv = uv
        self._ground_age = np.concatenate([keep_age, np.zeros(new.shape[0])])
        self._ground_o = T[:3, 3].copy()
        self._ground_d = self.camera.unproject(uv) @ T[:3, :3].T if uv.shape[0] else np.zeros((0, 3))
        self._update_anchors(T, anchors, keep_uv.shape[0], new.shape[0])

    def _update_anchors(
        self, T: FloatArray, kept: tuple[FloatArray, FloatArray, FloatArray] | None, n_keep: int, n_new: int
    ) -> None:
        """Anchor rays of this frame's ground points (`_ground_uv`: the `n_keep` kept ones, then `n_new` new ones):
        kept anchors age by a frame; new points, and points anchored `ANCHOR_FRAMES` ago (the attitude error
        between two poses grows with the time between them), are anchored at this pose."""
        if kept is None:
            kept = (np.zeros((n_keep, 3)), np.zeros((n_keep, 3)), np.full(n_keep, np.inf))
        a_o = np.vstack([kept[0], np.zeros((n_new, 3))])
        a_d = np.vstack([kept[1], np.zeros((n_new, 3))])
        a_age = np.concatenate([kept[2] + 1.0, np.full(n_new, np.inf)])
        fresh = a_age > ANCHOR_FRAMES
        a_o[fresh] = T[:3, 3]
        a_d[fresh] = self._ground_d[fresh]
        a_age[fresh] = 0.0
        self._anchor_o, self._anchor_d, self._anchor_age = a_o, a_d, a_age

    def _fuse_ground_height(
        self, T: FloatArray, uv: FloatArray, anchor_o: FloatArray, anchor_d: FloatArray, ground_held: bool
    ) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """Update the long-baseline ground height (`ground_height.py`; on a `ground_held` frame without a sideways
        baseline `ground_height_vertical.py`) with this frame's kept points, hand it to the
        solver when surer than the frame-to-frame z_g, and return which points (K,) lie on the ground (all of them
        until the height is known to `CONVERGED_STD_M`).

        The solver gets it with a standard deviation of at least `ground_height_floor_m`: the fit followed each
        run's slow roll drift (a relative roll between two poses and a wrong height make nearly the same flow
        across the pipes, 0-12 % on the stress bench), and held tighter that error turned into roll and sideways
        slide. Vision only, the fit now estimates that roll beside the height (`fit_ground_height`); the floor
        is kept as it was.
        """
        cfg = self.config
        keep = np.ones(uv.shape[0], dtype=bool)
        # A vertical fit may run on a ground-held frame, and only it may start early (a full anchor window); with
        # it switched off nothing fits before the across fit's settling, so the filter does not start before then.
        vertical_fit = ground_held and cfg.ground_height_vertical_m > 0.0
        if cfg.ground_height_baseline_m <= 0.0 or cfg.ground_height_m is not None or self._z_g is None \
                or self._frames < (SETTLE_FRAMES_VERTICAL if vertical_fit else SETTLE_FRAMES):
            return keep
        if self._zf is None:
            self._zf, self._zf_var, self._zf_rejected = float(self._z_g), 2.0**2, 0
        # Vision only, the relative roll of the two poses is the fit's to estimate (few parallel pipes trade it
        # with a sideways slide); with an attitude prior the filtered gravity holds it, and estimating it too
        # only loosened the height (docs/rack.md, "Twenty-fifth session on #14").
        fit = None
        if self._frames >= SETTLE_FRAMES:
            fit = fit_ground_height(T, self.camera, anchor_o, anchor_d, uv, self._zf, cfg.ground_height_baseline_m,
                                    estimate_rotation=self._gravity is None)
        if fit is not None:
            self._zf_across = True
        elif vertical_fit:
            # No baseline across the pipes, and nothing but the ground measures the travel along them: the
            # camera's vertical motion, with the poses' along-pipe positions left free (`ground_height_vertical.py`).
            fit = fit_ground_height_vertical(T, self.camera, anchor_o, anchor_d, uv, self._zf,
                                             cfg.ground_height_vertical_m)
        if fit is not None:
            self._zf, self._zf_var, self._zf_rejected = update_ground_height(self._zf, self._zf_var, fit,
                                                                             self._zf_rejected)
        self._zf_var += cfg.ground_height_walk_m**2
        handed_var = max(self._zf_var, cfg.ground_height_floor_m**2)
        # A height from vertical fits alone stands in for the ground's depth only while the ground carries the
        # along-pipe travel; once texture points measure it, the solver's own z_g is better (and the along-pipe
        # rescale needs it: `along_rescale.py`).
        if handed_var < self._z_g_var and (self._zf_across or ground_held):
            self._z_g, self._z_g_var = min(self._zf, 0.0), handed_var
        if self._zf_var < CONVERGED_STD_M**2:
            keep = ~off_ground(T, self.camera, anchor_o, anchor_d, uv, self._zf, cfg.gate_px)
        return keep

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
        # Per column, bincount adds the samples in order into zeros: np.add.at's sums, in 2/3 of its time.
        inner_g = inner[g]
        acc = np.stack([np.bincount(limbs, weights=inner_g[:, j], minlength=n_l) for j in range(inner_g.shape[1])],
                       axis=1)
        seen = cnt >= 3
        mean = acc[seen] / cnt[seen, None]
        norm = np.linalg.norm(mean, axis=1, keepdims=True)
        mean = mean / np.maximum(norm, 1e-9)  # unit norm: the reference; a weak norm = inconsistent shapes
        fresh = seen & ~np.any(self._profiles != 0.0, axis=1)
        rate = np.where(fresh[seen], 1.0, self.config.edge_profile_rate)[:, None]
        upd = (1.0 - rate) * self._profiles[seen] + rate * mean * np.minimum(norm, 1.0)
        self._profiles[seen] = upd

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
            tm.age += 1
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
            cfg.texture_min_incidence_cos, cfg.texture_min_corner_ratio, cfg.texture_crossing_edge_fraction,
        )
        self._detect_short = new_pipe.size < need
        if new_pipe.size:
            tm.add(new_pipe, new_off, new_uv, sample_patches(img_f, new_uv, half_ref), T)
