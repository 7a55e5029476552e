"""MAP refinement of (dx, dy, dyaw) with the tilt and height errors of both frames modelled exactly.

Residuals of the exactly re-projected points (`tilt_reprojection`), their Jacobian and instrument
columns, in the reference frame's level frame, metres and radians.
"""

from __future__ import annotations

import math

import numpy as np

from companion.checks import FloatArray
from companion.vision.ground.refine_rigid import RefineResult
from companion.vision.ground.refine_tilt_fields import NuisanceResult
from companion.vision.ground.tilt_reprojection import _corrected_points, _corrected_stack, tilt_corrected_points


def residuals_and_jacobian_exact(
    params: FloatArray,
    rays_a: FloatArray,
    height_a_m: float,
    nadir_a_m: FloatArray,
    rays_b: FloatArray,
    height_b_m: float,
    nadir_b_m: FloatArray,
    map_b: FloatArray,
    map_a: FloatArray,
    instrument: bool = False,
) -> tuple[FloatArray, FloatArray]:
    """Residuals r_i = d + R(dyaw) P_b,i(map_b z) - P_a,i(map_a z) (N, 2) and their Jacobian
    (N, 2, 3 + m), parameters (dx, dy, dyaw, z), with P the exactly tilt/height-corrected points of
    each frame (`tilt_corrected_points`), all in the reference frame's level frame.

    `instrument=True` replaces the z columns by instruments: the first-order warp fields
    (`tilt_fields`) of both frames evaluated at the same noise-averaged points, the midpoints
    m = (P_a + d + R P_b) / 2 (and their image in frame b). The exact columns contain the point
    noise of both frames, and the shared-bias column is their small difference ~ field gradient x
    motion: its noise correlates with the residuals' (errors in variables) and, summed over a
    hundred points, pushes the weakly observed bias by ~0.05 deg per frame even when hovering. At
    the midpoints the instrument noise is (n_a + n_b) / 2, uncorrelated with the residual's
    n_a - n_b. The instruments equal the exact columns up to O(e) and the point noise."""
    z = params[3:]
    if instrument:
        Pa = _corrected_points(rays_a, height_a_m, nadir_a_m, map_a @ z)
        Pb = _corrected_points(rays_b, height_b_m, nadir_b_m, map_b @ z)
    else:
        Pa, Ja = tilt_corrected_points(rays_a, height_a_m, nadir_a_m, map_a @ z)
        Pb, Jb = tilt_corrected_points(rays_b, height_b_m, nadir_b_m, map_b @ z)
    c, s = np.cos(params[2]), np.sin(params[2])
    rb_x = c * Pb[:, 0] - s * Pb[:, 1]
    rb_y = s * Pb[:, 0] + c * Pb[:, 1]
    n = rays_a.shape[0]
    r = np.empty((n, 2))
    r[:, 0] = params[0] + rb_x - Pa[:, 0]
    r[:, 1] = params[1] + rb_y - Pa[:, 1]
    if instrument:
        Jf = _instrument_system(params, rays_a, height_a_m, nadir_a_m, rays_b, height_b_m, nadir_b_m, map_b, map_a,
                                Pa, Pb)
        return r, Jf.reshape(n, 2, 3 + z.size)
    return r, _pair_jacobian(rb_x, rb_y, c, s, Ja, Jb, map_a, map_b)


def _pair_jacobian(
    rb_x: FloatArray, rb_y: FloatArray, c: float, s: float, Fa: FloatArray, Fb: FloatArray, map_a: FloatArray,
    map_b: FloatArray,
) -> FloatArray:
    """Jacobian (N, 2, 3 + m) of r = d + R(dyaw) P_b - P_a in (dx, dy, dyaw, z): identity in d,
    the rotated P_b (`rb_x`, `rb_y`) in dyaw, and in z the per-point fields of P_a and P_b with
    respect to their tilt/height errors (`Fa`, `Fb`, (N, 2, 3)) through `map_a`, `map_b` (3, m);
    `c`, `s` are cos and sin of dyaw."""
    n = rb_x.shape[0]
    m = map_a.shape[1]
    Fb_rot = np.empty_like(Fb)
    Fb_rot[:, 0] = c * Fb[:, 0] - s * Fb[:, 1]
    Fb_rot[:, 1] = s * Fb[:, 0] + c * Fb[:, 1]
    J = np.zeros((n, 2, 3 + m))
    J[:, 0, 0] = 1.0
    J[:, 1, 1] = 1.0
    J[:, 0, 2] = -rb_y
    J[:, 1, 2] = rb_x
    J.reshape(2 * n, 3 + m)[:, 3:] = Fb_rot.reshape(2 * n, 3) @ map_b - Fa.reshape(2 * n, 3) @ map_a
    return J


