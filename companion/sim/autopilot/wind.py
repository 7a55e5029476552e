"""Dryden wind turbulence, MIL-F-8785C low-altitude form, seeded.

The gust components are produced by shaping white noise with the Dryden
filters (Taylor's frozen-turbulence hypothesis: spatial scale L over the
airspeed V gives the time constant T = L / V):

    u (along the mean wind):  H_u(s) = σ_u √(2T/π) / (1 + T_u s)
    v (lateral), w (vertical): H(s) = σ √(T/π) (1 + √3 T s) / (1 + T s)²

whose autocorrelations are ``σ² exp(-τ/T)`` (u) and
``σ² (1 - τ/(2T)) exp(-τ/T)`` (v, w). Each filter is discretized exactly
(state transition plus the exact discrete noise covariance, in closed form), so
the stationary variance is σ² at any step size.

Low-altitude scales (height h in feet, clamped to 10..1000 ft), MIL-F-8785C:
``L_w = h``, ``L_u = L_v = h / (0.177 + 0.000823 h)^1.2``,
``σ_w = 0.1 W20``, ``σ_u = σ_v = σ_w / (0.177 + 0.000823 h)^0.4``,
where W20 is the wind speed at 20 ft. The mean wind follows the logarithmic
profile ``W(h) = W20 ln(h / z0) / ln(20 / z0)`` with z0 = 0.15 ft.

The paper (Lippiello & Cacace, Sec. V) perturbs the vehicle with this model;
here it enters the vehicle dynamics as an aerodynamic drag disturbance.
All quantities are SI; the output is the air velocity in NED (m/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from companion.errors import InputError

__all__ = [
    "DrydenConfig",
    "DrydenWind",
    "TurbulenceScales",
    "lateral_autocorrelation",
    "longitudinal_autocorrelation",
    "low_altitude_scales",
    "mean_wind_speed_m_s",
]

FT_M = 0.3048
_Z0_FT = 0.15


@dataclass(frozen=True)
class TurbulenceScales:
    """Dryden scale lengths (m) and intensities (m/s) for one height."""

    L_u_m: float
    L_v_m: float
    L_w_m: float
    sigma_u_m_s: float
    sigma_v_m_s: float
    sigma_w_m_s: float


def low_altitude_scales(height_m: float, w20_m_s: float) -> TurbulenceScales:
    """MIL-F-8785C low-altitude scales at `height_m` above ground for wind `w20_m_s` at 20 ft."""
    if w20_m_s < 0.0 or not math.isfinite(w20_m_s):
        raise InputError(f"w20_m_s must be finite and >= 0, got {w20_m_s!r}")
    h_ft = min(max(height_m / FT_M, 10.0), 1000.0)
    k = 0.177 + 0.000823 * h_ft
    L_w_m = h_ft * FT_M
    L_uv_m = h_ft / k**1.2 * FT_M
    sigma_w = 0.1 * w20_m_s
    sigma_uv = sigma_w / k**0.4
    return TurbulenceScales(L_uv_m, L_uv_m, L_w_m, sigma_uv, sigma_uv, sigma_w)


def mean_wind_speed_m_s(height_m: float, w20_m_s: float) -> float:
    """Logarithmic mean-wind profile (m/s) at `height_m`; heights below 3 ft use 3 ft."""
    h_ft = max(height_m / FT_M, 3.0)
    return w20_m_s * math.log(h_ft / _Z0_FT) / math.log(20.0 / _Z0_FT)


def longitudinal_autocorrelation(lag_s: np.ndarray, sigma_m_s: float, T_s: float) -> np.ndarray:
    """Dryden longitudinal autocorrelation σ² exp(-τ/T) at lags `lag_s` (s)."""
    tau = np.abs(np.asarray(lag_s, dtype=float))
    return np.asarray(sigma_m_s**2 * np.exp(-tau / T_s))


def lateral_autocorrelation(lag_s: np.ndarray, sigma_m_s: float, T_s: float) -> np.ndarray:
    """Dryden lateral/vertical autocorrelation σ² (1 - τ/(2T)) exp(-τ/T) at lags `lag_s` (s)."""
    tau = np.abs(np.asarray(lag_s, dtype=float))
    return np.asarray(sigma_m_s**2 * (1.0 - tau / (2.0 * T_s)) * np.exp(-tau / T_s))


@dataclass(frozen=True)
class _Discrete:
    """Exact discretization of a unit-variance shaping filter: x+ = A x + L ξ, y = C x."""

    A: tuple[tuple[float, ...], ...]
    L: tuple[tuple[float, ...], ...]
    C: tuple[float, ...]
    P_chol: tuple[tuple[float, ...], ...]  # Cholesky factor of the stationary state covariance


def _quantize(T_s: float) -> float:
    # 1 % steps in log(T): the filters are cached, and T changes slowly with height and airspeed.
    return math.exp(round(math.log(T_s) * 100.0) / 100.0)


@lru_cache(maxsize=512)
def _discretize(order: int, T_s: float, dt_s: float) -> _Discrete:
    """Exact discretization in closed form (no matrix exponential: this runs inside the physics loop).

    First order: x' = -x/T + ξ. Second order (controllable canonical form of 1/(1 + T s)²):
    x'' = -x/T² - 2x'/T + ξ, a double pole at -1/T, so exp(A t) = e^{-t/T} (I + (A + I/T) t).
    The stationary covariance P of unit white noise is known in closed form, and the exact
    discrete process noise of a stationary process is Q_d = P - A_d P A_dᵀ.
    """
    decay = math.exp(-dt_s / T_s)
    if order == 1:
        P = np.array([[T_s / 2.0]])
        A_d = np.array([[decay]])
        C_c = np.array([1.0])
    else:
        A_c = np.array([[0.0, 1.0], [-1.0 / T_s**2, -2.0 / T_s]])
        A_d = decay * (np.eye(2) + (A_c + np.eye(2) / T_s) * dt_s)
        P = np.diag([T_s**3 / 4.0, T_s / 4.0])
        C_c = np.array([1.0 / T_s**2, math.sqrt(3.0) / T_s])
    C_c = C_c / math.sqrt(float(C_c @ P @ C_c))  # unit output variance
    Q_d = P - A_d @ P @ A_d.T
    Q_d = 0.5 * (Q_d + Q_d.T)
    w, V = np.linalg.eigh(Q_d)
    L_d = V @ np.diag(np.sqrt(np.clip(w, 0.0, None)))
    P_chol = np.linalg.cholesky(P)
    return _Discrete(
        tuple(tuple(float(v) for v in row) for row in A_d),
        tuple(tuple(float(v) for v in row) for row in L_d),
        tuple(float(v) for v in C_c),
        tuple(tuple(float(v) for v in row) for row in P_chol),
    )


@dataclass(frozen=True)
class DrydenConfig:
    """Wind settings.

    ``w20_m_s``: mean wind speed at 20 ft (6.1 m) above ground (m/s); 0 disables wind and gusts.
    ``from_rad``: direction the mean wind blows FROM, clockwise from north (rad).
    ``turbulence``: scale factor on the Dryden intensities (1 = MIL-F-8785C, 0 = mean wind only).
    ``min_airspeed_m_s``: floor on the airspeed used for T = L / V (a hovering vehicle in calm air).
    """

    w20_m_s: float = 0.0
    from_rad: float = 0.0
    turbulence: float = 1.0
    min_airspeed_m_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("w20_m_s", "turbulence"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0.0:
                raise InputError(f"DrydenConfig.{name} must be finite and >= 0, got {value!r}")
        if not self.min_airspeed_m_s > 0.0:
            raise InputError(f"DrydenConfig.min_airspeed_m_s must be > 0, got {self.min_airspeed_m_s!r}")


class DrydenWind:
    """Seeded Dryden gust generator (stateful: it owns the filter states and the noise stream).

    `step(height_m, velocity_ned_m_s, dt_s)` advances the filters by `dt_s` and returns the
    air velocity (mean wind + gust) in NED, m/s.
    """

    def __init__(self, config: DrydenConfig, rng: np.random.Generator) -> None:
        self.config = config
        self._rng = rng
        self._x_u = [0.0]
        self._x_v = [0.0, 0.0]
        self._x_w = [0.0, 0.0]
        self._initialized = False
        self.last_gust_uvw_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def _draw_stationary(self, filters: tuple[_Discrete, _Discrete, _Discrete]) -> None:
        # Start in the stationary distribution so statistics hold from the first sample.
        for x, d in zip((self._x_u, self._x_v, self._x_w), filters, strict=True):
            z = self._rng.standard_normal(len(x))
            x[:] = [sum(d.P_chol[i][j] * float(z[j]) for j in range(len(x))) for i in range(len(x))]
        self._initialized = True

    @staticmethod
    def _advance(x: list[float], d: _Discrete, noise: np.ndarray) -> float:
        n = len(x)
        new = [
            sum(d.A[i][j] * x[j] for j in range(n)) + sum(d.L[i][j] * float(noise[j]) for j in range(n))
            for i in range(n)
        ]
        x[:] = new
        return sum(d.C[i] * x[i] for i in range(n))

    def step(
        self, height_m: float, velocity_ned_m_s: tuple[float, float, float], dt_s: float
    ) -> tuple[float, float, float]:
        """Advance `dt_s` seconds; return the NED air velocity (m/s) at `height_m` above ground."""
        cfg = self.config
        if cfg.w20_m_s == 0.0:
            return (0.0, 0.0, 0.0)
        mean = mean_wind_speed_m_s(height_m, cfg.w20_m_s)
        toward = cfg.from_rad + math.pi
        c, s = math.cos(toward), math.sin(toward)
        mean_n, mean_e = mean * c, mean * s
        if cfg.turbulence == 0.0:
            return (mean_n, mean_e, 0.0)
        scales = low_altitude_scales(height_m, cfg.w20_m_s)
        airspeed = math.hypot(velocity_ned_m_s[0] - mean_n, velocity_ned_m_s[1] - mean_e)
        V = max(airspeed, cfg.min_airspeed_m_s)
        filters = (
            _discretize(1, _quantize(scales.L_u_m / V), dt_s),
            _discretize(2, _quantize(scales.L_v_m / V), dt_s),
            _discretize(2, _quantize(scales.L_w_m / V), dt_s),
        )
        if not self._initialized:
            self._draw_stationary(filters)
        noise = self._rng.standard_normal(5)
        u = self._advance(self._x_u, filters[0], noise[0:1])
        v = self._advance(self._x_v, filters[1], noise[1:3])
        w = self._advance(self._x_w, filters[2], noise[3:5])
        u *= cfg.turbulence * scales.sigma_u_m_s
        v *= cfg.turbulence * scales.sigma_v_m_s
        w *= cfg.turbulence * scales.sigma_w_m_s
        self.last_gust_uvw_m_s = (u, v, w)
        # u along the mean wind, v to its right, w down.
        return (mean_n + u * c - v * s, mean_e + u * s + v * c, w)
