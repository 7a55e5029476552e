"""Constant-acceleration Kalman filter on the odometer increments (paper eq. 27).

State per axis (x north, y east, yaw): (rate, acceleration) -- the paper's (x', x''). The three
axes are independent 2-state filters, stacked (3, 2) and (3, 2, 2). The measurement is the
increment over an interval dt, modelled exactly under constant acceleration as
dx = rate_k dt - accel_k dt^2 / 2 (the paper writes [dT 0]; the extra term removes the half-step
lag). Process noise: white jerk with spectral density q per axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray

_INITIAL_RATE_VAR = 100.0  # (m/s)^2 or (rad/s)^2: effectively unknown before the first increment
_INITIAL_ACCEL_VAR = 100.0


@dataclass(frozen=True)
class KalmanState:
    """Filter state: `x` (3, 2) rate/accel per axis, `P` (3, 2, 2), at time `stamp_s`."""

    x: FloatArray
    P: FloatArray
    stamp_s: float


def initial_state(stamp_s: float) -> KalmanState:
    P = np.zeros((3, 2, 2))
    P[:, 0, 0] = _INITIAL_RATE_VAR
    P[:, 1, 1] = _INITIAL_ACCEL_VAR
    return KalmanState(np.zeros((3, 2)), P, float(stamp_s))


def predict(state: KalmanState, stamp_s: float, jerk_psd: FloatArray) -> KalmanState:
    """Propagate to `stamp_s` (s) with white-jerk process noise `jerk_psd` (3,)."""
    dt = max(float(stamp_s) - state.stamp_s, 0.0)
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Qn = np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    x = state.x @ F.T
    P = F @ state.P @ F.T + jerk_psd[:, None, None] * Qn
    return KalmanState(x, P, float(stamp_s))


def update(state: KalmanState, increment: FloatArray, variance: FloatArray, dt_s: float) -> KalmanState:
    """Fuse a measured increment (3,) over the last `dt_s` seconds with per-axis `variance` (3,)."""
    H = np.array([dt_s, -0.5 * dt_s * dt_s])
    PHt = state.P @ H  # (3, 2)
    S = PHt @ H + variance  # (3,)
    K = PHt / S[:, None]
    innovation = increment - state.x @ H
    x = state.x + K * innovation[:, None]
    P = state.P - K[:, :, None] * PHt[:, None, :]
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    return KalmanState(x, P, state.stamp_s)


def increment_of(state: KalmanState, dt_s: float) -> tuple[FloatArray, FloatArray]:
    """The filtered increment (3,) over the last `dt_s` seconds and its per-axis variance (3,)."""
    H = np.array([dt_s, -0.5 * dt_s * dt_s])
    inc: FloatArray = state.x @ H
    var: FloatArray = (state.P @ H) @ H
    return inc, var
