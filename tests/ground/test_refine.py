"""LM refinement (eq. 26): Jacobians vs central differences, optimum, GEN/SMA agreement."""

from __future__ import annotations

import math

import numpy as np

from companion.vision.ground.closed_form import gen_to_increment, solve_gen, solve_sma
from companion.vision.ground.refine import (
    refine,
    refine_with_tilt,
    residuals_and_jacobian,
    residuals_and_jacobian_tilt,
    tilt_fields,
)
from tests.numdiff import central_jacobian


def _rot(theta: float) -> np.ndarray:
    return np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])


def _data(rng: np.random.Generator, dyaw: float, noise: float, n: int = 80) -> tuple[np.ndarray, np.ndarray]:
    b = rng.uniform(-0.8, 0.8, (n, 2))
    a = np.array([0.03, -0.02]) + b @ _rot(dyaw).T + rng.normal(0.0, noise, (n, 2))
    return a, b


def _procrustes(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Independent optimum of sum |d + R b - a|^2 (2-D Procrustes)."""
    ac, bc = a - a.mean(0), b - b.mean(0)
    theta = math.atan2(float(np.sum(bc[:, 0] * ac[:, 1] - bc[:, 1] * ac[:, 0])), float(np.sum(bc * ac)))
    d = a.mean(0) - _rot(theta) @ b.mean(0)
    return np.array([d[0], d[1], theta])


def test_jacobian_matches_central_differences(rng: np.random.Generator) -> None:
    a, b = _data(rng, 0.2, 0.01, 7)
    p = np.array([0.1, -0.2, 0.3])
    _, J = residuals_and_jacobian(p, a, b)
    Jn = central_jacobian(lambda x: residuals_and_jacobian(x, a, b)[0], p)
    np.testing.assert_allclose(J.reshape(-1, 3), Jn, atol=1e-8)


def test_tilt_jacobian_matches_central_differences(rng: np.random.Generator) -> None:
    a, b = _data(rng, 0.2, 0.01, 6)
    fb = tilt_fields(b, np.array([0.01, -0.02]), 1.3)
    fa = tilt_fields(a, np.zeros(2), 1.2)
    p = np.array([0.1, -0.2, 0.3, 0.01, -0.02, 0.004, 0.005, 0.003, -0.002])
    _, J = residuals_and_jacobian_tilt(p, a, b, fb, fa)
    Jn = central_jacobian(lambda x: residuals_and_jacobian_tilt(x, a, b, fb, fa)[0], p)
    np.testing.assert_allclose(J.reshape(-1, 9), Jn, atol=1e-8)


def test_lm_reaches_the_least_squares_optimum(rng: np.random.Generator) -> None:
    for dyaw in (0.0, 0.05, 0.5, -1.5):
        a, b = _data(rng, dyaw, 0.003)
        expected = _procrustes(a, b)
        for initial in (gen_to_increment(solve_gen(a, b)), solve_sma(a, b), np.zeros(3)):
            res = refine(a, b, initial, max_iterations=10)
            np.testing.assert_allclose(res.increment, expected, atol=1e-9)


def test_gen_and_sma_agree_after_refinement(rng: np.random.Generator) -> None:
    a, b = _data(rng, 0.08, 0.002)
    gen = refine(a, b, gen_to_increment(solve_gen(a, b)), 8).increment
    sma = refine(a, b, solve_sma(a, b), 8).increment
    assert np.abs(gen[:2] - sma[:2]).max() < 1e-6
    assert abs(gen[2] - sma[2]) < math.radians(0.05) * 1e-3


def test_covariance_matches_monte_carlo(rng: np.random.Generator) -> None:
    """The reported covariance is honest: it matches the scatter of repeated estimates."""
    b = rng.uniform(-0.8, 0.8, (100, 2))
    truth = np.array([0.03, -0.02, 0.1])
    estimates, covs = [], []
    for _ in range(300):
        a = truth[:2] + b @ _rot(truth[2]).T + rng.normal(0.0, 0.002, b.shape)
        res = refine(a, b, gen_to_increment(solve_gen(a, b)))
        estimates.append(res.increment)
        covs.append(res.covariance)
    empirical = np.cov(np.array(estimates).T)
    reported = np.mean(covs, axis=0)
    np.testing.assert_allclose(np.diag(reported), np.diag(empirical), rtol=0.25)


def test_tilt_refinement_removes_warp_from_yaw(rng: np.random.Generator) -> None:
    """A tilt error of one frame warps its points; the tilt-aware fit keeps yaw right."""
    h = 1.25
    b = rng.uniform(-0.9, 0.5, (150, 2))  # off-centre overlap: the warp then leaks into yaw
    truth = np.array([0.02, 0.01, 0.03])
    a = truth[:2] + b @ _rot(truth[2]).T
    eps = math.radians(1.0)
    x, y = b[:, 0], b[:, 1]
    warped_b = b + eps * np.stack([x * y / h, y * y / h], axis=-1)
    plain = refine(a, warped_b, np.zeros(3)).increment
    fb = tilt_fields(warped_b, np.zeros(2), h)
    fa = tilt_fields(a, np.zeros(2), h)
    prior = np.array([math.radians(2.0), math.radians(2.0), 0.01] * 2)
    tilt = refine_with_tilt(a, warped_b, fb, fa, plain, 0.001, prior, 20).increment
    assert abs(tilt[2] - truth[2]) < 0.2 * abs(plain[2] - truth[2])
