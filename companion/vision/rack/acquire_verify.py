"""Rack acquisition, step 3: check and refine a pose hypothesis with the tracker's edge measurement.

The limbs are rendered and sampled by `limbs.sample_limbs` and searched along their normals as
`edges.search_edges` does (`acquire_edges`: the same search, its profiles read once per
iteration), exactly as `RackTracker` does; the rows are the tracker's motion fields
(`motion.pose_jacobian`) solved by `motion.solve_normal_equations` with `motion.robust_weights`.
A few iterations with a shrinking search range refine the pose; the verdict is the fraction of
the predicted limb samples whose edge is found (strong, of the hypothesis' polarity) and agrees
with the refined pose, overall and per pipe (the along-pipe position y from a crossing pipe's
segments, `acquire_lines.crossing_y_candidates`, is confirmed by the same check). Frames:
`T_rack_cam` camera in rack frame; twists are right perturbations in the camera frame (v, w) like
the tracker's covariance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.geometry import se3
from companion.vision.rack.acquire_edges import normal_profiles, percentile_90, pick_edges
from companion.vision.rack.acquire_samples import sample_limbs_many
from companion.vision.rack.edges import EdgeMeasurements, refine_silhouette
from companion.vision.rack.limbs import LimbSamples
from companion.vision.rack.model import PipeArrays
from companion.vision.rack.motion import median_1d, pose_jacobian, robust_weights, solve_normal_equations

Float32Image = np.ndarray[Any, np.dtype[np.float32]]


@dataclass(frozen=True)
class EdgeCheck:
    """Outcome of `check_pose`: refined `T_rack_cam` (4x4); `num_samples` predicted limb samples;
    `agree_fraction` of them found and within the inlier distance; `pipe_samples` / `pipe_agree`
    (M,) the same per pipe, `limb_samples` / `limb_agree` (2M,) per limb (2m, 2m+1: pipe m)
    and `limb_polarity` (2M,) the polarity used (given or learnt, 0 = open), `limb_run` (2M,)
    the longest run of consecutive agreeing samples along each limb (a real limb agrees over
    long stretches; a grating or a texture crossing the predicted line agrees in short bursts);
    `residual_px` robust std of the agreeing residuals; `H_data` (8x8) the edge information AᵀWA
    of the last iteration over the pose (6) and the two edge offsets, and `scale2` the weighted
    residual variance (px²)."""

    T_rack_cam: FloatArray
    num_samples: int
    agree_fraction: float
    pipe_samples: FloatArray
    pipe_agree: FloatArray
    limb_samples: FloatArray
    limb_agree: FloatArray
    limb_polarity: FloatArray
    limb_run: FloatArray
    residual_px: float
    H_data: FloatArray
    scale2: float


def _longest_runs(limb: Any, agree: Any, n_limbs: int) -> FloatArray:
    """Longest run of consecutive True in `agree` (N,) within each limb (samples ordered along their limb),
    gaps of up to two samples (a rust spot on the limb, a missed edge) bridged."""
    out = np.zeros(n_limbs)
    if agree.size == 0:
        return out
    n = agree.size
    idx = np.arange(n)

    def shifted(a: Any, k: int) -> Any:
        j = idx + k
        ok = (j >= 0) & (j < n)
        jj = np.clip(j, 0, n - 1)
        return ok & (limb[jj] == limb) & a[jj]

    # Closing: dilate by one sample, then erode by one (within the limb).
    dil = agree | shifted(agree, -1) | shifted(agree, 1)
    ero = dil.copy()
    for k in (-1, 1):
        j = idx + k
        inside = (j >= 0) & (j < n) & (limb[np.clip(j, 0, n - 1)] == limb)
        ero &= ~inside | dil[np.clip(j, 0, n - 1)]
    agree = ero
    # A run breaks where the flag is false or the limb changes; label runs and count their lengths.
    start = np.ones(agree.size, dtype=bool)
    start[1:] = (limb[1:] != limb[:-1]) | ~agree[:-1]
    run_id = np.cumsum(start) - 1
    lengths = np.bincount(run_id, weights=agree.astype(np.float64))
    np.maximum.at(out, limb[start], lengths[run_id[start]])
    return out


def subset_pipes(pipes: PipeArrays, index: Any) -> PipeArrays:
    """The pipes at `index` only (keeps the order)."""
    return PipeArrays(starts=pipes.starts[index], directions=pipes.directions[index], radii=pipes.radii[index],
                      lengths=pipes.lengths[index], gap_index=pipes.gap_index[index])


def check_pose(
    image_f32: Float32Image,
    camera: PinholeCamera,
    pipes: PipeArrays,
    T_rack_cam: FloatArray,
    pipe_polarity: FloatArray,
    ranges_px: tuple[int, ...],
    samples_per_limb: int,
    edge_threshold: float,
    inlier_px: float,
    margin_px: float,
    damping: FloatArray,
    up_cam: FloatArray | None = None,
    up_weight: float = 0.0,
    height_m: float | None = None,
    height_weight: float = 0.0,
) -> EdgeCheck:
    """Refine `T_rack_cam` on the limbs of `pipes` (one iteration per search range) and score it.

    `pipe_polarity` (M,) is the tracker's polarity of each pipe's limbs (+1: brighter outward, -1:
    darker outward, 0: unknown, then each limb takes the sign most of its edges show in the first
    iteration, or stays open when they disagree, e.g. a crossing pipe seen against other pipes);
    the first iteration's open limbs take the polarity of their edges and count as known; `damping` (6,) the
    information of a zero-mean prior on each update. As the tracker does, two edge offsets (px
    along the outward normal, one per limb side) absorb the systematic shift of gradient-peak
    edges next to shaded limbs; without them the silhouettes read a little wide or narrow and the
    distance and the lateral position / roll about the pipes (nearly interchangeable from high
    above) come out biased. `up_cam` (3,), when given, is the autopilot's rack up axis in the
    camera frame, held with information `up_weight` (px² per rad²) against the rotation;
    `height_m`, when given, the measured camera height (rack z, m), held with `height_weight`
    (px² per m²): shadows and ground stripes can mimic a pipe pattern at another height. Edges
    count when their strength reaches a fifth of the 90th percentile of the strengths on the
    limbs of known polarity (a tenth on the others: a pipe lying on pipes shows a weak step):
    texture, noise and shading never reach a fraction of a real silhouette.
    """
    return check_poses(image_f32, camera, pipes, [T_rack_cam], [pipe_polarity], ranges_px, samples_per_limb,
                       edge_threshold, inlier_px, margin_px, damping, up_cam, up_weight, height_m, height_weight)[0]


def check_poses(
    image_f32: Float32Image,
    camera: PinholeCamera,
    pipes: PipeArrays,
    T_rack_cam: list[FloatArray],
    pipe_polarity: list[FloatArray],
    ranges_px: tuple[int, ...],
    samples_per_limb: int,
    edge_threshold: float,
    inlier_px: float,
    margin_px: float,
    damping: FloatArray,
    up_cam: FloatArray | None = None,
    up_weight: float = 0.0,
    height_m: float | None = None,
    height_weight: float = 0.0,
    silhouette: tuple[int, float] = (0, 0.0),
) -> list[EdgeCheck]:
    """`check_pose` of several poses (with their polarities) side by side: each pose's iterations are its
    own, the limb sampling and the edge search of an iteration run once over the samples of all poses.
    `silhouette` = (range_px, max_rms): on iterations whose range is at most range_px the edges are moved
    to the fitted limb silhouettes (`_to_silhouettes`; range_px 0 = never)."""
    M = pipes.radii.size
    states = [_Refinement(np.array(T, dtype=np.float64, copy=True), np.repeat(np.asarray(pol, dtype=np.float64), 2))
              for T, pol in zip(T_rack_cam, pipe_polarity, strict=True)]
    prior8 = np.concatenate([damping, [1.0 / 1.0**2] * 2])
    for rng_px in ranges_px:
        active = [st for st in states if st.result is None]
        if not active:
            break
        samples = sample_limbs_many([st.T for st in active], camera, pipes, samples_per_limb, margin_px, 12.0, 0.1,
                                    3.0)
        for st, s in zip(active, samples, strict=True):
            if s.uv.shape[0] == 0:
                st.result = EdgeCheck(st.T, 0, 0.0, np.zeros(M), np.zeros(M), np.zeros(2 * M), np.zeros(2 * M),
                                      st.limb_pol, np.zeros(2 * M), float("inf"), np.zeros((8, 8)), 0.0)
        pairs = [(st, s) for st, s in zip(active, samples, strict=True) if st.result is None]
        if not pairs:
            break
        # The profiles along the normals are read once; a polarity learnt below only re-picks the edges.
        n_rows = np.cumsum([0] + [s.uv.shape[0] for _, s in pairs])
        prof = normal_profiles(image_f32, np.concatenate([s.uv for _, s in pairs]),
                               np.concatenate([s.normal_px for _, s in pairs]), int(rng_px), 1.5)
        meas = pick_edges(prof, np.concatenate([st.limb_pol[s.limb] for st, s in pairs]), int(rng_px),
                          edge_threshold)
        fit = 0 < rng_px <= silhouette[0]
        if fit:
            meas = _to_silhouettes(image_f32, [s for _, s in pairs], meas, silhouette[1])
        metas = [_rows(meas, n_rows[k], n_rows[k + 1]) for k in range(len(pairs))]
        again = [k for k, (st, s) in enumerate(pairs) if _learn(st, s, metas[k])]
        if again:
            rows = np.concatenate([np.arange(n_rows[k], n_rows[k + 1]) for k in again])
            meas2 = pick_edges(prof[rows], np.concatenate([pairs[k][0].limb_pol[pairs[k][1].limb] for k in again]),
                               int(rng_px), edge_threshold)
            n2 = np.cumsum([0] + [n_rows[k + 1] - n_rows[k] for k in again])
            if fit:
                meas2 = _to_silhouettes(image_f32, [pairs[k][1] for k in again], meas2, silhouette[1])
            for j, k in enumerate(again):
                metas[k] = _rows(meas2, n2[j], n2[j + 1])
        # Strong edges per pose; the rows' motion fields and weights once for all poses.
        fs = [_strong(st.limb_pol[s.limb], m) for (st, s), m in zip(pairs, metas, strict=True)]
        f_all = np.concatenate([f + n_rows[k] for k, f in enumerate(fs)])
        J_all = np.concatenate([s.J_uv_pcam for _, s in pairs])
        p_all = np.concatenate([s.p_cam for _, s in pairs])
        n_all = np.concatenate([s.normal_px for _, s in pairs])
        A6 = np.einsum("nij,ni->nj", pose_jacobian(J_all[f_all], p_all[f_all]), n_all[f_all])
        side_l = [s.limb[f] % 2 for (_, s), f in zip(pairs, fs, strict=True)]
        r_all = np.concatenate([m.offset_px[f] - st.bias[side]
                                for (st, _), m, f, side in zip(pairs, metas, fs, side_l, strict=True)])
        w_all = robust_weights(r_all, "paper", 1.0, max(2.0 * inlier_px, float(rng_px)))
        n_f = np.cumsum([0] + [f.size for f in fs])
        for k, (st, s) in enumerate(pairs):
            a, b = n_f[k], n_f[k + 1]
            _solve(st, s, fs[k], A6[a:b], side_l[k], r_all[a:b], w_all[a:b], prior8, up_cam, up_weight, height_m,
                   height_weight)
    return [st.result if st.result is not None else _verdict(st, M, inlier_px) for st in states]


def _to_silhouettes(image_f32: Float32Image, samples: list[LimbSamples], meas: EdgeMeasurements,
                    max_rms: float) -> EdgeMeasurements:
    """`meas` (the edges of `samples`, concatenated) with each gradient peak moved to the silhouette of the
    fitted limb profile (`edges.refine_silhouette` with the tracker's default windows, 6 px in, 5 px out):
    the peak of a shaded limb lies 1-2 px inside it, by an amount that changes with the ground beside it."""
    uv = np.concatenate([s.uv for s in samples])
    normal = np.concatenate([s.normal_px for s in samples])
    offset = refine_silhouette(image_f32, uv, normal, meas.offset_px, 6, 5, max_rel_rms=max_rms)
    return EdgeMeasurements(offset_px=offset, found=meas.found, sign=meas.sign, strength=meas.strength,
                            inner=meas.inner)


class _Refinement:
    """One pose's state through `check_poses`' iterations."""

    def __init__(self, T: FloatArray, limb_pol: FloatArray) -> None:
        self.T = T
        self.limb_pol = limb_pol  # per limb: the pipe's where known, else learnt from the first iteration's edges
        self.learn = limb_pol == 0.0
        self.bias = np.zeros(2)
        self.last: dict[str, Any] = {}
        self.result: EdgeCheck | None = None


def _rows(meas: EdgeMeasurements, start: int, stop: int) -> EdgeMeasurements:
    return EdgeMeasurements(offset_px=meas.offset_px[start:stop], found=meas.found[start:stop],
                            sign=meas.sign[start:stop], strength=meas.strength[start:stop])


def _learn(st: _Refinement, s: LimbSamples, meas: EdgeMeasurements) -> bool:
    """Limbs of unknown polarity take the gradient sign most of their strongest edges show (the tracker
    learns it too); True when one did (its edges are then picked again)."""
    if not st.learn.any():
        return False
    good = meas.found & st.learn[s.limb]
    tot = np.bincount(s.limb[good], weights=meas.sign[good] * meas.strength[good], minlength=st.learn.size)
    mag = np.bincount(s.limb[good], weights=meas.strength[good], minlength=st.learn.size)
    decided = st.learn & (np.abs(tot) >= 0.5 * np.maximum(mag, 1e-9)) & (mag > 0)
    sign = np.sign(tot)
    # A limb against the clear majority of the others stays open: a pose a few pixels off puts its
    # search on the neighbouring pipe's facing limb, of the opposite sign.
    major = float(tot[decided].sum())
    if decided.sum() >= 3 and abs(major) >= 0.5 * float(mag[decided].sum()):
        sign = np.where(decided & (sign != np.sign(major)), 0.0, sign)
    st.limb_pol = np.where(decided, sign, st.limb_pol)
    st.learn = st.learn & ~decided
    return bool(decided.any())


def _strong(pol: FloatArray, meas: EdgeMeasurements) -> Any:
    """Rows whose edge is found and strong: a limb is a large step, texture and ground rarely reach a
    fraction of it (a fifth of the 90th percentile on limbs of known polarity, a tenth on the others)."""
    found = meas.found
    ref = found & (pol != 0.0)
    if not ref.any():
        ref = found
    if ref.any():
        frac = np.where(pol != 0.0, 0.2, 0.1)
        found = found & (meas.strength >= frac * percentile_90(meas.strength[ref]))
    return np.flatnonzero(found)


def _solve(st: _Refinement, s: LimbSamples, f: Any, A6: FloatArray, side: Any, r: FloatArray, w: FloatArray,
           prior8: FloatArray, up_cam: FloatArray | None, up_weight: float, height_m: float | None,
           height_weight: float) -> None:
    """One Gauss-Newton step of `check_pose` on the pose's strong edge rows `f` (motion fields `A6` on
    their normals, limb side, residual and weight)."""
    T = st.T
    # The edge rows, then the autopilot's tilt (3 rows) and height (1 row) when given, in one array.
    n_up = 3 if up_cam is not None and up_weight > 0 else 0
    n_h = 1 if height_m is not None and height_weight > 0 else 0
    A_all = np.zeros((f.size + n_up + n_h, 8))
    A = A_all[: f.size]
    A[:, :6] = A6
    A[np.arange(f.size), 6 + side] = 1.0
    r_all = np.empty(A_all.shape[0])
    w_all = np.empty(A_all.shape[0])
    r_all[: f.size] = r
    w_all[: f.size] = w
    if n_up:
        assert up_cam is not None
        u, J_up = up_axis_with_jacobian(T)
        A_all[f.size : f.size + 3, :6] = J_up
        r_all[f.size : f.size + 3] = up_cam - u
        w_all[f.size : f.size + 3] = up_weight
    if n_h:
        assert height_m is not None
        # z(T exp(δ)) ≈ z + R[2, :] v: one row on the translation.
        A_all[-1, :3] = T[2, :3]
        r_all[-1] = height_m - T[2, 3]
        w_all[-1] = height_weight
    x, _, _ = solve_normal_equations(A_all, r_all, w_all, prior8)
    st.T = T @ se3.exp_one(x[:6])
    st.bias = st.bias + x[6:]
    st.last = {"s": s, "f": f, "A": A, "r": r, "w": w, "x": x, "H": (A * w[:, None]).T @ A}


def _verdict(st: _Refinement, M: int, inlier_px: float) -> EdgeCheck:
    """The check of a refined pose: its last iteration's samples, edges and solution."""
    last = st.last
    s, f = last["s"], last["f"]
    r_post = last["r"] - last["A"] @ last["x"]
    agree_rows = np.abs(r_post) <= inlier_px
    agree = np.zeros(s.uv.shape[0], dtype=bool)
    agree[f[agree_rows]] = True
    pipe_samples = np.bincount(s.pipe, minlength=M).astype(np.float64)
    pipe_agree = np.bincount(s.pipe[agree], minlength=M).astype(np.float64)
    limb_samples = np.bincount(s.limb, minlength=2 * M).astype(np.float64)
    limb_agree = np.bincount(s.limb[agree], minlength=2 * M).astype(np.float64)
    w = last["w"]
    dof = max(int(np.count_nonzero(w > 0)) - 6, 1)
    scale2 = float(np.sum(w * r_post**2) / dof)
    resid = 1.4826 * median_1d(np.abs(r_post[agree_rows])) if np.any(agree_rows) else float("inf")
    return EdgeCheck(
        T_rack_cam=st.T,
        num_samples=int(s.uv.shape[0]),
        agree_fraction=float(agree.mean()),
        pipe_samples=pipe_samples,
        pipe_agree=pipe_agree,
        limb_samples=limb_samples,
        limb_agree=limb_agree,
        limb_polarity=st.limb_pol,
        limb_run=_longest_runs(s.limb, agree, 2 * M),
        residual_px=float(resid),
        H_data=last["H"],
        scale2=scale2,
    )


