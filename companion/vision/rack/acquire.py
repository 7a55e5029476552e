"""Rack acquisition: the camera pose over a pipe-rack from one image, without a start pose.

`acquire_rack(image, model, camera, prior)` finds straight edges (LSD) and the pipes' direction
(a vote under the autopilot's roll and pitch), then proposes camera positions in the rack's
cross-section two ways: by sweeping the lateral position against the image's edge profile across
the pipe lines (`acquire_profile`: every placement of any subset of the pipes, either direction
of travel, whatever the limbs' shading) and by pairing line segments into pipes by the width the
model predicts at the measured height (`acquire_match`). The best proposals are refined and
scored with the tracker's own edge measurement (`acquire_verify`); the along-pipe position y
comes from a crossing pipe when one is in view and from the prior otherwise. `confident` is true
only when the best hypothesis is unambiguous: a wrong lock is worse than no lock.

Frames: `rack` (the paper's P, z up, pipes along +y), `cam` (OpenCV optical), `body` (FRD),
`ned`. `T_rack_cam` is the camera pose in the rack frame. Covariances are those of a right
perturbation in the camera frame, twist (v, w) in (m, rad), as `RackEstimate.covariance`.
Pure: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.errors import InputError
from companion.geometry import se3
from companion.vision.rack.acquire_decide import credible, decide, distinct, good_pipes, num_limbs_ok
from companion.vision.rack.acquire_lines import (
    LimbClusters,
    Segments,
    crossing_y_candidates,
    detect_segments,
    direction_candidates,
    downscale,
    image_theta_range,
    limb_clusters,
    refine_direction,
    visible_length_px,
)
from companion.vision.rack.acquire_match import section_hypotheses
from companion.vision.rack.acquire_profile import (
    PencilProfile,
    image_gradient,
    pencil_profile,
    profile_scores,
    refine_on_peaks,
    sweep_section,
)
from companion.vision.rack.acquire_types import (
    AcquisitionConfig,
    AcquisitionPrior,
    AcquisitionResult,
    RackHypothesis,
)
from companion.vision.rack.acquire_verify import (
    EdgeCheck,
    check_poses,
    pose_covariance,
    subset_pipes,
)
from companion.vision.rack.model import PipeArrays, RackModel

__all__ = ["AcquisitionConfig", "AcquisitionPrior", "AcquisitionResult", "RackHypothesis", "acquire_rack"]


@dataclass(frozen=True)
class _Candidate:
    """A proposed cross-section position (x, z, roll about the pipes) with what is needed to score it
    against the profile of its direction; its pose is formed only when it is checked."""

    x_m: float
    z_m: float
    alpha_rad: float
    sign: int
    polarity: int  # +1 pipes brighter than around them, -1 darker, 0 unknown
    prelim: float
    direction: int  # index into the per-direction tables

    def pose(self, dirs: list[_Direction], y_m: float) -> FloatArray:
        return _pose_from_section(self.x_m, self.z_m, self.alpha_rad, self.sign, dirs[self.direction].limbs, y_m)


@dataclass(frozen=True)
class _Direction:
    limbs: LimbClusters
    profile: PencilProfile
    theta_range: tuple[float, float]
    grid: FloatArray
    table: FloatArray

    def visible_length(self, theta: FloatArray) -> FloatArray:
        return np.asarray(np.interp(theta, self.grid, self.table))


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


def _pose_from_section(x_m: float, z_m: float, alpha_rad: float, sign: int, limbs: LimbClusters,
                       y_m: float) -> FloatArray:
    """T_rack_cam from a cross-section position: rack axes in the camera frame, camera at (x, y, z)."""
    ca, sa = np.cos(alpha_rad), np.sin(alpha_rad)
    ex = ca * limbs.e_x + sa * limbs.e_z
    ez = -sa * limbs.e_x + ca * limbs.e_z
    R_cam_rack = np.column_stack([sign * ex, sign * limbs.d, ez])
    U, _, Vt = np.linalg.svd(R_cam_rack)
    return se3.make((U @ Vt).T, np.array([x_m, y_m, z_m]))


def _explained(dirs: list[_Direction], poses: list[tuple[int, FloatArray, int]], x_axes: FloatArray,
               radii: FloatArray, cfg: AcquisitionConfig, footprint: bool = False) -> list[float]:
    """Share of its direction's profile peaks that each pose's limbs explain; `poses` (direction index,
    T_rack_cam, sign), scored one direction at a time. With `footprint`, of the peaks over each pose's
    footprint only (`profile_scores`' `footprint_pitches`, `cfg.footprint_pitches`)."""
    tol = max(round(cfg.sweep_tol_px / cfg.profile_bin_px), 1)
    out = [0.0] * len(poses)
    for k in sorted({p[0] for p in poses}):
        di = dirs[k]
        sel = [i for i, p in enumerate(poses) if p[0] == k]
        T = np.stack([poses[i][1] for i in sel])
        u = T[:, 2, :3]
        # The refined pose's roll about the pipes relative to the profile's basis (see _pose_from_section).
        alpha = np.array([np.arctan2(-(ui @ di.limbs.e_x), ui @ di.limbs.e_z) for ui in u])
        _, ex = profile_scores(di.profile, T[:, 0, 3].copy(), T[:, 2, 3].copy(),
                               np.array([float(poses[i][2]) for i in sel]), x_axes, radii, di.theta_range,
                               di.visible_length, tol, cfg.min_limb_px, alpha,
                               cfg.footprint_pitches if footprint else None)
        for i, e in zip(sel, ex, strict=True):
            out[i] = float(e)
    return out


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
    small = downscale(gray, cfg.line_scale)
    seg = detect_segments(gray, small, camera, cfg.line_scale, cfg.min_segment_px, cfg.min_contrast)
    R0 = prior.R_rack_cam(0.0 if prior.yaw_rad is None else prior.yaw_rad)
    up_cam = R0[2, :]  # rack +z in the camera frame (independent of yaw for a level rack)
    pipes_all = model.pipe_arrays()
    n_par = model.num_parallel
    par = subset_pipes(pipes_all, np.arange(n_par))
    x_axes, radii = par.starts[:, 0], par.radii
    dirs, cands, num_limbs = _propose(seg, small, camera, prior, cfg, up_cam, R0, x_axes, radii, f_px)
    if not cands:
        return AcquisitionResult((), False, "no pipe pattern found", int(seg.length_px.size), num_limbs)
    cands = _dedupe(sorted(cands, key=lambda c: -c.prelim), cfg.distinct_m)
    damping = np.array([1.0 / 0.05**2] * 3 + [1.0 / 0.02**2] * 3)
    # The autopilot's tilt against the edges: edge rows count 1 / (edge_noise² × inflation) each.
    up_weight = cfg.covariance_inflation * (cfg.edge_noise_px / cfg.attitude_std_rad) ** 2
    h_weight = cfg.covariance_inflation * (cfg.edge_noise_px / prior.height_std_m) ** 2
    checked: list[tuple[float, int, EdgeCheck, int]] = []
    rivals: list[tuple[float, int, FloatArray, int]] = []
    n_all = pipes_all.radii.size
    y_lo, y_hi = prior.y_m - 4.0 * prior.y_std_m, prior.y_m + 4.0 * prior.y_std_m
    img_f = gray.astype(np.float32)
    top = cands[0].prelim
    to_check = [c for c in cands[: cfg.max_checked] if c.prelim >= cfg.check_score_ratio * top]
    # The best proposal of the other direction of travel is always checked too: a rack (or the part
    # in view) that looks the same both ways must come out ambiguous, not as the first one found.
    for sign in {c.sign for c in cands} - {c.sign for c in to_check}:
        to_check.append(next(c for c in cands if c.sign == sign))

    def check(Ts: list[FloatArray], pols: list[FloatArray], extra: bool, polish: bool) -> list[EdgeCheck]:
        """`check_pose` of the poses side by side (all pipes when `extra`; the polish ranges when `polish`)."""
        return check_poses(img_f, camera, pipes_all if extra else par, Ts, pols,
                           cfg.polish_ranges_px if polish else cfg.check_ranges_px, cfg.samples_per_limb,
                           cfg.edge_threshold, cfg.inlier_px, cfg.margin_px, damping / 4.0 if polish else damping,
                           up_cam, up_weight, prior.height_m, h_weight,
                           silhouette=(cfg.silhouette_range_px if prior.height_m >= cfg.silhouette_min_height_m else 0,
                                       cfg.silhouette_max_rms))

    # Tracker polarity (+1: brighter outward) from the segments' pairing; from the sweep it is
    # unknown (0) and learnt limb by limb: a limb may be darker or brighter than the ground.
    T_cs = [c.pose(dirs, prior.y_m) for c in to_check]
    chks = check(T_cs, [np.full(n_par, -float(c.polarity)) for c in to_check], False, False)
    again: list[tuple[int, FloatArray, FloatArray]] = []
    for i, (c, T_c, chk) in enumerate(zip(to_check, T_cs, chks, strict=True)):
        if not credible(chk, cfg, prior, up_cam, n_par) and n_all > n_par:
            # A crossing pipe in view hides limbs and its own limbs cross theirs: place it (y from
            # the segments along it) and check again with every pipe.
            ys = crossing_y_candidates(seg, T_c, pipes_all, np.arange(n_par, n_all), y_lo, y_hi,
                                       cfg.direction_tol_rad, 0.03, 1)
            if ys.size:
                T_y = T_c.copy()
                T_y[1, 3] = ys[0]
                again.append((i, T_y, np.concatenate([np.full(n_par, -float(c.polarity)), np.zeros(n_all - n_par)])))
    if again:
        for (i, _, _), chk in zip(again, check([a[1] for a in again], [a[2] for a in again], True, False),
                                  strict=True):
            chks[i] = chk
    poses = [(c.direction, chk.T_rack_cam, c.sign) for c, chk in zip(to_check, chks, strict=True)]
    explained_all = _explained(dirs, poses, x_axes, radii, cfg)
    for c, chk, explained in zip(to_check, chks, explained_all, strict=True):
        if not credible(chk, cfg, prior, up_cam, n_par):
            # Kept as a rival: a near-miss that fits about as well forbids confidence in another pose.
            rivals.append((chk.agree_fraction * explained, c.sign, chk.T_rack_cam, num_limbs_ok(chk, cfg, n_par)))
            continue
        checked.append((chk.agree_fraction * explained, c.sign, chk, c.direction))
    checked.sort(key=lambda sc: -sc[0])
    # Polish the contenders: the lateral position and the roll about the pipes are nearly
    # interchangeable from high above, and converge slowly under the per-iteration damping.
    polished: list[tuple[float, int, EdgeCheck, int]] = list(checked)
    todo = [i for i, (score, _, _, _) in enumerate(checked) if score >= cfg.ambiguity_ratio * checked[0][0] * 0.9]
    for extra in (False, True):  # checked with the crossing pipe placed or not
        group = [i for i in todo if (checked[i][2].pipe_samples.size > n_par) == extra]
        if not group:
            continue
        pols = [np.concatenate([np.full(n_par, -float(_polarity_of(checked[i][2], n_par))),
                                np.zeros(n_all - n_par if extra else 0)]) for i in group]
        chk2s = check([checked[i][2].T_rack_cam for i in group], pols, extra, True)
        ok = [(i, chk2) for i, chk2 in zip(group, chk2s, strict=True) if credible(chk2, cfg, prior, up_cam, n_par)]
        ex2 = _explained(dirs, [(checked[i][3], chk2.T_rack_cam, checked[i][1]) for i, chk2 in ok], x_axes, radii, cfg)
        for (i, chk2), e in zip(ok, ex2, strict=True):
            polished[i] = (chk2.agree_fraction * e, checked[i][1], chk2, checked[i][3])
    polished.sort(key=lambda sc: -sc[0])
    if polished and good_pipes(polished[0][2], cfg).size < cfg.min_pipes:
        # Close range: a pose off by one pipe explains fewer limbs (a neighbour's limb where it puts the
        # rack's side, or none where it puts a neighbour) rather than failing outright; the poses that
        # explain the most limbs are the hypotheses.
        n_ok = [num_limbs_ok(chk, cfg, n_par) for _, _, chk, _ in polished]
        polished = [p for p, n in zip(polished, n_ok, strict=True) if n == max(n_ok)]
    # y from a crossing pipe for the best only: the others are kept as alternatives to report.
    out = [_finish(sign, chk, score, seg, img_f, camera, pipes_all, n_par, prior, cfg, damping, up_cam, up_weight,
                   k == 0) for k, (score, sign, chk, _) in enumerate(polished)]
    out = distinct(out, cfg)
    if not out:
        return AcquisitionResult((), False, "no hypothesis agrees with the image edges", int(seg.length_px.size),
                                 num_limbs)
    best_chk = polished[0][2]
    # At close range a pose off by a pipe explains fewer limbs (a missing neighbour) rather than
    # failing outright; it counts as a rival only when it explains as many limbs as the best.
    rival_limbs = num_limbs_ok(best_chk, cfg, n_par) if good_pipes(best_chk, cfg).size < cfg.min_pipes else 0
    # Whether the image is explained: the whole image's lines, or those over the rack's footprint
    # (ground clutter beside the rack is not evidence against the pose); the ranking and the ambiguity
    # tests keep the whole image's (`_explained`), which is what tells a pose one or more pipes off.
    # A best rescued that way must also stand out among the contenders on that score.
    shown = [chk.agree_fraction * e for (_, _, chk, _), e in zip(polished, _explained(
        dirs, [(d, chk.T_rack_cam, sign) for _, sign, chk, d in polished], x_axes, radii, cfg, footprint=True),
        strict=True)]
    status = decide(out, rivals, prior, cfg, up_cam, rival_limbs,
                    shown[0] if all(v <= cfg.ambiguity_ratio * shown[0] for v in shown[1:]) else out[0].score)
    return AcquisitionResult(tuple(out), status == "", status, int(seg.length_px.size), num_limbs)


def _propose(
    seg: Segments, small: Any, camera: PinholeCamera, prior: AcquisitionPrior, cfg: AcquisitionConfig,
    up_cam: FloatArray, R0: FloatArray, x_axes: FloatArray, radii: FloatArray, f_px: float,
) -> tuple[list[_Direction], list[_Candidate], int]:
    """Pose proposals per pipe direction: the profile sweep's and the limb pairs', with the tables
    (limbs, profile, field of view) their direction's scoring needs, and the most limbs found."""
    dirs: list[_Direction] = []
    cands: list[_Candidate] = []
    num_limbs = 0
    gradient = None
    for d0 in direction_candidates(seg, up_cam, np.deg2rad(1.0), cfg.max_directions, np.deg2rad(15.0)):
        d, inl = refine_direction(seg, d0, up_cam, cfg.direction_tol_rad)
        limbs = limb_clusters(seg, inl, d, up_cam, camera, cfg.merge_px / f_px)
        num_limbs = max(num_limbs, int(limbs.theta.size))
        signs = _signs(d, R0, prior, cfg)
        if not signs:
            continue
        th_range = image_theta_range(camera, limbs)
        grid = np.linspace(th_range[0], th_range[1], 181)
        gradient = gradient or image_gradient(small)  # once per image
        di = _Direction(limbs, pencil_profile(small, camera, limbs, cfg.profile_bin_px / f_px, gradient), th_range,
                        grid, visible_length_px(camera, limbs, grid))
        k = len(dirs)
        dirs.append(di)
        tol_bins = max(round(cfg.sweep_tol_px / cfg.profile_bin_px), 1)
        swept = sweep_section(di.profile, x_axes, radii, prior.height_m, prior.height_std_m, signs, th_range,
                              di.visible_length, cfg.sweep_step_m, tol_bins, cfg.min_limb_px,
                              cfg.max_swept_hypotheses, cfg.distinct_m)
        refined = refine_on_peaks(di.profile, swept, x_axes, radii, th_range, prior.height_m, prior.height_std_m,
                                  cfg.alpha_std_rad, cfg.sweep_tol_px / f_px, 1.0 / f_px)
        for sh, (x, z, a) in zip(swept, refined, strict=True):
            cands.append(_Candidate(float(x), float(z), float(a), sh.sign, 0, sh.score, k))
        if limbs.theta.size >= 2:
            hyps = section_hypotheses(limbs, x_axes, radii, prior.height_m, prior.height_std_m, signs, th_range,
                                      di.visible_length, cfg.match_px / f_px, cfg.min_limb_px, cfg.alpha_std_rad,
                                      cfg.max_section_hypotheses, cfg.distinct_m)
            if hyps:
                ev, ex = profile_scores(di.profile, np.array([h.x_m for h in hyps]), np.array([h.z_m for h in hyps]),
                                        np.array([float(h.sign) for h in hyps]), x_axes, radii, th_range,
                                        di.visible_length, tol_bins, cfg.min_limb_px)
                for h, e, x in zip(hyps, ev, ex, strict=True):
                    cands.append(_Candidate(h.x_m, h.z_m, h.alpha_rad, h.sign, h.polarity, float(e * x), k))
    return dirs, cands, num_limbs


def _polarity_of(chk: EdgeCheck, n_par: int) -> int:
    """The pipes' polarity (+1 brighter than around them, -1 darker) the check's limbs agree on, else 0."""
    s = float(np.sum(chk.limb_polarity[: 2 * n_par]))
    n = int(np.count_nonzero(chk.limb_polarity[: 2 * n_par]))
    return 0 if n == 0 or abs(s) < 0.8 * n else (-1 if s > 0 else 1)


def _signs(d: FloatArray, R0: FloatArray, prior: AcquisitionPrior, cfg: AcquisitionConfig) -> tuple[int, ...]:
    """Directions of travel (+1: along rack +y) allowed for pipe direction `d` (cam frame) by the heading."""
    if prior.yaw_rad is None:
        return (1, -1)
    y_cam_prior = R0[1, :]  # rack +y in the camera frame at the prior heading
    c = float(d @ y_cam_prior) / float(np.linalg.norm(d))
    ang = float(np.arccos(min(abs(c), 1.0)))  # angle between the lines, modulo the direction
    gate = cfg.yaw_gate_sigma * prior.yaw_std_rad
    if ang > gate:
        return ()
    return (1 if c >= 0 else -1,) if gate < np.pi / 2 else (1, -1)


def _dedupe(cands: list[_Candidate], sep_m: float) -> list[_Candidate]:
    out: list[_Candidate] = []
    for c in cands:
        if all(c.sign != o.sign or abs(c.x_m - o.x_m) >= sep_m or abs(c.z_m - o.z_m) >= 2 * sep_m for o in out):
            out.append(c)
    return out


def _finish(
    sign: int, chk: EdgeCheck, score: float, seg: Segments, img_f: Any, camera: PinholeCamera,
    pipes_all: PipeArrays, n_par: int, prior: AcquisitionPrior, cfg: AcquisitionConfig, damping: FloatArray,
    up_cam: FloatArray, up_weight: float, find_y: bool,
) -> RackHypothesis:
    """Along-pipe y (crossing pipe when `find_y`, else the prior), covariance and the public hypothesis."""
    T = chk.T_rack_cam.copy()
    T[1, 3] = prior.y_m
    final = chk
    y_observed = False
    n_all = pipes_all.radii.size
    if find_y and n_all > n_par:
        h_weight = cfg.covariance_inflation * (cfg.edge_noise_px / prior.height_std_m) ** 2
        span = 4.0 * prior.y_std_m
        ys = crossing_y_candidates(seg, T, pipes_all, np.arange(n_par, n_all), prior.y_m - span, prior.y_m + span,
                                   cfg.direction_tol_rad, 0.03, 3)
        passed: list[tuple[float, EdgeCheck]] = []
        Tys = []
        for y in ys:
            Ty = T.copy()
            Ty[1, 3] = y
            Tys.append(Ty)
        for c in check_poses(img_f, camera, pipes_all, Tys, [np.zeros(n_all)] * len(Tys), cfg.check_ranges_px,
                             cfg.samples_per_limb, cfg.edge_threshold, cfg.inlier_px, cfg.margin_px, damping,
                             up_cam, up_weight, prior.height_m, h_weight):
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
    T_out = np.array(final.T_rack_cam if y_observed else T, copy=True)
    cov = pose_covariance(final, cfg.covariance_inflation, None if y_observed else prior.y_std_m, np.full(6, 1e-6))
    T_out.flags.writeable = False
    cov.flags.writeable = False
    good = good_pipes(chk, cfg)
    good = good[good < n_par]
    ordered = tuple(int(m) for m in (good[::-1] if sign < 0 else good))
    return RackHypothesis(T_rack_cam=T_out, covariance=cov, score=score, pipes=ordered,
                          reversed=sign < 0, y_observed=y_observed, residual_px=chk.residual_px,
                          num_samples=chk.num_samples)
