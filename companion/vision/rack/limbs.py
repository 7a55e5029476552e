"""Visible limbs of the pipes (Lippiello & Cacace eq. 10-14), clipping, sampling and occlusion.

All functions are vectorized over pipes and samples. Frames: `rack` (the paper's P) and `cam`
(OpenCV optical). `T_rack_cam` is the camera pose in the rack frame. Lengths in metres, pixels
follow OpenCV (integer coordinates are pixel centres).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.limbs_jit import kernels as jit_kernels
from companion.vision.rack.model import PipeArrays

IntArray = np.ndarray[Any, np.dtype[np.intp]]
BoolArray = np.ndarray[Any, np.dtype[np.bool_]]


@dataclass(frozen=True)
class LimbLines:
    """The two visible limb lines of each pipe seen from the camera centre (L = 2 M lines).

    Line l is `point[l] + s * direction[l]` (rack frame, m) for s in [s_min[l], s_max[l]]
    (the part on the pipe; not clipped to the image). Line 2 m is the side R(v, +β) u of
    pipe m (eq. 13), line 2 m + 1 the side R(v, -β) u (eq. 14). `outward[l]` is the unit
    surface normal at the limb (rack frame). `valid[l]` is false when the camera is inside
    the pipe's cylinder.
    """

    point: FloatArray
    direction: FloatArray
    outward: FloatArray
    s_min: FloatArray
    s_max: FloatArray
    valid: BoolArray


def limb_lines(o_rack: FloatArray, pipes: PipeArrays) -> LimbLines:
    """Limb lines of every pipe seen from camera centre `o_rack` (3,) (eq. 10-14)."""
    c, v, r = pipes.starts, pipes.directions, pipes.radii
    a = np.einsum("mi,mi->m", o_rack[None, :] - c, v)  # axial coordinate of the camera centre
    p_axis = c + a[:, None] * v  # eq. 10: closest axis point to the camera
    to_axis = p_axis - o_rack[None, :]
    l = np.sqrt(to_axis[:, 0] * to_axis[:, 0] + to_axis[:, 1] * to_axis[:, 1] + to_axis[:, 2] * to_axis[:, 2])
    valid = l > r * (1.0 + 1e-9)
    ls = np.where(valid, l, 1.0)
    u = to_axis / ls[:, None]  # eq. 11
    beta = np.arcsin(np.minimum(np.maximum(r / ls, 0.0), 1.0))
    delta = np.sqrt(np.maximum(ls * ls - r * r, 0.0))  # eq. 12
    vxu = np.empty_like(u)  # v x u
    vxu[:, 0] = v[:, 1] * u[:, 2] - v[:, 2] * u[:, 1]
    vxu[:, 1] = v[:, 2] * u[:, 0] - v[:, 0] * u[:, 2]
    vxu[:, 2] = v[:, 0] * u[:, 1] - v[:, 1] * u[:, 0]
    cb, sb = np.cos(beta), np.sin(beta)
    # Both sides of each pipe in one (M, 2, 3) array, rows 2 m and 2 m + 1 once flattened.
    cu, svu = cb[:, None] * u, sb[:, None] * vxu
    dirs = np.empty((c.shape[0], 2, 3))
    dirs[:, 0] = cu + svu  # R(v, +β) u (u ⟂ v)
    dirs[:, 1] = cu - svu  # R(v, -β) u
    point3 = o_rack + delta[:, None, None] * dirs  # eq. 13, 14
    outward = (point3 - p_axis[:, None, :]) / np.where(valid, r, 1.0)[:, None, None]
    return LimbLines(
        point=point3.reshape(-1, 3),
        direction=v.repeat(2, axis=0),
        outward=outward.reshape(-1, 3),
        s_min=(-a).repeat(2),
        s_max=(pipes.lengths - a).repeat(2),
        valid=valid.repeat(2),
    )


def clip_lines_to_view(
    A_cam: FloatArray,
    D_cam: FloatArray,
    s_min: FloatArray,
    s_max: FloatArray,
    camera: PinholeCamera,
    margin_px: float,
    z_near_m: float,
) -> tuple[FloatArray, FloatArray]:
    """Clip lines A + s D (cam frame) to the near plane and the image rectangle (pinhole part).

    Returns the clipped parameter interval (s0, s1); empty where s0 >= s1.
    """
    umax = camera.width - 1.0 - margin_px
    vmax = camera.height - 1.0 - margin_px
    m = margin_px
    fx, fy, sk, cx, cy = camera.fx, camera.fy, camera.skew, camera.cx, camera.cy
    ks = jit_kernels()
    if ks is not None:
        # The same arithmetic per line, compiled (`limbs_jit.py`).
        s0_k, s1_k = ks.clip_lines(np.ascontiguousarray(A_cam, dtype=np.float64),
                                   np.ascontiguousarray(D_cam, dtype=np.float64),
                                   np.ascontiguousarray(s_min, dtype=np.float64),
                                   np.ascontiguousarray(s_max, dtype=np.float64),
                                   float(fx), float(fy), float(sk), float(cx), float(cy), float(umax), float(vmax),
                                   float(m), float(z_near_m))
        return s0_k, s1_k
    # Constraints a + b s >= 0: the same linear forms of the points A (rows :n) and directions D (rows n:).
    n = A_cam.shape[0]
    P = np.concatenate([A_cam, D_cam])
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    ab = np.empty((2 * n, 5))
    ab[:, 0] = Z
    ab[:n, 0] -= z_near_m
    u_lin = fx * X + sk * Y
    v_lin = fy * Y
    ab[:, 1] = u_lin + (cx - m) * Z
    ab[:, 2] = -(u_lin + (cx - umax) * Z)
    ab[:, 3] = v_lin + (cy - m) * Z
    ab[:, 4] = -(v_lin + (cy - vmax) * Z)
    a_c, b_c = ab[:n], ab[n:]
    with np.errstate(divide="ignore", invalid="ignore"):
        root = -a_c / b_c
    pos = b_c > 1e-12
    neg = b_c < -1e-12
    flat_bad = ~(pos | neg) & (a_c < 0.0)
    lo = np.where(pos, root, -np.inf).max(axis=1)
    hi = np.where(neg, root, np.inf).min(axis=1)
    s0 = np.maximum(s_min, lo)
    s1 = np.minimum(s_max, hi)
    bad = flat_bad.any(axis=1)
    s1 = np.where(bad, s0 - 1.0, s1)
    return s0, s1


def _ray_cylinder_terms(
    o_rack: FloatArray, d_rack: FloatArray, pipes: PipeArrays, radius_margin_m: Any
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, BoolArray]:
    """Per ray and pipe (N, M): A, half B, the discriminant, d.v, and (M,) w.v of `ray_cylinder_hits`'
    quadratic A t^2 + 2 B t + C = 0, and where it has two roots (the only pairs that can hit)."""
    c, v, r = pipes.starts, pipes.directions, pipes.radii
    w = o_rack[None, :] - c  # (M, 3)
    wv = np.einsum("mi,mi->m", w, v)  # (M,)
    dv = d_rack @ v.T  # (N, M)
    dw = d_rack @ w.T  # (N, M)
    w_perp2 = np.einsum("mi,mi->m", w, w) - wv * wv  # (M,)
    A = 1.0 - dv * dv
    B = dw - dv * wv[None, :]  # half of the usual B
    rr = r[None, :] + np.asarray(radius_margin_m, dtype=np.float64).reshape(-1, 1)
    C = w_perp2[None, :] - rr * rr
    disc = B * B - A * C
    hit = (disc > 0.0) & (A > 1e-12)
    return A, B, disc, dv, wv, hit


def _first_hits(
    A: FloatArray, B: FloatArray, disc: FloatArray, dv: FloatArray, wv: FloatArray, length: FloatArray
) -> FloatArray:
    """Distance to the first hit within the pipe's length (inf if none) of selected (ray, pipe) pairs
    (1-D, all with two roots): the near root (-B - sq) / A unless it fails, then the far one."""
    sq = np.sqrt(disc)
    t_out = np.full(A.shape, np.inf)
    for t in ((-B - sq) / A, (-B + sq) / A):
        s = wv + t * dv
        ok = (t > 0.0) & (s >= 0.0) & (s <= length) & (t < t_out)
        np.copyto(t_out, t, where=ok)
    return t_out


def ray_cylinder_hits(
    o_rack: FloatArray, d_rack: FloatArray, pipes: PipeArrays, radius_margin_m: Any = 0.0
) -> FloatArray:
    """Distance t (N, M) along unit rays o + t d (N, 3) to the first hit of each finite pipe; inf if none.

    `radius_margin_m` (scalar or (N,)) inflates every radius (used to keep samples away from
    occluding silhouettes). Both roots are tried so a ray entering through the pipe's open end
    still counts when it meets the wall inside the length.
    """
    A, B, disc, dv, wv, hit = _ray_cylinder_terms(o_rack, d_rack, pipes, radius_margin_m)
    t_out: FloatArray = np.full(A.shape, np.inf)
    # Roots only for the pairs whose line meets the (inflated) cylinder: mostly each ray's own pipe (a sixth
    # of the pairs on the paper's rack), the same values as computing them everywhere (test).
    sel = np.flatnonzero(hit)
    m = sel % A.shape[1]
    t_out.ravel()[sel] = _first_hits(A.ravel()[sel], B.ravel()[sel], disc.ravel()[sel], dv.ravel()[sel], wv[m],
                                     pipes.lengths[m])
    return t_out


def occluded(
    o_rack: FloatArray,
    p_rack: FloatArray,
    own_pipe: IntArray,
    pipes: PipeArrays,
    margin_m: Any = 0.0,
) -> BoolArray:
    """True where point p (N, 3) on pipe `own_pipe` (N,) is hidden from o by another pipe."""
    ks = jit_kernels()
    if ks is not None:
        # Per sample and pipe, compiled (`limbs_jit.py`: the same test, dot products without fused multiply-adds).
        n = p_rack.shape[0]
        margin = np.ascontiguousarray(np.broadcast_to(np.asarray(margin_m, dtype=np.float64), (n,)))
        return np.asarray(ks.occluded(np.ascontiguousarray(o_rack, dtype=np.float64),
                                      np.ascontiguousarray(p_rack, dtype=np.float64),
                                      np.ascontiguousarray(own_pipe, dtype=np.intp), pipes.starts, pipes.directions,
                                      pipes.radii, pipes.lengths, margin))
    d = p_rack - o_rack[None, :]
    dist = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    d = d / np.maximum(dist, 1e-12)[:, None]
    A, B, disc, dv, wv, hit = _ray_cylinder_terms(o_rack, d, pipes, margin_m)
    n, n_pipes = A.shape
    hit[np.arange(n), own_pipe] = False  # a point's own pipe does not hide it
    out = np.zeros(n, dtype=bool)
    sel = np.flatnonzero(hit)
    if sel.size:
        # `ray_cylinder_hits`' distances of the pairs that can hit (the same arithmetic), against the point's.
        row, m = sel // n_pipes, sel % n_pipes
        t = _first_hits(A.ravel()[sel], B.ravel()[sel], disc.ravel()[sel], dv.ravel()[sel], wv[m], pipes.lengths[m])
        out[row[t < dist[row] * (1.0 - 1e-6)]] = True
    return out


@dataclass(frozen=True)
class LimbSamples:
    """Measurement points on the visible limbs (N samples).

    `p_rack`/`p_cam` (N, 3) points on the limb (m); `uv` (N, 2) pixels; `normal_px` (N, 2) unit
    image normal pointing out of the pipe; `J_uv_pcam` (N, 2, 3) projection Jacobian;
    `pipe` (N,) pipe index; `limb` (N,) limb index (2 * pipe + side); `segments_uv` (L, 2, 2)
    the clipped limb segments' end pixels (pinhole part) and `segment_limb` (L,) their limb index.
    """

    p_rack: FloatArray
    p_cam: FloatArray
    uv: FloatArray
    normal_px: FloatArray
    J_uv_pcam: FloatArray
    pipe: IntArray
    limb: IntArray
    segments_uv: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    segment_limb: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.intp))


@functools.lru_cache(maxsize=8)
def _image_uniform(K: int) -> tuple[FloatArray, FloatArray]:
    """Read-only sample parameters t = (k + 0.5) / K (1, K) along a limb's image and 1 - t."""
    t = ((np.arange(K) + 0.5) / K)[None, :]
    one_minus_t = 1.0 - t
    t.flags.writeable = False
    one_minus_t.flags.writeable = False
    return t, one_minus_t


