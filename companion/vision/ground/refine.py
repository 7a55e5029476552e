"""Levenberg-Marquardt refinement of (dx, dy, dyaw) (paper eq. 26), hand-written, 3 parameters.

Residuals r_i = d + R(dyaw) b_i - a_i (N, 2), metres, NED-aligned (see `closed_form`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray


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
