"""How the safety manager reads its inputs: impossible readings made unknown, ages of timestamps,
threshold tests, number formatting for messages and the debounce latch of the battery failsafe."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from companion.safety.types import SafetyInputs


def _fmt(value: float | None) -> str:
    return "?" if value is None else f"{value:.2f}"


def _age(now_s: float, last_s: float | None) -> float:
    """Seconds since last_s; infinite when there is none or it is not a finite time."""
    return math.inf if last_s is None or not math.isfinite(last_s) else now_s - last_s


def _finite(value: float | None, lo: float = -math.inf, hi: float = math.inf) -> float | None:
    """value as a float when it is a finite reading within [lo, hi], else None (unknown)."""
    if value is None:
        return None
    x = float(value)
    return x if math.isfinite(x) and lo <= x <= hi else None


def _sanitized(inputs: SafetyInputs) -> SafetyInputs:
    """The inputs with impossible readings turned into "unknown" (None).

    NaN/inf anywhere, a battery voltage <= 0 V (an autopilot without a battery monitor reports
    0), a percentage outside 0..100 and a negative ceiling clearance are not readings: treating
    them as values would either trigger a false landing or silently disable a limit (NaN compares
    false). Unknown altitude and position are then handled conservatively by `filter`.
    """
    pos: tuple[float, float, float] | None = None
    if inputs.position_ned_m is not None:
        p = np.asarray(inputs.position_ned_m, dtype=np.float64)
        if p.shape == (3,) and bool(np.all(np.isfinite(p))):
            pos = (float(p[0]), float(p[1]), float(p[2]))
    return replace(
        inputs,
        battery_v=_finite(inputs.battery_v, lo=1e-6),
        battery_pct=_finite(inputs.battery_pct, lo=0.0, hi=100.0),
        altitude_m=_finite(inputs.altitude_m),
        ceiling_clearance_m=_finite(inputs.ceiling_clearance_m, lo=0.0),
        position_ned_m=pos,
    )


def _below(value: float | None, threshold: float | None) -> bool:
    return value is not None and threshold is not None and value < threshold


def _above(value: float | None, threshold: float | None) -> bool:
    """value >= threshold, or no reading/threshold at all (nothing keeps a debounce running)."""
    return value is None or threshold is None or value >= threshold


class _Debounce:
    """Condition true for `hold_s` -> latched; a reading back in the clear-zone restarts the timer."""

    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s
        self.since_s: float | None = None
        self.latched = False

    def update(self, now_s: float, condition: bool, clear: bool) -> bool:
        """Return True exactly when the latch sets."""
        if self.latched:
            return False
        if condition:
            if self.since_s is None:
                self.since_s = now_s
            if now_s - self.since_s >= self.hold_s - 1e-9:
                self.latched = True
                return True
        elif clear:
            self.since_s = None
        return False

    def reset(self) -> None:
        self.since_s = None
        self.latched = False
