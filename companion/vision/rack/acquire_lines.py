"""Rack acquisition, step 1: straight edges, the pipes' direction and their limb angles.

Line segments come from OpenCV's LSD on a downscaled image. Every segment and the camera centre
span an interpretation plane (unit normal `n`, cam frame). The limbs of parallel pipes all lie in
planes containing the pipes' direction `d`, so `d` is the direction orthogonal to all their
normals; the autopilot's roll and pitch give the rack's up axis `u` in the camera, which makes
`d` one angle (the yaw) found by a length-weighted vote. In the cross-section plane orthogonal
to `d` (basis e_x = d × u, e_z = u) each limb plane is a ray from the camera at the angle
`theta` = atan2(t·e_z, t·e_x) of its downward direction t: the 2-D picture in which a pipe is a
circle and its silhouette the two tangent rays. Pixels follow OpenCV (integer coordinates are
pixel centres); angles in radians; the cam frame is OpenCV's optical frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.model import PipeArrays

BoolArray = np.ndarray[Any, np.dtype[np.bool_]]
GrayImage = np.ndarray[Any, np.dtype[np.uint8]]


@dataclass(frozen=True)
class Segments:
    """Straight edge segments (N) at full resolution: end pixels `uv0`, `uv1` (N, 2), `length_px`
    (N,), unit interpretation-plane normals `normal_cam` (N, 3), and `contrast` (N,): the mean grey
    difference across the segment, positive when the side to the right of uv0 -> uv1 (image x
    right, y down) is brighter."""

    uv0: FloatArray
    uv1: FloatArray
    length_px: FloatArray
    normal_cam: FloatArray
    contrast: FloatArray

    def subset(self, keep: Any) -> Segments:
        return Segments(self.uv0[keep], self.uv1[keep], self.length_px[keep], self.normal_cam[keep],
                        self.contrast[keep])


def downscale(gray: GrayImage, scale: float) -> GrayImage:
    """`gray` resized by `scale` (area averaging); the same array when scale >= 1."""
    if scale >= 1.0:
        return gray
    return np.asarray(cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA), dtype=np.uint8)


def detect_segments(
    gray: GrayImage, small: GrayImage, camera: PinholeCamera, scale: float, min_length_px: float, min_contrast: float
) -> Segments:
    """LSD segments of `gray` (H, W) found in `small` (`gray` downscaled by `scale`, 0 < scale <= 1),
    at least `min_length_px` long (full-resolution pixels) with |contrast| >= `min_contrast` grey
    levels (measured in `gray`)."""
    lines = cv2.createLineSegmentDetector().detect(small)[0]
    if lines is None or len(lines) == 0:
        return _empty_segments()
    seg = lines.reshape(-1, 4).astype(np.float64)
    # Small-image pixel centres back to full-resolution pixel centres.
    seg = (seg + 0.5) / scale - 0.5
    uv0, uv1 = seg[:, :2], seg[:, 2:]
    length = np.hypot(uv1[:, 0] - uv0[:, 0], uv1[:, 1] - uv0[:, 1])
    keep = length >= min_length_px
    uv0, uv1, length = uv0[keep], uv1[keep], length[keep]
    if length.size == 0:
        return _empty_segments()
    contrast = _side_contrast(gray, uv0, uv1, length)
    keep = np.abs(contrast) >= min_contrast
    uv0, uv1, length, contrast = uv0[keep], uv1[keep], length[keep], contrast[keep]
    rays0 = _rays(camera, uv0)
    rays1 = _rays(camera, uv1)
    n = np.cross(rays0, rays1)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return Segments(uv0=uv0, uv1=uv1, length_px=length, normal_cam=n, contrast=contrast)


def _empty_segments() -> Segments:
    z2 = np.zeros((0, 2))
    return Segments(z2, z2, np.zeros(0), np.zeros((0, 3)), np.zeros(0))


def _rays(camera: PinholeCamera, uv: FloatArray) -> FloatArray:
    xy = camera.normalized(uv)
    return np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)


def _side_contrast(gray: GrayImage, uv0: FloatArray, uv1: FloatArray, length: FloatArray) -> FloatArray:
    """Mean grey level 3 px right of each segment minus 3 px left (7 points along its middle 70 %)."""
    t_dir = (uv1 - uv0) / length[:, None]
    right = np.stack([-t_dir[:, 1], t_dir[:, 0]], axis=1)  # image x right, y down: (−ty, tx) is "right"
    s = np.linspace(0.15, 0.85, 7)
    pts = uv0[:, None, :] + s[None, :, None] * (uv1 - uv0)[:, None, :]  # (N, 7, 2)
    off = 3.0 * right[:, None, :]
    both = np.concatenate([pts + off, pts - off], axis=1).astype(np.float32)  # (N, 14, 2)
    vals = cv2.remap(gray, np.ascontiguousarray(both[..., 0]), np.ascontiguousarray(both[..., 1]),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    return np.asarray(vals[:, :7].mean(axis=1) - vals[:, 7:].mean(axis=1))


def horizontal_basis(up_cam: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors (a, b) spanning the plane orthogonal to `up_cam` (cam frame)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up_cam[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = helper - (helper @ up_cam) * up_cam
    a /= np.linalg.norm(a)
    return a, np.cross(up_cam, a)


def direction_candidates(
    seg: Segments, up_cam: FloatArray, bin_rad: float, max_candidates: int, min_separation_rad: float
) -> FloatArray:
    """Horizontal directions (K, 3), cam frame, that many segment planes contain (strongest first).

    A plane with normal n contains d(psi) = cos(psi) a + sin(psi) b when n·d = 0; each segment
    votes, weighted by its length, for that psi (modulo pi) in a circularly smoothed histogram.
    """
    if seg.length_px.size == 0:
        return np.zeros((0, 3))
    a, b = horizontal_basis(up_cam)
    na, nb = seg.normal_cam @ a, seg.normal_cam @ b
    horiz = np.hypot(na, nb)
    psi = np.mod(np.arctan2(-na, nb), np.pi)
    n_bins = round(np.pi / bin_rad)
    hist = np.bincount(np.minimum((psi / bin_rad).astype(np.intp), n_bins - 1), weights=seg.length_px * horiz,
                       minlength=n_bins)
    smooth = hist + 0.5 * (np.roll(hist, 1) + np.roll(hist, -1))
    out: list[int] = []
    order = np.argsort(-smooth)
    sep_bins = min_separation_rad / bin_rad
    for i in order:
        if smooth[i] <= 0 or len(out) >= max_candidates:
            break
        if any(min(abs(i - j), n_bins - abs(i - j)) < sep_bins for j in out):
            continue
        out.append(int(i))
    ang = (np.asarray(out, dtype=np.float64) + 0.5) * bin_rad
    return np.asarray(np.cos(ang)[:, None] * a[None, :] + np.sin(ang)[:, None] * b[None, :])


def refine_direction(
    seg: Segments, d0_cam: FloatArray, up_cam: FloatArray, tol_rad: float
) -> tuple[FloatArray, BoolArray]:
    """Pipe direction through the inlier segments (|n·d| < sin tol) as the least-squares null vector of
    their plane normals (length-weighted), kept near the horizontal by a weak pull toward `d0`.

    Returns the unit direction (3,) (sign of d0) and the inlier mask (N,).
    """
    inl = np.abs(seg.normal_cam @ d0_cam) < np.sin(tol_rad)
    if np.count_nonzero(inl) < 2:
        return d0_cam, inl
    n = seg.normal_cam[inl]
    w = seg.length_px[inl]
    M = (n * w[:, None]).T @ n
    # The attitude is uncertain by about a degree: a soft pull toward the horizontal (up·d = 0)
    # decides only when all limbs are (nearly) coplanar with one another.
    M = M + 3.0 * float(w.sum()) * np.outer(up_cam, up_cam)
    _, vecs = np.linalg.eigh(M)
    d = vecs[:, 0]
    d = d if d @ d0_cam >= 0 else -d
    inl = np.abs(seg.normal_cam @ d) < np.sin(tol_rad)
    return d, inl


@dataclass(frozen=True)
class LimbClusters:
    """Observed limbs of pipes along `d` (K clusters, sorted by angle) in the cross-section plane.

    `theta` (K,) angle of the limb plane's downward ray (rad, increasing toward e_x); `polarity`
    (K,) +1 when the image is brighter on the +e_x side, -1 otherwise; `length_px` (K,) total
    segment length; `contrast` (K,) length-weighted mean |contrast| (grey levels). `e_x`, `e_z`,
    `d` the cross-section basis and pipe direction (cam frame).
    """

    theta: FloatArray
    polarity: FloatArray
    length_px: FloatArray
    contrast: FloatArray
    d: FloatArray
    e_x: FloatArray
    e_z: FloatArray


def limb_clusters(
    seg: Segments, inliers: BoolArray, d_cam: FloatArray, up_cam: FloatArray, camera: PinholeCamera, merge_rad: float
) -> LimbClusters:
    """Angles and polarities of the inlier segments, merged into limbs when closer than `merge_rad`."""
    e_z = up_cam - (up_cam @ d_cam) * d_cam
    e_z /= np.linalg.norm(e_z)
    e_x = np.cross(d_cam, e_z)
    s = seg.subset(inliers)
    if s.length_px.size == 0:
        z = np.zeros(0)
        return LimbClusters(z, z, z, z, d_cam, e_x, e_z)
    t = np.cross(s.normal_cam, d_cam)
    t *= np.where(t @ e_z > 0.0, -1.0, 1.0)[:, None]
    theta = np.arctan2(t @ e_z, t @ e_x)
    # Polarity along +e_x: compare the segment's "right" side with the image motion of a step toward +e_x.
    mid = 0.5 * (s.uv0 + s.uv1)
    ray = _rays(camera, mid)
    p = camera.project(ray)
    q = camera.project(ray + 0.01 * np.linalg.norm(ray, axis=1, keepdims=True) * e_x[None, :])
    tdir = s.uv1 - s.uv0
    right = np.stack([-tdir[:, 1], tdir[:, 0]], axis=1)
    toward = np.sign(np.einsum("ij,ij->i", q - p, right))
    pol = np.sign(s.contrast) * toward
    order = np.argsort(theta)
    theta, pol, length, con = theta[order], pol[order], s.length_px[order], np.abs(s.contrast[order])
    # A new cluster starts where the angle jumps by more than merge_rad or the polarity flips.
    new = np.ones(theta.size, dtype=bool)
    new[1:] = (np.diff(theta) > merge_rad) | (pol[1:] != pol[:-1])
    cid = np.cumsum(new) - 1
    k = int(cid[-1]) + 1
    wsum = np.bincount(cid, weights=length, minlength=k)
    return LimbClusters(
        theta=np.bincount(cid, weights=theta * length, minlength=k) / wsum,
        polarity=pol[new],
        length_px=np.asarray(wsum, dtype=np.float64),
        contrast=np.bincount(cid, weights=con * length, minlength=k) / wsum,
        d=d_cam,
        e_x=e_x,
        e_z=e_z,
    )


def image_theta_range(camera: PinholeCamera, limbs: LimbClusters) -> tuple[float, float]:
    """The range of cross-section angles (rad) of the image's pixels (corners are the extremes)."""
    corners = np.array([[0.0, 0.0], [camera.width - 1.0, 0.0], [0.0, camera.height - 1.0],
                        [camera.width - 1.0, camera.height - 1.0]])
    r = _rays(camera, corners)
    r = r - (r @ limbs.d)[:, None] * limbs.d[None, :]
    th = np.arctan2(r @ limbs.e_z, r @ limbs.e_x)
    return float(th.min()), float(th.max())


