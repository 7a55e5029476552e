"""MAP refinement of (dx, dy, dyaw) with first-order tilt and height warp fields as nuisance parameters.

Ground points in metres, NED-aligned (see `closed_form`); the fields are per radian of attitude
error (0, 1) and per unit relative height error (2).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray
from companion.vision.ground.refine_rigid import RefineResult


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
