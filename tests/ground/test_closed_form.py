"""GEN (eq. 20) and SMA (eq. 25) against a generic least-squares solve of the same systems."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.errors import TrackingError
from companion.vision.ground.closed_form import gen_to_increment, paper_sums, solve_gen, solve_sma


def _rot(theta: float) -> np.ndarray:
    return np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])


def _pairs(rng: np.random.Generator, n: int, d: np.ndarray, dyaw: float, noise: float) -> tuple[np.ndarray, np.ndarray]:
    b = rng.uniform(-0.8, 0.8, (n, 2))
    a = d + b @ _rot(dyaw).T + rng.normal(0.0, noise, (n, 2))
    return a, b


def _omega(b: np.ndarray) -> np.ndarray:
    """Eq. 15's matrix: rows [1, 0, bx, -by] and [0, 1, by, bx] per point."""
    n = b.shape[0]
    om = np.zeros((2 * n, 4))
    om[0::2, 0] = 1.0
    om[1::2, 1] = 1.0
    om[0::2, 2] = b[:, 0]
    om[0::2, 3] = -b[:, 1]
    om[1::2, 2] = b[:, 1]
    om[1::2, 3] = b[:, 0]
    return om


@pytest.mark.parametrize("dyaw", [0.0, 0.02, -0.3, 1.2, math.pi - 0.01])
def test_gen_matches_generic_least_squares(rng: np.random.Generator, dyaw: float) -> None:
    a, b = _pairs(rng, 60, np.array([0.05, -0.03]), dyaw, 0.002)
    expected, *_ = np.linalg.lstsq(_omega(b), a.reshape(-1), rcond=None)
    np.testing.assert_allclose(solve_gen(a, b), expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("dyaw", [0.0, 0.01, -0.05, 0.4])
def test_sma_matches_generic_least_squares(rng: np.random.Generator, dyaw: float) -> None:
    a, b = _pairs(rng, 50, np.array([-0.02, 0.04]), dyaw, 0.002)
    n = b.shape[0]
    gamma = np.zeros((2 * n, 3))
    gamma[0::2, 0] = 1.0
    gamma[1::2, 1] = 1.0
    gamma[0::2, 2] = -b[:, 1]
    gamma[1::2, 2] = b[:, 0]
    lam = (a - b).reshape(-1)
    expected, *_ = np.linalg.lstsq(gamma, lam, rcond=None)
    np.testing.assert_allclose(solve_sma(a, b), expected, rtol=1e-9, atol=1e-12)


def test_gen_exact_without_noise_for_any_yaw(rng: np.random.Generator) -> None:
    for dyaw in np.linspace(-3.0, 3.0, 7):
        d = rng.normal(0.0, 0.5, 2)
        a, b = _pairs(rng, 10, d, float(dyaw), 0.0)
        sol = solve_gen(a, b)
        np.testing.assert_allclose(sol, [d[0], d[1], math.cos(dyaw), math.sin(dyaw)], atol=1e-10)
        np.testing.assert_allclose(gen_to_increment(sol), [d[0], d[1], dyaw], atol=1e-10)


def test_sma_close_for_small_yaw(rng: np.random.Generator) -> None:
    a, b = _pairs(rng, 40, np.array([0.01, 0.02]), 0.005, 0.0)
    np.testing.assert_allclose(solve_sma(a, b), [0.01, 0.02, 0.005], atol=2e-5)


def test_paper_sums_definitions() -> None:
    a = np.array([[1.0, 2.0], [3.0, -1.0]])
    b = np.array([[0.5, 1.0], [-2.0, 4.0]])
    s = paper_sums(a, b)
    assert (s.n, s.A, s.B, s.C) == (2, -1.5, -5.0, 0.25 + 1 + 4 + 16)
    assert (s.D, s.E) == (4.0, 1.0)
    assert np.isclose(s.F, 1 * 0.5 + 2 * 1 + 3 * -2 + -1 * 4)
    assert np.isclose(s.G, 2 * 0.5 - 1 * 1 + -1 * -2 - 3 * 4)


def test_degenerate_points_raise() -> None:
    a = np.array([[1.0, 1.0], [1.0, 1.0]])
    with pytest.raises(TrackingError):
        solve_gen(a, a.copy())
    with pytest.raises(TrackingError):
        solve_sma(a[:1], a[:1])
