"""Dryden wind: MIL-F-8785C low-altitude scales, stationary variance and autocorrelation, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.errors import InputError
from companion.sim.autopilot.wind import (
    FT_M,
    DrydenConfig,
    DrydenWind,
    lateral_autocorrelation,
    longitudinal_autocorrelation,
    low_altitude_scales,
    mean_wind_speed_m_s,
)


def test_low_altitude_scales_match_mil_f_8785c_formulas() -> None:
    h_ft = 100.0
    s = low_altitude_scales(h_ft * FT_M, 10.0)
    k = 0.177 + 0.000823 * h_ft
    assert s.L_w_m == pytest.approx(h_ft * FT_M)
    assert s.L_u_m == pytest.approx(h_ft / k**1.2 * FT_M)
    assert s.L_v_m == s.L_u_m
    assert s.sigma_w_m_s == pytest.approx(1.0)
    assert s.sigma_u_m_s == pytest.approx(1.0 / k**0.4)
    # Below 10 ft the scales are those of 10 ft.
    assert low_altitude_scales(0.5, 10.0) == low_altitude_scales(10.0 * FT_M, 10.0)
    with pytest.raises(InputError):
        low_altitude_scales(10.0, -1.0)


def test_mean_wind_profile_is_w20_at_20_ft_and_grows_with_height() -> None:
    assert mean_wind_speed_m_s(20.0 * FT_M, 7.0) == pytest.approx(7.0)
    assert mean_wind_speed_m_s(30.0, 7.0) > mean_wind_speed_m_s(5.0, 7.0)


def test_no_wind_gives_zero_and_mean_wind_blows_from_the_given_direction() -> None:
    calm = DrydenWind(DrydenConfig(), np.random.default_rng(0))
    assert calm.step(5.0, (0.0, 0.0, 0.0), 0.01) == (0.0, 0.0, 0.0)
    # Wind from the east (pi/2) blows toward the west: negative east component.
    steady = DrydenWind(DrydenConfig(w20_m_s=5.0, from_rad=math.pi / 2, turbulence=0.0), np.random.default_rng(0))
    n, e, d = steady.step(20.0 * FT_M, (0.0, 0.0, 0.0), 0.01)
    assert n == pytest.approx(0.0, abs=1e-12)
    assert e == pytest.approx(-5.0)
    assert d == 0.0


def _series(seed: int, n: int, dt_s: float, height_m: float, velocity: tuple[float, float, float]) -> np.ndarray:
    wind = DrydenWind(DrydenConfig(w20_m_s=6.0, from_rad=0.0), np.random.default_rng(seed))
    return np.array([wind.step(height_m, velocity, dt_s) for _ in range(n)])


def test_gust_statistics_follow_the_dryden_model() -> None:
    # Flying fast (airspeed 20 m/s) makes the correlation times short, so 60,000 samples hold
    # hundreds of correlation times of every component.
    dt_s, height_m, n = 0.05, 10.0, 60_000
    out = _series(7, n, dt_s, height_m, (-20.0, 0.0, 0.0))
    scales = low_altitude_scales(height_m, 6.0)
    mean = mean_wind_speed_m_s(height_m, 6.0)
    # Wind from north blows south: u (along the mean wind) = -north - mean, v (right of it) = -east, w = down.
    u = -out[:, 0] - mean
    v = -out[:, 1]
    w = out[:, 2]
    airspeed = 20.0 - mean
    checks = [
        (u, scales.sigma_u_m_s, scales.L_u_m / airspeed, longitudinal_autocorrelation),
        (v, scales.sigma_v_m_s, scales.L_v_m / airspeed, lateral_autocorrelation),
        (w, scales.sigma_w_m_s, scales.L_w_m / airspeed, lateral_autocorrelation),
    ]
    for x, sigma, T_s, model in checks:
        assert abs(float(np.mean(x))) < 0.15 * sigma
        assert float(np.std(x)) == pytest.approx(sigma, rel=0.12)
        for lag_T in (0.5, 1.0):
            lag = max(1, round(lag_T * T_s / dt_s))
            empirical = float(np.mean(x[:-lag] * x[lag:]))
            expected = float(model(np.array(lag * dt_s), sigma, T_s))
            assert empirical == pytest.approx(expected, abs=0.12 * sigma**2)
    # The lateral correlation goes negative near 2T (the (1 - τ/2T) factor): the shape is not first order.
    lag = round(3.0 * scales.L_w_m / airspeed / dt_s)
    assert float(np.mean(w[:-lag] * w[lag:])) < 0.05 * scales.sigma_w_m_s**2


def test_gusts_are_deterministic_by_seed() -> None:
    a = _series(3, 200, 0.01, 5.0, (0.0, 0.0, 0.0))
    b = _series(3, 200, 0.01, 5.0, (0.0, 0.0, 0.0))
    c = _series(4, 200, 0.01, 5.0, (0.0, 0.0, 0.0))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_config_rejects_bad_values() -> None:
    with pytest.raises(InputError):
        DrydenConfig(w20_m_s=-1.0)
    with pytest.raises(InputError):
        DrydenConfig(min_airspeed_m_s=0.0)


@pytest.mark.parametrize("T_s", [0.2, 3.0, 40.0])
@pytest.mark.parametrize("dt_s", [0.0025, 0.05])
def test_closed_form_discretization_matches_van_loan(T_s: float, dt_s: float) -> None:
    from scipy import linalg

    from companion.sim.autopilot.wind import _discretize

    for order, A_c in ((1, np.array([[-1.0 / T_s]])), (2, np.array([[0.0, 1.0], [-1.0 / T_s**2, -2.0 / T_s]]))):
        n = order
        B = np.zeros((n, 1))
        B[-1, 0] = 1.0
        M = np.zeros((2 * n, 2 * n))
        M[:n, :n] = -A_c
        M[:n, n:] = B @ B.T
        M[n:, n:] = A_c.T
        E = linalg.expm(M * dt_s)
        A_d = E[n:, n:].T
        Q_d = A_d @ E[:n, n:]
        d = _discretize(order, T_s, dt_s)
        L = np.array(d.L)
        assert np.allclose(np.array(d.A), A_d, rtol=1e-12, atol=1e-15)
        assert np.allclose(L @ L.T, Q_d, rtol=1e-6, atol=1e-8 * np.abs(Q_d).max())
