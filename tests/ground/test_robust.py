"""Outlier rejection with 40 % bad matches, and the Kalman filter of eq. 27."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.vision.ground import kalman
from companion.vision.ground.closed_form import gen_to_increment, solve_gen
from companion.vision.ground.refine import refine
from companion.vision.ground.robust import mad_trim, ransac_rigid


def _with_outliers(rng: np.random.Generator, fraction: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n = 200
    truth = np.array([0.03, -0.015, 0.04])
    c, s = math.cos(truth[2]), math.sin(truth[2])
    b = rng.uniform(-0.8, 0.8, (n, 2))
    a = truth[:2] + b @ np.array([[c, -s], [s, c]]).T + rng.normal(0.0, 0.001, (n, 2))
    bad = rng.random(n) < fraction
    # Bad matches: wrong points within the speed gate (the hard case), e.g. repeated texture.
    a[bad] = a[bad] + rng.uniform(-0.15, 0.15, (int(bad.sum()), 2))
    return a, b, bad, truth


@pytest.mark.parametrize("method", ["ransac", "mad"])
def test_forty_percent_bad_matches(rng: np.random.Generator, method: str) -> None:
    a, b, bad, truth = _with_outliers(rng, 0.4)
    assert 0.35 < bad.mean() < 0.45
    if method == "ransac":
        inl = ransac_rigid(a, b, 0.005, 48, rng)
    else:
        inl = mad_trim(a, b, 0.005)
    # Nearly all good matches kept, bad ones (that are really off) dropped.
    far = bad & (
        np.linalg.norm(
            a
            - (
                truth[:2]
                + b @ np.array([[math.cos(truth[2]), -math.sin(truth[2])], [math.sin(truth[2]), math.cos(truth[2])]]).T
            ),
            axis=1,
        )
        > 0.01
    )
    assert inl[~bad].mean() > 0.95
    assert not inl[far].any()
    est = refine(a[inl], b[inl], gen_to_increment(solve_gen(a[inl], b[inl]))).increment
    np.testing.assert_allclose(est, truth, atol=5e-4)
    # Without rejection the same data give a clearly worse answer (the test can fail).
    naive = refine(a, b, gen_to_increment(solve_gen(a, b))).increment
    assert np.abs(naive - truth).max() > 5 * np.abs(est - truth).max()


def test_ransac_is_deterministic_for_a_seed(rng: np.random.Generator) -> None:
    a, b, _, _ = _with_outliers(rng, 0.4)
    m1 = ransac_rigid(a, b, 0.005, 32, np.random.default_rng(1))
    m2 = ransac_rigid(a, b, 0.005, 32, np.random.default_rng(1))
    assert np.array_equal(m1, m2)


def test_kalman_follows_constant_acceleration() -> None:
    dt = 0.05
    state = kalman.initial_state(0.0)
    psd = np.array([1.0, 1.0, 1.0])
    accel = np.array([0.2, -0.1, 0.05])
    for k in range(1, 200):
        t = k * dt
        rate = accel * t
        measured = rate * dt - 0.5 * accel * dt * dt  # exact increment over the last interval
        state = kalman.predict(state, t, psd)
        state = kalman.update(state, measured, np.full(3, 1e-6), dt)
    inc, var = kalman.increment_of(state, dt)
    np.testing.assert_allclose(state.x[:, 0], accel * 199 * dt, rtol=1e-3)
    np.testing.assert_allclose(state.x[:, 1], accel, rtol=2e-2)
    np.testing.assert_allclose(inc, accel * 199 * dt * dt - 0.5 * accel * dt * dt, rtol=1e-3)
    assert np.all(var > 0)


def test_kalman_smooths_noisy_increments(rng: np.random.Generator) -> None:
    dt = 0.05
    state = kalman.initial_state(0.0)
    raw, filt = [], []
    for k in range(1, 400):
        z = np.array([0.5, 0.0, 0.0]) * dt + rng.normal(0.0, 0.005, 3)
        state = kalman.update(kalman.predict(state, k * dt, np.full(3, 0.05)), z, np.full(3, 0.005**2), dt)
        raw.append(z)
        filt.append(kalman.increment_of(state, dt)[0])
    assert np.std(np.array(filt)[100:, 0]) < 0.5 * np.std(np.array(raw)[100:, 0])
    assert np.mean(np.array(filt)[100:, 0]) == pytest.approx(0.5 * dt, abs=1e-3)