def visible_length_px(camera: PinholeCamera, limbs: LimbClusters, theta: FloatArray) -> FloatArray:
    """Length (px) inside the image of the limb lines at cross-section angles `theta` (K,) (pinhole)."""
    t = np.cos(theta)[:, None] * limbs.e_x[None, :] + np.sin(theta)[:, None] * limbs.e_z[None, :]
    n = np.cross(t, limbs.d[None, :])
    # Image line l·(u, v, 1) = 0 with l = K^-T n.
    l_img = np.linalg.solve(camera.K.T, n.T).T
    W, H = camera.width - 1.0, camera.height - 1.0
    a, b, c = l_img[:, 0], l_img[:, 1], l_img[:, 2]
    pts = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for u_fixed in (0.0, W):
            v = -(a * u_fixed + c) / b
            pts.append(np.stack([np.full_like(v, u_fixed), v], axis=1))
        for v_fixed in (0.0, H):
            u = -(b * v_fixed + c) / a
            pts.append(np.stack([u, np.full_like(u, v_fixed)], axis=1))
    P = np.stack(pts, axis=1)  # (K, 4, 2)
    inside = (P[..., 0] >= -1e-6) & (P[..., 0] <= W + 1e-6) & (P[..., 1] >= -1e-6) & (P[..., 1] <= H + 1e-6)
    P = np.where(inside[..., None], P, np.nan)
    lo = np.nanmin(np.where(inside[..., None], P, np.inf), axis=1)
    hi = np.nanmax(np.where(inside[..., None], P, -np.inf), axis=1)
    length = np.hypot(hi[:, 0] - lo[:, 0], hi[:, 1] - lo[:, 1])
    return np.asarray(np.where(np.isfinite(length), length, 0.0))