def _instrument_system(
    params: FloatArray,
    rays_a: FloatArray,
    height_a_m: float,
    nadir_a_m: FloatArray,
    rays_b: FloatArray,
    height_b_m: float,
    nadir_b_m: FloatArray,
    map_b: FloatArray,
    map_a: FloatArray,
    Pa: FloatArray | None = None,
    Pb: FloatArray | None = None,
) -> FloatArray:
    """`residuals_and_jacobian_exact(instrument=True)` Jacobian as a (2N, 3 + m) matrix (hot path);
    `Pa`, `Pb`: the corrected points at `params` when already known."""
    z = params[3:]
    ea, eb = map_a @ z, map_b @ z
    n = rays_a.shape[0]
    if Pa is None or Pb is None:
        Pa = _corrected_points(rays_a, height_a_m, nadir_a_m, ea)
        Pb = _corrected_points(rays_b, height_b_m, nadir_b_m, eb)
    c, s = math.cos(params[2]), math.sin(params[2])
    rot_rows = np.array([[c, s], [-s, c]])  # v @ rot_rows = R v
    RPb = Pb @ rot_rows
    d = params[:2]
    mid_a = 0.5 * (Pa + RPb) + 0.5 * d
    mid_b = (mid_a - d) @ rot_rows.T  # R^T (m - d)

    # First-order warp fields (`tilt_fields`, per point (2, 3)) of both frames at once: (2, N, 2, 3).
    mids = np.stack([mid_a, mid_b])
    nads = np.array([[nadir_a_m[0], nadir_a_m[1]], [nadir_b_m[0], nadir_b_m[1]]])
    scale = [1.0 + float(ea[2]), 1.0 + float(eb[2])]
    inv_h = np.array([[1.0 / (height_a_m * scale[0])], [1.0 / (height_b_m * scale[1])]])
    scale_col = np.array([[scale[0]], [scale[1]]])
    x = mids[:, :, 0] - nads[:, 0:1]
    y = mids[:, :, 1] - nads[:, 1:2]
    F = np.empty((2, n, 2, 3))
    F[:, :, 0, 0] = F[:, :, 1, 1] = x * y * inv_h
    F[:, :, 1, 0] = y * y * inv_h
    F[:, :, 0, 1] = x * x * inv_h
    F[:, :, 0, 2] = x / scale_col
    F[:, :, 1, 2] = y / scale_col
    J = _pair_jacobian(RPb[:, 0], RPb[:, 1], c, s, F[0], F[1], map_a, map_b)
    return J.reshape(2 * n, 3 + z.size)


_MAP_CACHE: list[tuple[FloatArray, FloatArray, FloatArray]] = []


def _stacked_maps(map_a: FloatArray, map_b: FloatArray) -> FloatArray:
    """np.stack([map_a, map_b]) (2, 3, m); cached for the last pair when both are read-only arrays
    (the constant maps of `tilt_bias`), so a caller mutating its maps never sees a stale stack."""
    if _MAP_CACHE and _MAP_CACHE[0][0] is map_a and _MAP_CACHE[0][1] is map_b:
        return _MAP_CACHE[0][2]
    out = np.stack([map_a, map_b])
    if not np.asarray(map_a).flags.writeable and not np.asarray(map_b).flags.writeable:
        out.flags.writeable = False
        _MAP_CACHE[:] = [(map_a, map_b, out)]
    return out


