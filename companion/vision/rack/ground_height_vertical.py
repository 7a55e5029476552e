"""The ground's height from the camera's vertical motion, with the travel along the pipes left free (rack frame, m).

Flying along the pipes with no texture or crossing pipe in view, the tracker's along-pipe travel comes from the
ground's flow at the height being estimated, so the along component of a ground point's residual is satisfied by
whatever height the poses were solved with: a fit that trusts the poses' along-pipe positions returns that height
(docs/rack.md, "Thirty-third session on #14": at the tracker's poses -3.3 m for a true -2.0, at the true poses
-2.00). The across fit (`ground_height.py`) waits for a baseline across the pipes, which such a flight never makes.

What the limbs do measure is the camera's height above the pipes. A vertical move dz makes the ground's image grow
by dz over the ground's depth, a pattern (radial) that no rotation and no along-pipe shift makes. So this fit takes
each anchor pose's along-pipe position as unknown (one offset per anchor camera centre: the points anchored at one
frame share it), turns the current camera by a small free rotation as the across fit does, and reads the height
from what is left. Its precision is set by the vertical baseline against the poses' relative height error, stated
as a floor on the variance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.geometry import so3
from companion.vision.rack.ground import plane_points
from companion.vision.rack.ground_height import ANCHOR_FRAMES, GroundHeightFit
from companion.vision.rack.ground_height_jit import (
    MAX_ROTATION_STEP_RAD,
    MIN_POINTS,
    MIN_SCALE_PX,
    ROTATION_RIDGE,
    TUKEY_C,
)
from companion.vision.rack.motion import median_1d

ITERATIONS = 6
# The two poses' relative height error (m): the limbs give the camera's height above the pipes to about a
# millimetre from frame to frame; the height's relative error is this over the vertical baseline.
VERTICAL_ERROR_M = 0.002
# No vertical fit before this frame: once the first anchors span a full window. The across fit waits longer
# (`ground_height.SETTLE_FRAMES`) because the start's attitude transient, left in its anchors' relative roll,
# fitted the wrong height confidently; this fit estimates the current camera's rotation and frees every anchor
# centre's along-pipe position, and the along-pipe stretch it rescales (`along_rescale.filter_correction_m`)
# grows by a frame's travel every frame it waits.
SETTLE_FRAMES_VERTICAL = ANCHOR_FRAMES
OFFSET_RIDGE = 1e-6  # px² per m²: keeps an offset seen by one point's along residual only solvable


@dataclass(frozen=True)
class VerticalRows:
    """Residuals r (2K,) (px, observed minus predicted), and their derivatives (2K, 4 + G): the height (m), the
    current camera's rotation (3, rad, camera frame) and the G anchor offsets along rack +y (m); ok (K,)."""

    r: FloatArray
    A: FloatArray
    ok: np.ndarray


