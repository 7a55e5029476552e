"""The ground under the rack as a second, independent reference: a plane z = z_g (rack frame, m)
whose height is estimated online with the pose.

Limbs of a few parallel pipes at one depth leave two combinations nearly unobservable: the
translation along the pipes (without texture in view) and a roll traded against a sideways
slide. Points on the ground, at a different depth, separate both. Each ground corner is found in
the previous image outside the pipes, its ray from the previous (accepted) pose is intersected
with the plane, and its Lucas-Kanade position in the current image is a measurement of the
current pose and of z_g: a frame-to-frame (visual odometry) constraint that stops drift in
those directions; the pipes' limbs keep the absolute pose. Pure functions, vectorized over points.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.corners import shi_tomasi, strong_corners
from companion.vision.rack.limbs import LimbLines, clip_lines_to_view, limb_lines
from companion.vision.rack.model import PipeArrays
from companion.vision.rack.motion import pose_jacobian
from companion.vision.rack.rack_jit import kernels


def plane_points(o_rack: FloatArray, d_rack: FloatArray, z_g: float) -> tuple[FloatArray, FloatArray]:
    """Intersections X (K, 3) of rays o + t d (rack frame) with the plane z = z_g, and dX/dz_g (K, 3).

    `o_rack` is one origin (3,) for all rays or one per ray (K, 3). Rays that do not point down towards the
    plane give NaN rows.
    """
    ks = kernels()
    if ks is not None and o_rack.ndim in (1, 2):
        # The same arithmetic per ray, compiled (`rack_jit.py`).
        X_k, dX_k = ks.plane_points(np.ascontiguousarray(o_rack, dtype=np.float64).reshape(-1, 3),
                                    np.ascontiguousarray(d_rack, dtype=np.float64), float(z_g))
        return X_k, dX_k
    dz = d_rack[:, 2]
    ok = dz < -1e-6
    dz_s = np.where(ok, dz, np.nan)
    t = (z_g - o_rack[..., 2]) / dz_s
    X = o_rack + t[:, None] * d_rack
    X[~(t > 0)] = np.nan
    return X, d_rack / dz_s[:, None]


def ground_rows(
    T_rack_cam: FloatArray, camera: PinholeCamera, X: FloatArray, dX_dz: FloatArray, uv: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Rows (2K, 7) and residuals (2K,) of ground points X (K, 3) measured at pixels uv (K, 2).

    Columns: the pose twist (right perturbation, cam frame, as `pose_jacobian`) and z_g; the
    residual is measured minus predicted pixel (px), the rows its first-order change. Points
    with a NaN position (their ray misses the plane) or behind the camera get zero rows.
    """
    R = T_rack_cam[:3, :3]
    k = X.shape[0]
    A = np.zeros((2 * k, 7))
    r = np.zeros((k, 2))
    # Points whose ray misses the plane (NaN) or that are behind the camera give zero rows.
    fin = np.isfinite(X)
    p_cam = (np.where(fin, X, 0.0) - T_rack_cam[:3, 3]) @ R
    ok = fin.all(axis=1) & (p_cam[:, 2] > 1e-3)
    rows = A.reshape(k, 2, 7)
    if ok.all():  # the usual case: no selection copies (the same arrays as the selection of all)
        uv_hat, J = camera.project_with_jacobian(p_cam)
        rows[:, :, :6] = pose_jacobian(J, p_cam)
        rows[:, :, 6] = np.einsum("nij,nj->ni", J, dX_dz @ R)
        r = uv - uv_hat
    elif ok.any():
        uv_hat, J = camera.project_with_jacobian(p_cam[ok])
        rows[ok, :, :6] = pose_jacobian(J, p_cam[ok])
        rows[ok, :, 6] = np.einsum("nij,nj->ni", J, dX_dz[ok] @ R)
        r[ok] = uv[ok] - uv_hat
    return A, r.reshape(-1)