def refine_tilt_exact(
    rays_a: FloatArray,
    height_a_m: float,
    nadir_a_m: FloatArray,
    rays_b: FloatArray,
    height_b_m: float,
    nadir_b_m: FloatArray,
    initial: FloatArray,
    data_std_m: float,
    prior_mean: FloatArray,
    prior_cov: FloatArray,
    map_b: FloatArray,
    map_a: FloatArray,
    max_iterations: int = 8,
    data_std_floor_m: float | None = None,
) -> NuisanceResult:
    """MAP refinement of (dx, dy, dyaw) in the reference frame's level frame, with the tilt and
    height errors of both frames as nuisance parameters z, modelled exactly.

    As `refine_with_nuisance`, but the residuals re-project the points from the rays with the
    corrected attitude and height (`residuals_and_jacobian_exact`) instead of moving them along
    first-order fields: with 0.5 deg of white attitude noise the second-order terms of the warps
    are as large as the weak evidence about a slow bias shared by both frames, and biased. The
    steps use the instrument columns (`residuals_and_jacobian_exact(instrument=True)`), evaluated
    once at the start (the model is nearly linear: a chord iteration converges in a few steps), so
    the point noise does not push the bias.

    `data_std_floor_m`: when given, after the first step the point noise is re-estimated from the
    residual scatter (at least this floor) instead of `data_std_m`: the weak bias evidence is then
    weighed by each pair's own quality. Returns the increment (d in the level frame of frame a),
    its covariance and the posterior of z.
    """
    z0 = np.asarray(prior_mean, dtype=np.float64)
    m = z0.size
    k = 3 + m
    params = np.concatenate([np.asarray(initial, dtype=np.float64), z0])
    n = rays_a.shape[0]

    rays_ab = np.stack([rays_a, rays_b])
    heights = np.array([height_a_m, height_b_m])
    nadirs = np.stack([nadir_a_m, nadir_b_m])
    map_ab = _stacked_maps(map_a, map_b)  # (2, 3, m)
    points = np.zeros((2, n, 2))

    def residual(p: FloatArray) -> FloatArray:
        nonlocal points
        points = _corrected_stack(rays_ab, heights, nadirs, map_ab @ p[3:])
        c, s = math.cos(p[2]), math.sin(p[2])
        r: FloatArray = points[1] @ np.array([[c, s], [-s, c]]) + (p[:2] - points[0])
        return r

    def instruments(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        Jf = _instrument_system(
            p, rays_a, height_a_m, nadir_a_m, rays_b, height_b_m, nadir_b_m, map_b, map_a, points[0], points[1]
        )
        return Jf, Jf.T @ Jf

    r = residual(params)
    Jf, JtJ = instruments(params)
    info = np.zeros((k, k))
    info[3:, 3:] = np.linalg.inv(np.asarray(prior_cov, dtype=np.float64))
    w = 1.0 / (data_std_m * data_std_m)

    prior_info = info[3:, 3:]

    def inverse(weight: float) -> FloatArray:
        Hinv = np.linalg.inv(weight * JtJ + info)
        out: FloatArray = 0.5 * (Hinv + Hinv.T)
        return out

    Hinv = inverse(w)
    it = 0
    for it in range(1, max_iterations + 1):
        g = w * (Jf.T @ r.reshape(2 * n))
        g[3:] += prior_info @ (params[3:] - z0)
        step = -(Hinv @ g)
        params = params + step
        r = residual(params)
        if it == 1:
            # Re-evaluate the instruments next to the optimum: the fixed point then no longer
            # depends on the starting point (GEN and SMA agree), and re-weigh if asked.
            Jf, JtJ = instruments(params)
            if data_std_floor_m is not None:
                scatter = math.sqrt(float(np.einsum("ij,ij->", r, r)) / max(2 * n - 3 - m, 1))
                w = 1.0 / max(scatter, data_std_floor_m) ** 2
            Hinv = inverse(w)
            continue
        # Converged well below any physical resolution (1 um, 1e-7 rad; 1e-5 rad on the nuisances,
        # a hundredth of what one frame's evidence moves the bias by).
        if abs(step[2]) < 1e-7 and abs(step[0]) + abs(step[1]) < 1e-6 and float(np.abs(step[3:]).max()) < 1e-5:
            break
    data = float(np.einsum("ij,ij->", r, r))
    chi2_red = w * data / max(2 * n - 3, 1)
    result = RefineResult(params[:3].copy(), Hinv[:3, :3] * max(1.0, chi2_red), float(np.sqrt(data / max(n, 1))), it)
    return NuisanceResult(result, params[3:].copy(), Hinv[3:, 3:].copy())