def vertical_rows(
    T_rack_cam: FloatArray, camera: PinholeCamera, anchor_o: FloatArray, anchor_d: FloatArray, uv: FloatArray,
    z_m: float, group: np.ndarray, n_groups: int,
) -> VerticalRows:
    """Rows of one Gauss-Newton step at height `z_m`, offsets zero and no rotation (each step re-linearises at the
    updated anchors and pose). Point k lies where its anchor ray (`anchor_o[k]`, `anchor_d[k]`, rack frame) meets
    {z = `z_m`}; `group[k]` is its anchor's index among `n_groups`. Invalid points (rays that do not reach the
    plane, points behind the camera) get zero rows."""
    R = T_rack_cam[:3, :3]
    X, dX_dz = plane_points(anchor_o, anchor_d, z_m)
    d = X - T_rack_cam[:3, 3]
    p = d @ R
    ok = np.isfinite(p[:, 2]) & (np.nan_to_num(p[:, 2], nan=0.0) > 1e-3)
    p = np.where(ok[:, None], p, 1.0)
    uv_p, J = camera.project_with_jacobian(p)
    k = uv.shape[0]
    r = np.where(ok[:, None], uv - uv_p, 0.0)
    A = np.zeros((k, 2, 4 + n_groups))
    # r = uv - π(p): dr/dθ = -J dp/dθ, with dp/dz = Rᵀ dX/dz, dp/dω = [p]ₓ (p ≈ exp(-ω) p = p + p × ω) and
    # dp/dt = Rᵀ e_y (an anchor's centre moved along rack +y moves its point on the plane by as much).
    dp_dz = np.where(ok[:, None], dX_dz, 0.0) @ R
    A[:, :, 0] = -np.einsum("kij,kj->ki", J, dp_dz)
    skew = np.zeros((k, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = -p[:, 2], p[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = p[:, 2], -p[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = -p[:, 1], p[:, 0]
    A[:, :, 1:4] = -np.einsum("kij,kjl->kil", J, skew)
    A[np.arange(k), :, 4 + group] = -J @ R[1, :]
    A[~ok] = 0.0
    return VerticalRows(r=r.reshape(-1), A=A.reshape(2 * k, 4 + n_groups), ok=ok)


def fit_ground_height_vertical(
    T_rack_cam: FloatArray,
    camera: PinholeCamera,
    anchor_o: FloatArray,
    anchor_d: FloatArray,
    uv: FloatArray,
    z0_m: float,
    min_baseline_m: float,
) -> GroundHeightFit | None:
    """Height z of the plane {z = const} (rack frame) from ground points seen now at `uv` (K, 2) from pose
    `T_rack_cam` and before along rays `anchor_d` (K, 3) from camera centres `anchor_o` (K, 3), using only points
    whose anchor centre lies at least `min_baseline_m` above or below the camera's. Gauss-Newton from `z0_m` with
    Tukey's biweight on the height, the current camera's small rotation and one along-pipe offset per anchor
    centre (all but the height are nuisances); the height's variance is the marginal one, at least what
    `VERTICAL_ERROR_M` makes over the median vertical baseline. None with fewer than 8 such points or no fit.
    """
    o = T_rack_cam[:3, 3]
    use = np.abs(o[2] - anchor_o[:, 2]) >= min_baseline_m
    if np.count_nonzero(use) < MIN_POINTS:
        return None
    ao, ad, q = anchor_o[use].copy(), anchor_d[use], uv[use]
    _, group = np.unique(ao, axis=0, return_inverse=True)
    group = group.reshape(-1)
    n_g = int(group.max()) + 1
    top = float(np.min(ao[:, 2])) - 0.05  # the plane stays below every anchor camera
    T = np.array(T_rack_cam, dtype=float)
    z = float(z0_m)
    ridge = np.concatenate([[0.0], np.full(3, ROTATION_RIDGE), np.full(n_g, OFFSET_RIDGE)])
    var_z = np.inf
    n_used = 0
    for _ in range(ITERATIONS):
        rows = vertical_rows(T, camera, ao, ad, q, z, group, n_g)
        ok2 = np.repeat(rows.ok, 2)
        if np.count_nonzero(rows.ok) < MIN_POINTS:
            return None
        e = rows.r[ok2]
        A = rows.A[ok2]
        scale = max(1.4826 * median_1d(np.abs(e)), MIN_SCALE_PX)
        u = e / (TUKEY_C * scale)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        H = (A * w[:, None]).T @ A + np.diag(ridge)
        if not H[0, 0] > 0.0:
            return None
        try:
            H_inv = np.linalg.inv(H)
        except np.linalg.LinAlgError:
            return None
        step = -(H_inv @ ((A * w[:, None]).T @ e))  # minimises |r + A δ|² (A = dr/dθ)
        z = min(z + float(np.clip(step[0], -1.0, 1.0)), top)
        w_step = np.clip(step[1:4], -MAX_ROTATION_STEP_RAD, MAX_ROTATION_STEP_RAD)
        T[:3, :3] = T[:3, :3] @ so3.exp(w_step)
        ao[:, 1] += step[4 + group]
        n_used = int(np.count_nonzero(w.reshape(-1, 2).min(axis=1) > 0.0))
        dof = max(float(np.sum(w)) - (4 + n_g), 1.0)
        sigma2 = max(float(np.sum(w * e * e)) / dof, MIN_SCALE_PX * MIN_SCALE_PX)
        var_z = sigma2 * float(H_inv[0, 0])
    if n_used < MIN_POINTS or not np.isfinite(z) or not np.isfinite(var_z):
        return None
    depth = float(np.median(ao[:, 2])) - z
    baseline = float(np.median(np.abs(o[2] - anchor_o[use, 2])))
    var_z = max(var_z, (depth * VERTICAL_ERROR_M / baseline) ** 2)
    return GroundHeightFit(z_m=z, var_m2=var_z, n_points=n_used)

