"""Levenberg-Marquardt refinement of (dx, dy, dyaw) (paper eq. 26), hand-written, 3 parameters.

Residuals r_i = d + R(dyaw) b_i - a_i (N, 2), metres, NED-aligned (see `closed_form`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray
from companion.geometry import so3


@dataclass(frozen=True)
class RefineResult:
    """Refined increment (dx, dy, dyaw), its covariance and the fit statistics.

    increment:   (3,) dx, dy (m, NED) and dyaw (rad).
    covariance:  (3, 3) sigma^2 (J^T J)^-1 with sigma^2 = sum r^2 / (2N - 3): the covariance of
                 the increment implied by the residual scatter (order dx, dy, dyaw).
    rms_m:       root mean square residual length, metres.
    iterations:  LM iterations used.
    """

    increment: FloatArray
    covariance: FloatArray
    rms_m: float
    iterations: int


def residuals_and_jacobian(params: FloatArray, a_m: FloatArray, b_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Residuals (N, 2) and their Jacobian d r_i / d (dx, dy, dyaw) (N, 2, 3)."""
    c, s = np.cos(params[2]), np.sin(params[2])
    bx, by = b_m[:, 0], b_m[:, 1]
    rb_x = c * bx - s * by
    rb_y = s * bx + c * by
    r = np.stack([params[0] + rb_x - a_m[:, 0], params[1] + rb_y - a_m[:, 1]], axis=-1)
    J = np.zeros((a_m.shape[0], 2, 3))
    J[:, 0, 0] = 1.0
    J[:, 1, 1] = 1.0
    J[:, 0, 2] = -rb_y
    J[:, 1, 2] = rb_x
    return r, J