def pipe_silhouettes(
    T_rack_cam: FloatArray, camera: PinholeCamera, pipes: PipeArrays, lines: LimbLines | None = None
) -> list[FloatArray]:
    """Image quadrilaterals (4, 2) (pinhole pixels, not clipped to the image) of every pipe in front of the camera.

    Each is bounded by the pipe's two limb lines, clipped to the near plane and to a band of three
    image sizes around the image, so that a pipe entering the view with one limb still outside it
    (or both: the camera right over a wide pipe) still masks the ground it covers. `lines`:
    `limb_lines(T_rack_cam[:3, 3], pipes)` when the caller has it already.
    """
    if lines is None:
        lines = limb_lines(T_rack_cam[:3, 3], pipes)
    R = T_rack_cam[:3, :3]
    A = (lines.point - T_rack_cam[:3, 3]) @ R
    D = lines.direction @ R
    s0, s1 = clip_lines_to_view(A, D, lines.s_min, lines.s_max, camera,
                                -float(max(camera.width, camera.height)), 0.1)
    # All pipes at once (the same arithmetic per corner as one pipe at a time), then the usable ones.
    P0 = A + s0[:, None] * D
    P1 = A + s1[:, None] * D
    ends = np.stack([P0[0::2], P1[0::2], P1[1::2], P0[1::2]], axis=1)  # (M, 4, 3)
    use = lines.valid[0::2] & (s0[0::2] < s1[0::2]) & (s0[1::2] < s1[1::2])
    # Pinhole part only: a distortion polynomial is meaningless far outside the image.
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = ends[:, :, :2] / ends[:, :, 2:3]
        uv = np.stack([camera.fx * xn[:, :, 0] + camera.skew * xn[:, :, 1] + camera.cx,
                       camera.fy * xn[:, :, 1] + camera.cy], axis=2)
    use &= np.all(np.isfinite(uv), axis=(1, 2))
    return [uv[m] for m in np.flatnonzero(use)]


def ground_mask(shape: tuple[int, int], pipe_polygons: list[FloatArray], margin_px: float) -> np.ndarray[Any, Any]:
    """uint8 mask (H, W): 255 where the ground may be seen, 0 on the pipes' image regions (grown by
    `margin_px` on each side) and the image border."""
    h, w = shape
    mask = np.zeros((h, w), dtype=np.uint8)
    b = int(margin_px) + 4
    mask[b : h - b, b : w - b] = 255
    grow = max(round(2 * margin_px), 1)
    for poly in pipe_polygons:
        corners = np.rint(poly).astype(np.int32)
        cv2.fillConvexPoly(mask, corners, 0)
        cv2.polylines(mask, [corners], True, 0, grow)
    return mask


def on_ground(uv: FloatArray, mask: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Which pixels uv (K, 2) fall where `mask` (from `ground_mask`) is set."""
    h, w = mask.shape[:2]
    c = np.rint(uv).astype(np.intp)
    inside = (c[:, 0] >= 0) & (c[:, 0] < w) & (c[:, 1] >= 0) & (c[:, 1] < h)
    out = np.zeros(uv.shape[0], dtype=bool)
    out[inside] = mask[c[inside, 1], c[inside, 0]] > 0
    return out


def detect_ground_points(
    gray: np.ndarray[Any, np.dtype[np.uint8]],
    pipe_polygons: list[FloatArray],
    existing_uv: FloatArray,
    max_new: int,
    min_distance_px: float,
    margin_px: float,
    min_corner_ratio: float,
    mask: np.ndarray[Any, Any] | None = None,
) -> FloatArray:
    """Corners (J, 2) outside the pipes' image regions (grown by `margin_px`) and the image border.

    A corner's minimum structure-tensor eigenvalue must reach `min_corner_ratio` times the median
    over the searched region (its noise floor). `mask`: `ground_mask(gray.shape, pipe_polygons,
    margin_px)` when the caller has it already (not modified).
    """
    h, w = gray.shape[:2]
    if max_new <= 0:
        return np.zeros((0, 2))
    mask = ground_mask((h, w), pipe_polygons, margin_px) if mask is None else mask.copy()
    for q in existing_uv:
        cv2.circle(mask, (round(q[0]), round(q[1])), int(min_distance_px), 0, -1)
    if not np.any(mask):
        return np.zeros((0, 2))
    # With a floor: one eigenvalue pass, only the corners above it ordered and thinned (`corners.py`; the
    # same corners as OpenCV's detector followed by the floor).
    strong = strong_corners(gray, mask, int(2 * max_new), float(min_distance_px), 0.01, 7, min_corner_ratio) \
        if min_corner_ratio > 0 else None
    if strong is not None:
        return strong.astype(np.float64)[:max_new]
    corners = shi_tomasi(gray, mask, int(2 * max_new), float(min_distance_px), 0.01, 7)
    if corners.shape[0] == 0:
        return np.zeros((0, 2))
    uv = corners.astype(np.float64)
    if min_corner_ratio > 0:
        ev = np.asarray(cv2.cornerMinEigenVal(gray, 7, ksize=3))
        floor = float(np.median(ev[mask > 0]))
        c = np.rint(uv).astype(np.intp)
        uv = uv[ev[np.clip(c[:, 1], 0, h - 1), np.clip(c[:, 0], 0, w - 1)] >= min_corner_ratio * floor]
    return uv[:max_new]