def inside_margin(uv: FloatArray, camera: PinholeCamera, margin_px: float) -> BoolArray:
    """Which pixels uv (N, 2) lie at least `margin_px` inside the image (pixel centres at integers; NaN: no)."""
    lo = -0.5 + margin_px
    with np.errstate(invalid="ignore"):
        return np.asarray((uv[:, 0] >= lo) & (uv[:, 1] >= lo) & (uv[:, 0] <= camera.width - 0.5 - margin_px)
                          & (uv[:, 1] <= camera.height - 0.5 - margin_px))

def sample_limbs(
    T_rack_cam: FloatArray,
    camera: PinholeCamera,
    pipes: PipeArrays,
    samples_per_limb: int,
    margin_px: float = 4.0,
    min_length_px: float = 12.0,
    z_near_m: float = 0.1,
    occlusion_margin_px: float = 3.0,
    lines: LimbLines | None = None,
) -> LimbSamples:
    """Sample every visible limb at `samples_per_limb` image-uniform points; drop occluded samples.

    `lines`: `limb_lines(T_rack_cam[:3, 3], pipes)` when the caller has it already.
    """
    R_rc = T_rack_cam[:3, :3]
    o = T_rack_cam[:3, 3]
    if lines is None:
        lines = limb_lines(o, pipes)
    R_cr = R_rc.T
    A_cam = (lines.point - o) @ R_rc  # R_cam_rack (p - o)
    D_cam = lines.direction @ R_rc
    s0, s1 = clip_lines_to_view(A_cam, D_cam, lines.s_min, lines.s_max, camera, margin_px, z_near_m)
    K = int(samples_per_limb)
    ks = jit_kernels() if K >= 2 else None  # (numpy's product of a single row rounds differently)
    if ks is not None:
        # Lines to samples in one compiled call, the same arithmetic (`limbs_jit.py`).
        t, one_minus_t = _image_uniform(K)
        idx, seg, p_cam, p_rack, limb, margin_m = ks.limb_points(
            A_cam, D_cam, s0, s1, lines.valid, t[0], one_minus_t[0], float(camera.fx), float(camera.fy),
            float(camera.skew), float(camera.cx), float(camera.cy), float(min_length_px), R_cr, o,
            float(occlusion_margin_px))
        if idx.size == 0:
            return _empty_samples()
        pipe = limb // 2
    else:
        idx, seg, p_cam, p_rack, limb, pipe, margin_m = _lines_to_samples(
            A_cam, D_cam, s0, s1, lines.valid, camera, K, min_length_px, R_cr, o, occlusion_margin_px)
        if idx.size == 0:
            return _empty_samples()
    vis = ~occluded(o, p_rack, pipe, pipes, margin_m)
    uv, J = camera.project_with_jacobian(p_cam)
    vis &= inside_margin(uv, camera, margin_px)
    if not vis.all():
        ii = np.flatnonzero(vis)
        p_cam, p_rack, uv, J, limb, pipe = p_cam[ii], p_rack[ii], uv[ii], J[ii], limb[ii], pipe[ii]
    # Image tangent (direction of the pipe axis) and outward normal through the Jacobian.
    if ks is not None:
        n_img = ks.limb_normals(J, D_cam, np.ascontiguousarray(lines.outward @ R_rc), limb)
    else:
        t_img = np.einsum("nij,nj->ni", J, D_cam[limb])
        m_img = np.einsum("nij,nj->ni", J, (lines.outward @ R_rc)[limb])
        t_img /= np.maximum(np.sqrt(t_img[:, 0:1] * t_img[:, 0:1] + t_img[:, 1:2] * t_img[:, 1:2]), 1e-12)
        n_img = np.empty_like(t_img)
        n_img[:, 0] = -t_img[:, 1]
        n_img[:, 1] = t_img[:, 0]
        flip = n_img[:, 0] * m_img[:, 0] + n_img[:, 1] * m_img[:, 1] < 0.0
        np.negative(n_img, out=n_img, where=flip[:, None])
    return LimbSamples(p_rack=p_rack, p_cam=p_cam, uv=uv, normal_px=n_img, J_uv_pcam=J, pipe=pipe, limb=limb,
                       segments_uv=seg, segment_limb=idx)


