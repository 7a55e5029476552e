"""Levenberg-Marquardt refinement of the rigid increment (dx, dy, dyaw) (paper eq. 26), and its result type.

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