def _normal_equations(params: FloatArray, a_m: FloatArray, b_m: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """J^T J (3, 3), J^T r (3,) and the cost sum r^2, built from sums (no (2N, 3) matrix)."""
    c, s = np.cos(params[2]), np.sin(params[2])
    bx, by = b_m[:, 0], b_m[:, 1]
    rb_x = c * bx - s * by
    rb_y = s * bx + c * by
    rx = params[0] + rb_x - a_m[:, 0]
    ry = params[1] + rb_y - a_m[:, 1]
    n = float(a_m.shape[0])
    sx, sy = float(rb_x.sum()), float(rb_y.sum())
    JtJ = np.array([[n, 0.0, -sy], [0.0, n, sx], [-sy, sx, float(bx @ bx + by @ by)]])
    Jtr = np.array([rx.sum(), ry.sum(), float(rb_x @ ry - rb_y @ rx)])
    return JtJ, Jtr, float(rx @ rx + ry @ ry)


def refine(a_m: FloatArray, b_m: FloatArray, initial: FloatArray, max_iterations: int = 8) -> RefineResult:
    """Minimize sum |d + R(dyaw) b_i - a_i|^2 from `initial` (dx, dy, dyaw) by Levenberg-Marquardt."""
    params = np.asarray(initial, dtype=np.float64).copy()
    JtJ, Jtr, cost = _normal_equations(params, a_m, b_m)
    lam = 1e-4
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - the count is reported
        H = JtJ + lam * np.diag(np.diag(JtJ))
        step = -np.linalg.solve(H, Jtr)
        trial = params + step
        JtJ_t, Jtr_t, cost_t = _normal_equations(trial, a_m, b_m)
        if cost_t <= cost:
            params, JtJ, Jtr, cost = trial, JtJ_t, Jtr_t, cost_t
            lam = max(lam * 0.1, 1e-12)
            if abs(step[2]) < 1e-9 and abs(step[0]) + abs(step[1]) < 1e-8:
                break
        else:
            lam *= 10.0
    return _result(params, JtJ, cost, a_m.shape[0], it)


def evaluate(a_m: FloatArray, b_m: FloatArray, params: FloatArray) -> RefineResult:
    """Statistics of a given increment without iterating (for refine = False)."""
    p = np.asarray(params, dtype=np.float64)
    JtJ, _, cost = _normal_equations(p, a_m, b_m)
    return _result(p, JtJ, cost, a_m.shape[0], 0)


def _result(params: FloatArray, JtJ: FloatArray, cost: float, n: int, iterations: int) -> RefineResult:
    dof = max(2 * n - 3, 1)
    sigma2 = cost / dof
    try:
        cov = sigma2 * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    return RefineResult(
        increment=params.copy(),
        covariance=0.5 * (cov + cov.T),
        rms_m=float(np.sqrt(cost / max(n, 1))),
        iterations=iterations,
    )


def tilt_fields(q_level_m: FloatArray, nadir_level_m: FloatArray, height_m: float) -> FloatArray:
    """Ground displacement fields (3, N, 2) of small attitude and height errors of one frame.

    A roll or pitch error e of a camera at height h moves a ground point at (x, y) from the nadir by
    e (h + y^2/h, x y/h) or e (h + x^2/h, x y/h) (up to sign and axis). The uniform h e part cannot
    be told from a translation; the quadratic parts can: fields 0 and 1 are (x y, y^2)/h and
    (x^2, x y)/h (per radian). A relative height error s scales the points about the nadir:
    field 2 is (x, y) (per unit relative error).
    """
    x = q_level_m[:, 0] - nadir_level_m[0]
    y = q_level_m[:, 1] - nadir_level_m[1]
    xy = x * y / height_m
    u = np.stack([xy, y * y / height_m], axis=-1)
    v = np.stack([x * x / height_m, xy], axis=-1)
    return np.stack([u, v, np.stack([x, y], axis=-1)])


def residuals_and_jacobian_tilt(
    params: FloatArray, a_m: FloatArray, b_m: FloatArray, fields_b: FloatArray, fields_a: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Residuals and Jacobian of the model with nuisance warp fields on both frames.

    r_i = d + R(dyaw) (b_i + sum_j e_j fb_j,i) - (a_i + sum_j e'_j fa_j,i), parameters
    (dx, dy, dyaw, e_1..e_K, e'_1..e'_M); `fields_b` (K, N, 2), `fields_a` (M, N, 2).
    Returns r (N, 2) and d r / d params (N, 2, 3 + K + M).
    """
    nb, na = fields_b.shape[0], fields_a.shape[0]
    n = a_m.shape[0]
    c, s = np.cos(params[2]), np.sin(params[2])
    p = b_m + (params[3 : 3 + nb] @ fields_b.reshape(nb, 2 * n)).reshape(n, 2)
    q = a_m + (params[3 + nb : 3 + nb + na] @ fields_a.reshape(na, 2 * n)).reshape(n, 2)
    rp_x = c * p[:, 0] - s * p[:, 1]
    rp_y = s * p[:, 0] + c * p[:, 1]
    r = np.empty((n, 2))
    r[:, 0] = params[0] + rp_x - q[:, 0]
    r[:, 1] = params[1] + rp_y - q[:, 1]
    J = np.zeros((n, 2, 3 + nb + na))
    J[:, 0, 0] = 1.0
    J[:, 1, 1] = 1.0
    J[:, 0, 2] = -rp_y
    J[:, 1, 2] = rp_x
    J[:, 0, 3 : 3 + nb] = (c * fields_b[:, :, 0] - s * fields_b[:, :, 1]).T
    J[:, 1, 3 : 3 + nb] = (s * fields_b[:, :, 0] + c * fields_b[:, :, 1]).T
    J[:, 0, 3 + nb :] = -fields_a[:, :, 0].T
    J[:, 1, 3 + nb :] = -fields_a[:, :, 1].T
    return r, J


def refine_with_tilt(
    a_m: FloatArray,
    b_m: FloatArray,
    fields_b: FloatArray,
    fields_a: FloatArray,
    initial: FloatArray,
    data_std_m: float,
    prior_std: FloatArray,
    max_iterations: int = 8,
) -> RefineResult:
    """MAP (Gauss-Newton) refinement of (dx, dy, dyaw) with tilt and height errors of both frames
    as nuisance parameters.

    Beyond the paper: an IMU roll/pitch error warps a frame's ground points non-rigidly
    (`tilt_fields`); the rotation fitted to a warped point set depends on which points matched,
    so the warp leaks into dyaw and accumulates. The nuisance coefficients (radians) get a
    zero-mean Gaussian prior with standard deviations `prior_std` (one per field: the IMU attitude
    error in radians, the relative height error), the point residuals a standard deviation
    `data_std_m`. The covariance is the (dx, dy, dyaw) block of the posterior
    one, scaled up by the reduced chi-square when the data scatter more than `data_std_m`.
    """
    nf = fields_b.shape[0] + fields_a.shape[0]
    k = 3 + nf
    params = np.zeros(k)
    params[:3] = initial
    n = a_m.shape[0]
    w = 1.0 / (data_std_m * data_std_m)
    prior = np.zeros(k)
    prior[3:] = 1.0 / np.maximum(np.asarray(prior_std, dtype=np.float64), 1e-9) ** 2

    def normal(p: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        r, J = residuals_and_jacobian_tilt(p, a_m, b_m, fields_b, fields_a)
        Jf = J.reshape(2 * n, k)
        rf = r.reshape(2 * n)
        data = float(rf @ rf)
        H = w * (Jf.T @ Jf) + np.diag(prior)
        g = w * (Jf.T @ rf) + prior * p
        return H, g, data

    # The model is linear in everything but dyaw, and the closed form starts next to the optimum:
    # undamped Gauss-Newton steps converge in two or three iterations.
    H, g, data = normal(params)
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - the count is reported
        step = -np.linalg.solve(H, g)
        params = params + step
        H, g, data = normal(params)
        if abs(step[2]) < 1e-9 and abs(step[0]) + abs(step[1]) < 1e-8:
            break
    chi2_red = w * data / max(2 * n - 3, 1)
    cov = np.linalg.inv(H)[:3, :3] * max(1.0, chi2_red)
    return RefineResult(params[:3].copy(), 0.5 * (cov + cov.T), float(np.sqrt(data / max(n, 1))), it)


@dataclass(frozen=True)
class NuisanceResult:
    """`refine_with_nuisance` output: the increment result and the nuisance posterior.

    result:          the (dx, dy, dyaw) `RefineResult` (covariance as in `refine_with_tilt`).
    nuisance_mean:   (m,) posterior mean of the nuisance parameters z.
    nuisance_cov:    (m, m) posterior covariance of z (Gauss-Newton, at the optimum, unscaled).
    """

    result: RefineResult
    nuisance_mean: FloatArray
    nuisance_cov: FloatArray


def residuals_and_jacobian_nuisance(
    params: FloatArray,
    a_m: FloatArray,
    b_m: FloatArray,
    fields_b: FloatArray,
    fields_a: FloatArray,
    map_b: FloatArray,
    map_a: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Residuals and Jacobian of the warp model with linearly mapped nuisance parameters.

    Parameters (dx, dy, dyaw, z_1..z_m); the warp coefficients are e = map_b @ z on the fields of
    b (`fields_b` (K, N, 2), `map_b` (K, m)) and e' = map_a @ z on those of a (`fields_a` (M, N, 2),
    `map_a` (M, m)): r_i = d + R(dyaw) (b_i + sum_j e_j fb_j,i) - (a_i + sum_j e'_j fa_j,i).
    Returns r (N, 2) and d r / d params (N, 2, 3 + m).
    """
    z = params[3:]
    full = np.concatenate([params[:3], map_b @ z, map_a @ z])
    r, J = residuals_and_jacobian_tilt(full, a_m, b_m, fields_b, fields_a)
    nb = fields_b.shape[0]
    Jz = J[:, :, 3 : 3 + nb] @ map_b + J[:, :, 3 + nb :] @ map_a
    return r, np.concatenate([J[:, :, :3], Jz], axis=2)


def refine_with_nuisance(
    a_m: FloatArray,
    b_m: FloatArray,
    fields_b: FloatArray,
    fields_a: FloatArray,
    initial: FloatArray,
    data_std_m: float,
    prior_mean: FloatArray,
    prior_cov: FloatArray,
    map_b: FloatArray,
    map_a: FloatArray,
    max_iterations: int = 8,
) -> NuisanceResult:
    """MAP (Gauss-Newton) refinement of (dx, dy, dyaw) with correlated nuisance warp parameters.

    As `refine_with_tilt`, but the warp coefficients of both frames are linear maps of nuisance
    parameters z (`residuals_and_jacobian_nuisance`) with a full Gaussian prior
    z ~ N(`prior_mean`, `prior_cov`). With z = (slow tilt bias shared by both frames, white tilt
    and height errors of each frame) this lets the odometer accumulate evidence about a slowly
    varying attitude bias over many frames (`tilt_bias`). Returns the increment result and the
    posterior mean and covariance of z.
    """

    def model(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        return residuals_and_jacobian_nuisance(p, a_m, b_m, fields_b, fields_a, map_b, map_a)

    return _map_gauss_newton(model, initial, data_std_m, prior_mean, prior_cov, max_iterations)


def _map_gauss_newton(
    model: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
    initial: FloatArray,
    data_std_m: float,
    prior_mean: FloatArray,
    prior_cov: FloatArray,
    max_iterations: int,
) -> NuisanceResult:
    """Gauss-Newton MAP estimate of (dx, dy, dyaw, z) for a residual `model` (r (N, 2), J (N, 2, 3 + m)),
    isotropic point noise `data_std_m` and the Gaussian prior z ~ N(prior_mean, prior_cov)."""
    z0 = np.asarray(prior_mean, dtype=np.float64)
    k = 3 + z0.size
    params = np.concatenate([np.asarray(initial, dtype=np.float64), z0])
    w = 1.0 / (data_std_m * data_std_m)
    info = np.zeros((k, k))
    info[3:, 3:] = np.linalg.inv(np.asarray(prior_cov, dtype=np.float64))

    def normal(p: FloatArray) -> tuple[FloatArray, FloatArray, float, int]:
        r, J = model(p)
        n = r.shape[0]
        Jf = J.reshape(2 * n, k)
        rf = r.reshape(2 * n)
        dz = np.zeros(k)
        dz[3:] = p[3:] - z0
        H = w * (Jf.T @ Jf) + info
        g = w * (Jf.T @ rf) + info @ dz
        return H, g, float(rf @ rf), n

    # Linear in everything but dyaw (and mildly in the exact tilt model); the closed form starts
    # next to the optimum: undamped Gauss-Newton converges in two or three iterations.
    H, g, data, n = normal(params)
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - the count is reported
        step = -np.linalg.solve(H, g)
        params = params + step
        H, g, data, n = normal(params)
        small_z = float(np.abs(step[3:]).max(initial=0.0)) < 1e-8
        if abs(step[2]) < 1e-9 and abs(step[0]) + abs(step[1]) < 1e-8 and small_z:
            break
    chi2_red = w * data / max(2 * n - 3, 1)
    Hinv = np.linalg.inv(H)
    Hinv = 0.5 * (Hinv + Hinv.T)
    cov = Hinv[:3, :3] * max(1.0, chi2_red)
    result = RefineResult(params[:3].copy(), cov, float(np.sqrt(data / max(n, 1))), it)
    return NuisanceResult(result, params[3:].copy(), Hinv[3:, 3:].copy())


# d omega / d (e_0, e_1): the level-frame rotation that undoes a tilt error with field coefficients
# (e_0, e_1) (`tilt_fields`: the points move by -omega_x field 0 + omega_y field 1 to first order).
_OMEGA_OF_E = np.array([[-1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])


def tilt_corrected_points(
    rays_level: FloatArray, height_m: float, nadir_level_m: FloatArray, e: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Ground points of one frame re-projected with a tilt and height correction, exactly.

    `rays_level` (N, 3): the frame's rays in its (measured) level frame at unit depth
    (`backproject.ground_rays_level`); `e` = (e_0, e_1, s): the rays are rotated by
    omega = (-e_0, e_1, 0) (so e_0, e_1 are the coefficients of `tilt_fields` 0 and 1 to first
    order) and the height scaled by (1 + s). The uniform shift of the camera nadir that the rotation
    causes is removed (it cannot be told from a translation; left in the data it telescopes
    between consecutive increments), so e = 0 gives nadir + h * ray[:2] and the first-order change
    is e_0 field 0 + e_1 field 1 + s field 2.
    Returns the points (N, 2), metres, and their Jacobian d points / d e (N, 2, 3).
    """
    omega = _OMEGA_OF_E @ e[:2]
    R = so3.exp(omega)
    M = so3.left_jacobian(omega) @ _OMEGA_OF_E  # (3, 2): d omega_eff / d (e_0, e_1)
    H = height_m * (1.0 + e[2])
    p = rays_level @ R.T
    nad = R[:, 2]
    pz = p[:, 2:3]
    u = p[:, :2] / pz - nad[:2] / nad[2]
    points = nadir_level_m + H * u
    J = np.empty((rays_level.shape[0], 2, 3))
    for j in range(2):
        dp = np.cross(M[:, j], p)  # d p / d e_j = (M e_j) x p
        dn = np.cross(M[:, j], nad)
        du = (dp[:, :2] * pz - p[:, :2] * dp[:, 2:3]) / (pz * pz) - (dn[:2] * nad[2] - nad[:2] * dn[2]) / nad[2] ** 2
        J[:, :, j] = H * du
    J[:, :, 2] = height_m * u
    return points, J


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


def _rotation_xy_rows(wx: float, wy: float) -> list[list[float]]:
    """Rodrigues rotation of the vector (wx, wy, 0) as nested lists, with scalar math (hot path)."""
    t2 = wx * wx + wy * wy
    if t2 < 1e-12:
        A, B = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        A, B = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    # W = hat((wx, wy, 0)); W^2 = w w^T - t2 I.
    return [
        [1.0 + B * (wx * wx - t2), B * wx * wy, A * wy],
        [B * wx * wy, 1.0 + B * (wy * wy - t2), -A * wx],
        [-A * wy, A * wx, 1.0 - B * t2],
    ]


def _corrected_stack(rays_level: FloatArray, heights_m: FloatArray, nadirs_m: FloatArray, e: FloatArray) -> FloatArray:
    """`tilt_corrected_points` of F frames at once, without the Jacobian (hot path): rays (F, N, 3),
    heights (F,), nadirs (F, 2), e (F, 3) -> points (F, N, 2)."""
    # The per-frame scalars with Python floats (the same IEEE operations as the array expressions
    # H = h (1 + s), offset = nadir - (H / R_22) R_:2,2).
    rows = []
    heights = []
    offsets = []
    for ef, h, nad in zip(e.tolist(), heights_m.tolist(), nadirs_m.tolist(), strict=True):
        Rf = _rotation_xy_rows(-ef[0], ef[1])
        Hf = h * (1.0 + ef[2])
        k = Hf / Rf[2][2]
        rows.append(Rf)
        heights.append([[Hf]])
        offsets.append([[nad[0] - k * Rf[0][2], nad[1] - k * Rf[1][2]]])
    R = np.array(rows)  # (F, 3, 3)
    p = rays_level @ np.transpose(R, (0, 2, 1))
    out: FloatArray = p[:, :, :2] * (np.array(heights) / p[:, :, 2:3]) + np.array(offsets)
    return out


def _corrected_points(rays_level: FloatArray, height_m: float, nadir_level_m: FloatArray, e: FloatArray) -> FloatArray:
    """`tilt_corrected_points` without the Jacobian (hot path)."""
    out: FloatArray = _corrected_stack(
        rays_level[None], np.array([height_m]), np.asarray(nadir_level_m)[None], np.asarray(e)[None]
    )[0]
    return out


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