def _lines_to_samples(
    A_cam: FloatArray, D_cam: FloatArray, s0: FloatArray, s1: FloatArray, valid: BoolArray, camera: PinholeCamera,
    K: int, min_length_px: float, R_cr: FloatArray, o: FloatArray, occlusion_margin_px: float,
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, IntArray, IntArray, FloatArray]:
    """`sample_limbs` from the clipped lines to the samples in numpy (see `limbs_jit._limb_points`): kept line
    indices, their end pixels, p_cam, p_rack, limb, pipe and occlusion margin (m) of every sample."""
    empty = (np.zeros(0, dtype=np.intp), np.zeros((0, 2, 2)), np.zeros((0, 3)), np.zeros((0, 3)),
             np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), np.zeros(0))
    keep = valid & (s1 > s0)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return empty
    # Both clipped ends of each line at once (L, 2, 3): row 0 at s0, row 1 at s1.
    s01 = np.empty((idx.size, 2))
    s01[:, 0] = s0[idx]
    s01[:, 1] = s1[idx]
    P = A_cam[idx][:, None, :] + s01[:, :, None] * D_cam[idx][:, None, :]
    # Image length of each clipped line (pinhole part) to drop tiny ones.
    U = P[:, :, :2] / P[:, :, 2:3]
    len_px = np.hypot((U[:, 1, 0] - U[:, 0, 0]) * camera.fx, (U[:, 1, 1] - U[:, 0, 1]) * camera.fy)
    long_enough = len_px >= min_length_px
    if not long_enough.all():
        idx, P, U = idx[long_enough], P[long_enough], U[long_enough]
    if idx.size == 0:
        return empty
    seg = np.empty((idx.size, 2, 2))
    seg[:, :, 0] = U[:, :, 0] * camera.fx + U[:, :, 1] * camera.skew + camera.cx
    seg[:, :, 1] = U[:, :, 1] * camera.fy + camera.cy
    t, one_minus_t = _image_uniform(K)
    Za, Zb = P[:, 0, 2:3], P[:, 1, 2:3]
    tZa = t * Za
    lam = tZa / (tZa + one_minus_t * Zb)  # (L, K)
    p_cam = (1.0 - lam)[..., None] * P[:, None, 0, :] + lam[..., None] * P[:, None, 1, :]
    p_cam = p_cam.reshape(-1, 3)
    limb = idx.repeat(K)
    pipe = limb // 2
    p_rack = p_cam @ R_cr + o
    # Occlusion by other pipes, with a margin of a few pixels at the sample's depth.
    margin_m = occlusion_margin_px * p_cam[:, 2] / camera.fx
    return idx, seg, p_cam, p_rack, limb, pipe, margin_m


def _empty_samples() -> LimbSamples:
    z3 = np.zeros((0, 3))
    zi = np.zeros(0, dtype=np.intp)
    return LimbSamples(p_rack=z3, p_cam=z3, uv=np.zeros((0, 2)), normal_px=np.zeros((0, 2)),
                       J_uv_pcam=np.zeros((0, 2, 3)), pipe=zi, limb=zi)