def crossing_y_candidates(
    seg: Segments,
    T_rack_cam: FloatArray,
    pipes: PipeArrays,
    extra_index: Any,
    y_lo_m: float,
    y_hi_m: float,
    angle_tol_rad: float,
    merge_m: float,
    max_candidates: int,
) -> FloatArray:
    """Camera y positions (rack frame, m) at which a segment would be a limb of an extra pipe.

    A limb plane (unit normal n, rack frame) through the camera centre o = (x, y, z) is tangent to
    the pipe with axis point c and radius r when n·(c - o) = ±r: linear in y for the fixed x, z
    and rotation of the hypothesis. Candidates are voted by segment length within `merge_m`
    (strongest first; at most `max_candidates`, at least `2 merge_m` apart).
    """
    if seg.length_px.size == 0:
        return np.zeros(0)
    R = T_rack_cam[:3, :3]
    o = T_rack_cam[:3, 3]
    n_r = seg.normal_cam @ R.T  # (N, 3) rack frame
    ys, ws = [], []
    for k in np.atleast_1d(np.asarray(extra_index)):
        e, c, r = pipes.directions[k], pipes.starts[k], float(pipes.radii[k])
        ok = (np.abs(n_r @ e) < np.sin(angle_tol_rad)) & (np.abs(n_r[:, 1]) > 0.2)
        if not np.any(ok):
            continue
        n = n_r[ok]
        base = n @ c - n[:, 0] * o[0] - n[:, 2] * o[2]
        for sgn in (-1.0, 1.0):
            ys.append((base + sgn * r) / n[:, 1])
            ws.append(seg.length_px[ok])
    if not ys:
        return np.zeros(0)
    y = np.concatenate(ys)
    w = np.concatenate(ws)
    keep = (y >= y_lo_m) & (y <= y_hi_m)
    y, w = y[keep], w[keep]
    if y.size == 0:
        return np.zeros(0)
    votes = (np.abs(y[:, None] - y[None, :]) <= merge_m).astype(np.float64) @ w
    out: list[float] = []
    for i in np.argsort(-votes):
        if len(out) >= max_candidates:
            break
        if all(abs(y[i] - v) >= 2.0 * merge_m for v in out):
            out.append(float(y[i]))
    return np.asarray(out)