def up_axis_with_jacobian(T_rack_cam: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The rack's +z axis in the camera frame (3,) and its Jacobian (3, 6) with respect to a right
    perturbation (v, w) of `T_rack_cam`: u(T exp(δ)) = exp(-w) u ≈ u + u × w, so J = [0, hat(u)]."""
    u = np.array(T_rack_cam[2, :3], dtype=np.float64)
    J = np.zeros((3, 6))
    J[:, 3:] = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    return u, J


def pose_covariance(check: EdgeCheck, inflation: float, y_std_m: float | None, damping: FloatArray) -> FloatArray:
    """6x6 covariance (right perturbation, cam frame, (v, w), m and rad) of a checked pose.

    Edge information scaled by the residual variance and `inflation` (samples along a limb are
    correlated), plus the prior on the along-pipe position y (rack frame) with std `y_std_m` when
    y was not observed, plus `damping` so that directions nothing observes keep a finite variance.
    """
    info = check.H_data / max(check.scale2 * inflation, 1e-12)
    info = info + np.diag(np.concatenate([damping, np.full(info.shape[0] - 6, 1.0)]))
    if y_std_m is not None:
        e_y = check.T_rack_cam[1, :3]  # rack y of a camera-frame translation: R[1, :] v
        info[:3, :3] += np.outer(e_y, e_y) / y_std_m**2
    cov = np.linalg.inv(info)[:6, :6]  # the edge offsets marginalised out
    return np.asarray(0.5 * (cov + cov.T))
