"""The ground's height from its points seen across a long sideways baseline (rack frame, metres).

Frame to frame, a ground point's flow is the camera's translation over the ground's depth plus the
camera's rotation, and one frame's translation (a couple of centimetres) makes as much flow at the ground's
depth as a few hundredths of a degree of rotation error: the per-frame solve's z_g wanders by a metre and
more while the same points at the true poses fit the true height to the centimetre (docs/rack.md,
"Fifteenth session on #14"). Over tens of frames the translation grows while the attitude error *between*
the two poses does not (it is mostly slow), so a ground point's ray from the pose it was anchored at,
against where it is seen now, fixes the height. Only the component of the residual that the camera's
motion *across* the pipes makes is used: across the pipes the limbs measure the translation in metres,
while along them the tracker's own translation came from the ground's flow scaled by the very height being
estimated.

The two poses' *relative* attitude error is the other thing the residual carries: a roll between them moves
every ground point sideways, as the height's error does, and few parallel pipes hardly tell a roll from a
sideways slide. A roll's flow is not a translation's, though (over a camera's field of view it grows towards
the image's sides as 1 + u²/f², while a translation's over a level ground is the same everywhere), so the fit
estimates the current camera's small rotation beside the height and reads the height only from what no
rotation explains (docs/rack.md, "Twenty-fifth session on #14").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.ground import plane_points
from companion.vision.rack.ground_height_jit import (
    ITERATIONS,
    MAX_POINTS,
    MAX_ROTATION_STEP_RAD,
    MIN_POINTS,
    MIN_SCALE_PX,
    ROTATION_RIDGE,
    TUKEY_C,
    kernels,
    solve4,
    turn,
)
from companion.vision.rack.motion import median_1d

BoolArray = np.ndarray[Any, np.dtype[np.bool_]]

ANCHOR_FRAMES = 25  # a point is re-anchored after this many frames (the poses' relative error grows with time)
SETTLE_FRAMES = 50  # no fit before: anchors spanning the start's transient fitted the wrong height confidently
MEMORY = 10.0  # consecutive fits share anchors and poses: each counts this many times less than it says
CONVERGED_STD_M = 0.1  # below this the filter's height tests each point for lying on the ground

# The two poses' relative error across the pipes (m): the limbs' sideways position and the roll between the
# poses at the ground's depth. Shared by every point, it bounds the fit's precision whatever their number:
# the height's relative error is this over the baseline.
_BASELINE_ERROR_M = 0.005


@dataclass(frozen=True)
class GroundHeightFit:
    """One frame's fit: height z_m (rack z, m), its variance var_m2 (m²) and the points that carried it."""

    z_m: float
    var_m2: float
    n_points: int


def across_residuals(
    T_rack_cam: FloatArray, camera: PinholeCamera, anchor_o: FloatArray, anchor_d: FloatArray, uv: FloatArray,
    z_m: float, direction: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, BoolArray, FloatArray]:
    """Residuals e (K,) (px), their derivative de/dz (K,) (px per m), validity (K,) and image directions (K, 2).

    Point k lies where its anchor ray (camera centre `anchor_o[k]`, direction `anchor_d[k]`, rack frame) meets the
    plane {z = `z_m`}; projected at pose `T_rack_cam` it should land on `uv[k]` (px). e is the miss along the
    unit image direction in which a move of the camera along rack +x shifts that point (or along `direction`
    when given); de/dz holds that direction fixed, as Gauss-Newton does (it turns slowly with z). Invalid
    (e = de = 0): rays that do not descend to the plane or points behind the camera.
    """
    e, de, ok, direction, _ = _across(T_rack_cam, camera, anchor_o, anchor_d, uv, z_m, direction)
    return e, de, ok, direction


def rotation_derivative(
    T_rack_cam: FloatArray, camera: PinholeCamera, anchor_o: FloatArray, anchor_d: FloatArray, z_m: float,
    direction: FloatArray,
) -> FloatArray:
    """de/dω (K, 3) (px per rad) of `across_residuals`' e, with its `direction` held, for the camera at pose
    `T_rack_cam` turned by a small rotation ω (camera frame: R_rack_cam exp(ω)); zero rows for invalid points."""
    return _across(T_rack_cam, camera, anchor_o, anchor_d, np.zeros((anchor_o.shape[0], 2)), z_m, direction)[4]


