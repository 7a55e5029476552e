"""Rack acquisition: `limbs.sample_limbs` for several camera poses at once (the edge check's poses).

The edge check refines a few proposals side by side; sampling their limbs one pose at a time
spends most of its time in NumPy's per-call overhead (a few hundred samples per pose). Here the
per-pose steps (the limb lines seen from the camera centre, the rotation into the camera, the
occlusion by other pipes) run per pose with the functions of `limbs`, and the row-wise steps
(clipping to the view, sample placement, projection, image normals) run once over the rows of
all poses. The result per pose is exactly `sample_limbs`' (the same arithmetic per row; tested).
Frames: `T_rack_cam` camera in the rack frame; pixels follow OpenCV.
"""

from __future__ import annotations

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.limbs import LimbSamples, clip_lines_to_view, limb_lines, occluded, sample_limbs
from companion.vision.rack.model import PipeArrays

__all__ = ["sample_limbs_many"]


def sample_limbs_many(
    T_rack_cam: list[FloatArray],
    camera: PinholeCamera,
    pipes: PipeArrays,
    samples_per_limb: int,
    margin_px: float = 4.0,
    min_length_px: float = 12.0,
    z_near_m: float = 0.1,
    occlusion_margin_px: float = 3.0,
) -> list[LimbSamples]:
    """`sample_limbs(T, camera, pipes, ...)` for every pose T in `T_rack_cam` (same arguments)."""
    n_pose = len(T_rack_cam)
    if n_pose == 1:
        return [sample_limbs(T_rack_cam[0], camera, pipes, samples_per_limb, margin_px, min_length_px, z_near_m,
                             occlusion_margin_px)]
    L = 2 * pipes.radii.size
    A_l, D_l, O_l, smin_l, smax_l, valid_l = [], [], [], [], [], []
    for T in T_rack_cam:
        R_rc, o = T[:3, :3], T[:3, 3]
        lines = limb_lines(o, pipes)
        A_l.append((lines.point - o) @ R_rc)
        D_l.append(lines.direction @ R_rc)
        O_l.append(lines.outward @ R_rc)
        smin_l.append(lines.s_min)
        smax_l.append(lines.s_max)
        valid_l.append(lines.valid)
    A_cam, D_cam, out_cam = np.concatenate(A_l), np.concatenate(D_l), np.concatenate(O_l)
    s0, s1 = clip_lines_to_view(A_cam, D_cam, np.concatenate(smin_l), np.concatenate(smax_l), camera, margin_px,
                                z_near_m)
    idx = np.flatnonzero(np.concatenate(valid_l) & (s1 > s0))  # rows over all poses: pose * L + limb
    if idx.size == 0:
        return [_empty() for _ in range(n_pose)]
    Pa = A_cam[idx] + s0[idx, None] * D_cam[idx]
    Pb = A_cam[idx] + s1[idx, None] * D_cam[idx]
    ua = Pa[:, :2] / Pa[:, 2:3]
    ub = Pb[:, :2] / Pb[:, 2:3]
    len_px = np.hypot((ub[:, 0] - ua[:, 0]) * camera.fx, (ub[:, 1] - ua[:, 1]) * camera.fy)
    long_enough = len_px >= min_length_px
    idx, Pa, Pb, ua, ub = idx[long_enough], Pa[long_enough], Pb[long_enough], ua[long_enough], ub[long_enough]
    seg = np.empty((idx.size, 2, 2))
    seg[:, 0, 0] = ua[:, 0] * camera.fx + ua[:, 1] * camera.skew + camera.cx
    seg[:, 0, 1] = ua[:, 1] * camera.fy + camera.cy
    seg[:, 1, 0] = ub[:, 0] * camera.fx + ub[:, 1] * camera.skew + camera.cx
    seg[:, 1, 1] = ub[:, 1] * camera.fy + camera.cy
    K = int(samples_per_limb)
    t = (np.arange(K) + 0.5) / K
    Za, Zb = Pa[:, 2:3], Pb[:, 2:3]
    lam = t[None, :] * Za / (t[None, :] * Za + (1.0 - t[None, :]) * Zb)
    p_cam = ((1.0 - lam)[..., None] * Pa[:, None, :] + lam[..., None] * Pb[:, None, :]).reshape(-1, 3)
    row = np.repeat(idx, K)  # (N,) line row of each sample
    pose = row // L
    limb = row % L
    pipe = limb // 2
    # Per pose: the rack-frame points and their occlusion (the same calls as sample_limbs).
    bounds = np.searchsorted(pose, np.arange(n_pose + 1))
    p_rack = np.empty_like(p_cam)
    vis = np.empty(p_cam.shape[0], dtype=bool)
    margin_m = occlusion_margin_px * p_cam[:, 2] / camera.fx
    for k, T in enumerate(T_rack_cam):
        a, b = bounds[k], bounds[k + 1]
        if a == b:
            continue
        o = T[:3, 3]
        p_rack[a:b] = p_cam[a:b] @ T[:3, :3].T + o
        vis[a:b] = ~occluded(o, p_rack[a:b], pipe[a:b], pipes, margin_m[a:b])
    uv, J = camera.project_with_jacobian(p_cam)
    lo = -0.5 + margin_px
    with np.errstate(invalid="ignore"):
        vis &= (uv[:, 0] >= lo) & (uv[:, 1] >= lo) & (uv[:, 0] <= camera.width - 0.5 - margin_px) & (
            uv[:, 1] <= camera.height - 0.5 - margin_px)
    if not vis.all():
        ii = np.flatnonzero(vis)
        p_cam, p_rack, uv, J, row, pose, limb, pipe = (p_cam[ii], p_rack[ii], uv[ii], J[ii], row[ii], pose[ii],
                                                       limb[ii], pipe[ii])
    t_img = np.einsum("nij,nj->ni", J, D_cam[row])
    m_img = np.einsum("nij,nj->ni", J, out_cam[row])
    t_img /= np.maximum(np.sqrt(t_img[:, 0:1] * t_img[:, 0:1] + t_img[:, 1:2] * t_img[:, 1:2]), 1e-12)
    n_img = np.empty_like(t_img)
    n_img[:, 0] = -t_img[:, 1]
    n_img[:, 1] = t_img[:, 0]
    flip = n_img[:, 0] * m_img[:, 0] + n_img[:, 1] * m_img[:, 1] < 0.0
    n_img[flip] = -n_img[flip]
    bounds = np.searchsorted(pose, np.arange(n_pose + 1))
    seg_bounds = np.searchsorted(idx // L, np.arange(n_pose + 1))
    out: list[LimbSamples] = []
    for k in range(n_pose):
        a, b = bounds[k], bounds[k + 1]
        sa, sb = seg_bounds[k], seg_bounds[k + 1]
        if sa == sb:  # no limb long enough in view: sample_limbs' empty samples
            out.append(_empty())
            continue
        out.append(LimbSamples(p_rack=p_rack[a:b], p_cam=p_cam[a:b], uv=uv[a:b], normal_px=n_img[a:b],
                               J_uv_pcam=J[a:b], pipe=pipe[a:b], limb=limb[a:b], segments_uv=seg[sa:sb],
                               segment_limb=idx[sa:sb] % L))
    return out


def _empty() -> LimbSamples:
    z3 = np.zeros((0, 3))
    zi = np.zeros(0, dtype=np.intp)
    return LimbSamples(p_rack=z3, p_cam=z3, uv=np.zeros((0, 2)), normal_px=np.zeros((0, 2)),
                       J_uv_pcam=np.zeros((0, 2, 3)), pipe=zi, limb=zi)
