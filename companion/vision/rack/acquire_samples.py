"""Rack acquisition: `limbs.sample_limbs` for several camera poses at once (the edge check's poses).

The edge check refines a few proposals side by side; sampling their limbs one pose at a time
spends most of its time in NumPy's per-call overhead (a few hundred samples per pose). Here the
limb lines of `limbs.limb_lines` are formed for all camera centres at once (the same arithmetic
with a leading pose axis), the occlusion by other pipes is `limbs.occluded` per pose, and the
row-wise steps (clipping to the view, sample placement, projection, image normals) run once over
the rows of all poses. The result per pose is exactly `sample_limbs`' (bit-identical; tested).
Frames: `T_rack_cam` camera in the rack frame; pixels follow OpenCV.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.limbs import LimbSamples, clip_lines_to_view, inside_margin, occluded, sample_limbs
from companion.vision.rack.model import PipeArrays

BoolArray = np.ndarray[Any, np.dtype[np.bool_]]

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
    T_all = np.stack(T_rack_cam)
    O = T_all[:, :3, 3]
    R_rc = T_all[:, :3, :3]
    point, direction, outward, s_min, s_max, valid = _limb_lines_many(O, pipes)
    A_cam = np.matmul(point - O[:, None, :], R_rc).reshape(-1, 3)  # per pose R_cam_rack (p - o)
    D_cam = np.matmul(direction[None, :, :], R_rc).reshape(-1, 3)
    out_cam = np.matmul(outward, R_rc).reshape(-1, 3)
    s0, s1 = clip_lines_to_view(A_cam, D_cam, s_min.ravel(), s_max.ravel(), camera, margin_px, z_near_m)
    idx = np.flatnonzero(valid.ravel() & (s1 > s0))  # rows over all poses: pose * L + limb
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
    vis &= inside_margin(uv, camera, margin_px)
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


def _limb_lines_many(
    O: FloatArray, pipes: PipeArrays
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, BoolArray]:
    """`limbs.limb_lines` seen from K camera centres `O` (K, 3) (the same arithmetic, a leading pose axis):
    point (K, 2M, 3), direction (2M, 3), outward (K, 2M, 3), s_min, s_max, valid (K, 2M)."""
    c, v, r = pipes.starts, pipes.directions, pipes.radii
    a = np.einsum("kmi,mi->km", O[:, None, :] - c[None, :, :], v)
    p_axis = c[None, :, :] + a[:, :, None] * v[None, :, :]
    to_axis = p_axis - O[:, None, :]
    tx, ty, tz = to_axis[..., 0], to_axis[..., 1], to_axis[..., 2]
    l = np.sqrt(tx * tx + ty * ty + tz * tz)
    valid = l > r * (1.0 + 1e-9)
    ls = np.where(valid, l, 1.0)
    u = to_axis / ls[:, :, None]
    beta = np.arcsin(np.minimum(np.maximum(r / ls, 0.0), 1.0))
    delta = np.sqrt(np.maximum(ls * ls - r * r, 0.0))
    vxu = np.empty_like(u)
    vxu[..., 0] = v[:, 1] * u[..., 2] - v[:, 2] * u[..., 1]
    vxu[..., 1] = v[:, 2] * u[..., 0] - v[:, 0] * u[..., 2]
    vxu[..., 2] = v[:, 0] * u[..., 1] - v[:, 1] * u[..., 0]
    cb, sb = np.cos(beta), np.sin(beta)
    dir_l = cb[:, :, None] * u + sb[:, :, None] * vxu
    dir_r = cb[:, :, None] * u - sb[:, :, None] * vxu
    point = np.empty((O.shape[0], 2 * c.shape[0], 3))
    point[:, 0::2] = O[:, None, :] + delta[:, :, None] * dir_l
    point[:, 1::2] = O[:, None, :] + delta[:, :, None] * dir_r
    outward = (point - np.repeat(p_axis, 2, axis=1)) / np.repeat(np.where(valid, r, 1.0), 2, axis=1)[:, :, None]
    return (point, np.repeat(v, 2, axis=0), outward, np.repeat(-a, 2, axis=1),
            np.repeat(pipes.lengths - a, 2, axis=1), np.repeat(valid, 2, axis=1))


def _empty() -> LimbSamples:
    z3 = np.zeros((0, 3))
    zi = np.zeros(0, dtype=np.intp)
    return LimbSamples(p_rack=z3, p_cam=z3, uv=np.zeros((0, 2)), normal_px=np.zeros((0, 2)),
                       J_uv_pcam=np.zeros((0, 2, 3)), pipe=zi, limb=zi)