def _across(
    T_rack_cam: FloatArray, camera: PinholeCamera, anchor_o: FloatArray, anchor_d: FloatArray, uv: FloatArray,
    z_m: float, direction: FloatArray | None,
) -> tuple[FloatArray, FloatArray, BoolArray, FloatArray, FloatArray]:
    """`across_residuals`' four results and `rotation_derivative`'s (K, 3), from one projection.

    Products with the pose's rotation are written out element by element (no matrix products), in the order
    `ground_height_jit._fit` repeats for a pinhole camera, so that the compiled fit gives these bits.
    """
    R = T_rack_cam[:3, :3]
    X, dX_dz, ok = _anchored_points(T_rack_cam, anchor_o, anchor_d, z_m)
    d = X - T_rack_cam[:3, 3]
    p_cam = np.where(ok[:, None], _times(d, R), 1.0)
    uv_p, J = camera.project_with_jacobian(p_cam)
    if direction is None:
        # a camera step along rack +x moves a point by -J Rᵀ e_x
        du = -(J[:, 0, 0] * R[0, 0] + J[:, 0, 1] * R[0, 1] + J[:, 0, 2] * R[0, 2])
        dv = -(J[:, 1, 0] * R[0, 0] + J[:, 1, 1] * R[0, 1] + J[:, 1, 2] * R[0, 2])
        nrm = np.sqrt(du * du + dv * dv)
        nrm = np.where(nrm >= 1e-12, nrm, 1e-12)
        direction = np.stack([du / nrm, dv / nrm], axis=1)
    du, dv = direction[:, 0], direction[:, 1]
    e = du * (uv[:, 0] - uv_p[:, 0]) + dv * (uv[:, 1] - uv_p[:, 1])
    g = _times(np.where(ok[:, None], dX_dz, 0.0), R)
    de = -(du * (J[:, 0, 0] * g[:, 0] + J[:, 0, 1] * g[:, 1] + J[:, 0, 2] * g[:, 2])
           + dv * (J[:, 1, 0] * g[:, 0] + J[:, 1, 1] * g[:, 1] + J[:, 1, 2] * g[:, 2]))
    # Turning the camera by ω moves a point's camera coordinates p to exp(-ω) p ≈ p + p × ω, so with
    # h = Jᵀ direction, de = -h · (p × ω) = (p × h) · ω.
    h = du[:, None] * J[:, 0, :] + dv[:, None] * J[:, 1, :]
    px, py, pz = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    de_dw = np.stack([py * h[:, 2] - pz * h[:, 1], pz * h[:, 0] - px * h[:, 2], px * h[:, 1] - py * h[:, 0]], axis=1)
    return np.where(ok, e, 0.0), np.where(ok, de, 0.0), ok, direction, np.where(ok[:, None], de_dw, 0.0)


def _times(a: FloatArray, R: FloatArray) -> FloatArray:
    """a @ R for rows a (K, 3), each element a sum of three products left to right (no BLAS kernel's order)."""
    return np.stack([a[:, 0] * R[0, c] + a[:, 1] * R[1, c] + a[:, 2] * R[2, c] for c in range(3)], axis=1)


def _anchored_points(
    T_rack_cam: FloatArray, anchor_o: FloatArray, anchor_d: FloatArray, z_m: float
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """The anchor rays' points on the plane {z = `z_m`} (K, 3), their dX/dz (K, 3) and which are usable (K,):
    rays that reach the plane, in front of the camera at pose `T_rack_cam` (NaN rows elsewhere)."""
    X, dX_dz = plane_points(anchor_o, anchor_d, z_m)
    d = X - T_rack_cam[:3, 3]
    R = T_rack_cam[:3, :3]
    p_z = d[:, 0] * R[0, 2] + d[:, 1] * R[1, 2] + d[:, 2] * R[2, 2]
    ok = np.isfinite(X[:, 0]) & (np.nan_to_num(p_z, nan=0.0) > 1e-3)
    return X, dX_dz, np.asarray(ok)


def fit_ground_height(
    T_rack_cam: FloatArray,
    camera: PinholeCamera,
    anchor_o: FloatArray,
    anchor_d: FloatArray,
    uv: FloatArray,
    z0_m: float,
    min_baseline_m: float,
    estimate_rotation: bool = True,
) -> GroundHeightFit | None:
    """Height z of the plane {z = const} (rack frame) that best explains ground points seen now at `uv` (K, 2)
    from pose `T_rack_cam` and before along rays `anchor_d` (K, 3) from camera centres `anchor_o` (K, 3).

    Only points whose anchor lies at least `min_baseline_m` across the pipes (rack x) from the camera count,
    by the residual component of `across_residuals`. Gauss-Newton from `z0_m` with Tukey's biweight, on the
    height and, with `estimate_rotation`, a small rotation of the current camera (the two poses' relative
    attitude error, not reported; the height's variance is then the marginal one). Without it the poses'
    attitudes are taken as they are: the caller's choice when an attitude prior holds the tilt, where the
    rotation would only cost the height precision. The variance is at least what a 5 mm relative error of the
    two poses makes over the median baseline. None with fewer than 8 such points or no fit.
    """
    o = T_rack_cam[:3, 3]
    use = np.abs(o[0] - anchor_o[:, 0]) >= min_baseline_m
    if np.count_nonzero(use) < MIN_POINTS:
        return None
    ao, ad, q = anchor_o[use], anchor_d[use], uv[use]
    top = float(np.min(ao[:, 2])) - 0.05  # the plane stays below every anchor camera
    ks = kernels() if camera.dist is None and ao.shape[0] <= MAX_POINTS else None
    if ks is not None:
        # The same iterations per point, compiled (`ground_height_jit.py`).
        status, z, var, n_used = ks.fit(np.ascontiguousarray(T_rack_cam[:3, :3], dtype=np.float64),
                                        np.ascontiguousarray(o, dtype=np.float64), np.ascontiguousarray(ao),
                                        np.ascontiguousarray(ad), np.ascontiguousarray(q, dtype=np.float64),
                                        float(z0_m), top, camera.fx, camera.fy, camera.skew, camera.cx, camera.cy,
                                        bool(estimate_rotation))
        if not status:
            return None
    else:
        fitted = _iterate(T_rack_cam, camera, ao, ad, q, float(z0_m), top, estimate_rotation)
        if fitted is None:
            return None
        z, var, n_used = fitted
    if n_used < MIN_POINTS or not np.isfinite(z):
        return None
    depth = float(np.median(ao[:, 2])) - z
    baseline = float(np.median(np.abs(o[0] - ao[:, 0])))
    var = max(var, (depth * _BASELINE_ERROR_M / baseline) ** 2)
    return GroundHeightFit(z_m=z, var_m2=var, n_points=n_used)


def _iterate(
    T_rack_cam: FloatArray, camera: PinholeCamera, ao: FloatArray, ad: FloatArray, q: FloatArray, z0_m: float,
    top: float, estimate_rotation: bool,
) -> tuple[float, float, int] | None:
    """`fit_ground_height`'s Gauss-Newton iterations in numpy: (z, variance, points used), or None. Sums are
    numpy's (pairwise) over element-wise products, the 4x4 step and the rotation update scalar by scalar
    (`ground_height_jit.solve4`, `turn`): the order the compiled fit repeats."""
    z = z0_m
    var = np.inf
    n_used = 0
    R = np.array(T_rack_cam[:3, :3], dtype=float)
    T = np.array(T_rack_cam, dtype=float)
    n_par = 4.0 if estimate_rotation else 1.0
    H = np.empty((4, 4))
    step = np.empty(4)
    for _ in range(ITERATIONS):
        T[:3, :3] = R
        e, de, ok, _, de_dw = _across(T, camera, ao, ad, q, z, None)
        if np.count_nonzero(ok) < MIN_POINTS:
            return None
        e, de_ok = e[ok], de[ok]
        scale = 1.4826 * median_1d(np.abs(e))
        if not scale >= MIN_SCALE_PX:
            scale = MIN_SCALE_PX
        u = e / (TUKEY_C * scale)
        a1 = 1.0 - u * u
        w = np.where(np.abs(u) < 1.0, a1 * a1, 0.0)
        info = float(np.sum(w * de_ok * de_ok))
        if not info > 0.0:
            return None
        if estimate_rotation:
            cols = [de_ok, de_dw[ok, 0], de_dw[ok, 1], de_dw[ok, 2]]
            for r in range(4):
                for c in range(4):
                    H[r, c] = np.sum((cols[r] * w) * cols[c])
            b = np.array([np.sum((cols[r] * w) * e) for r in range(4)])
            for r in range(1, 4):
                H[r, r] = H[r, r] + ROTATION_RIDGE
            var_per_px2 = solve4(H, b, step)
            if np.isnan(var_per_px2):
                return None
            z_step = float(step[0])
            lim = MAX_ROTATION_STEP_RAD
            turn(R, *(min(max(float(step[i]), -lim), lim) for i in (1, 2, 3)))
        else:
            z_step, var_per_px2 = -float(np.sum(w * de_ok * e)) / info, 1.0 / info
        z = min(z + min(max(z_step, -1.0), 1.0), top)
        n_used = int(np.count_nonzero(w > 0.0))
        dof = max(float(np.sum(w)) - n_par, 1.0)
        var = max(float(np.sum(w * e * e)) / dof, MIN_SCALE_PX * MIN_SCALE_PX) * var_per_px2
    return z, var, n_used


def update_ground_height(
    z_m: float, var_m2: float, fit: GroundHeightFit, rejected: int, reset_after: int = 25
) -> tuple[float, float, int]:
    """One filter step: (height, variance, consecutive rejections) after a frame's `fit`.

    A fit counts `MEMORY` times less than its own variance says (consecutive frames share their anchors and
    their poses' errors). A fit more than three standard deviations from the estimate is rejected (an
    overhead beam's corners, the deck); after `reset_after` rejections in a row the ground has changed and
    the filter restarts from the fit.
    """
    v = MEMORY * fit.var_m2
    innov = fit.z_m - z_m
    if innov * innov > 9.0 * (var_m2 + v):
        if rejected + 1 >= reset_after:
            return fit.z_m, v, 0
        return z_m, var_m2, rejected + 1
    k = var_m2 / (var_m2 + v)
    return z_m + k * innov, (1.0 - k) * var_m2, 0


def off_ground(
    T_rack_cam: FloatArray,
    camera: PinholeCamera,
    anchor_o: FloatArray,
    anchor_d: FloatArray,
    uv: FloatArray,
    z_m: float,
    gate_px: float,
    parallax_fraction: float = 0.3,
) -> BoolArray:
    """Points (K,) seen at `uv` (K, 2) that do not lie on the ground {z = `z_m`} (rack frame): their anchor ray
    (`anchor_o`, `anchor_d`, (K, 3) each) at that height projects, at pose `T_rack_cam`, more than `gate_px`
    plus `parallax_fraction` of the parallax the camera's move since the anchor gives a ground point away.

    A corner on an unmodelled structure nearer the camera (an overhead beam 1.4 m below it, the ground 4.7 m)
    moves several times as far as the ground's; frame to frame the difference is a few pixels, near the noise,
    but from its anchor it grows with the baseline while a ground point's error stays a small fraction of it.
    """
    o = T_rack_cam[:3, 3]
    X, _, front = _anchored_points(T_rack_cam, anchor_o, anchor_d, z_m)
    uv_p = camera.project(np.where(front[:, None], (X - o) @ T_rack_cam[:3, :3], 1.0))
    err = np.linalg.norm(uv - uv_p, axis=1)
    depth = max(float(o[2]) - z_m, 1e-3)
    parallax = camera.fx * np.linalg.norm(o - anchor_o, axis=1) / depth
    return np.asarray(front & (err > gate_px + parallax_fraction * parallax))
