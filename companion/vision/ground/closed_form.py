"""The paper's closed forms for the planar roto-translation between two frames (eqs. 14-25).

Both take matched ground points a_i (frame k) and b_i (frame k+1), each expressed in the level
frame of its own time and rotated by the yaw estimate at time k (a_i = R(yaw_k) q_k,i,
b_i = R(yaw_k) q_k+1,i, NED-aligned, metres), and solve

    a_i = d + R(dyaw) b_i      for d = (dx, dy) (NED, metres) and dyaw (rad, about down).

GEN (eq. 20) estimates cos(dyaw) and sin(dyaw) as two free unknowns; SMA (eq. 25) assumes
cos = 1, sin = dyaw. The sums are the paper's script letters (eq. 19):

    A = sum bx, B = -sum by, C = sum |b|^2, D = sum ax, E = sum ay,
    F = sum (ax bx + ay by), G = sum (ay bx - ax by).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray
from companion.errors import TrackingError


@dataclass(frozen=True)
class PaperSums:
    """The script-letter sums of eq. 19 and the point count n."""

    n: int
    A: float
    B: float
    C: float
    D: float
    E: float
    F: float
    G: float

    @property
    def denominator(self) -> float:
        """A^2 + B^2 - n C, the common denominator of eqs. 20 and 25 (< 0 unless degenerate)."""
        return self.A * self.A + self.B * self.B - self.n * self.C


def paper_sums(a_m: FloatArray, b_m: FloatArray) -> PaperSums:
    """Sums of eq. 19 for matched points a (N, 2) and b (N, 2)."""
    ax, ay = a_m[:, 0], a_m[:, 1]
    bx, by = b_m[:, 0], b_m[:, 1]
    return PaperSums(
        n=int(a_m.shape[0]),
        A=float(bx.sum()),
        B=float(-by.sum()),
        C=float(bx @ bx + by @ by),
        D=float(ax.sum()),
        E=float(ay.sum()),
        F=float(ax @ bx + ay @ by),
        G=float(ay @ bx - ax @ by),
    )


def _check(sums: PaperSums) -> float:
    den = sums.denominator
    # The denominator is -n * sum |b - mean b|^2: it vanishes when all points coincide.
    if sums.n < 2 or not abs(den) > 1e-12 * max(1.0, sums.n * sums.C):
        raise TrackingError("closed form: fewer than two distinct ground points")
    return den


def solve_gen(a_m: FloatArray, b_m: FloatArray) -> FloatArray:
    """GEN, eq. 20: (dx, dy, cos dyaw, sin dyaw) with cos and sin estimated separately."""
    s = paper_sums(a_m, b_m)
    den = _check(s)
    A, B, C, D, E, F, G, n = s.A, s.B, s.C, s.D, s.E, s.F, s.G, s.n
    return (
        np.array(
            [
                A * F - C * D + B * G,
                A * G - C * E - B * F,
                A * D - n * F - B * E,
                A * E - n * G + B * D,
            ]
        )
        / den
    )


def solve_sma(a_m: FloatArray, b_m: FloatArray) -> FloatArray:
    """SMA, eq. 25: (dx, dy, dyaw) with cos dyaw = 1 and sin dyaw = dyaw."""
    s = paper_sums(a_m, b_m)
    den = _check(s)
    A, B, C, D, E, G, n = s.A, s.B, s.C, s.D, s.E, s.G, s.n
    dx = (-A * B * E + A * A * D - A**3 - A * B * B + n * A * C + n * B * G - n * C * D) / n
    dy = (-A * B * D + A * A * B + B**3 + E * B * B - n * B * C + n * A * G - n * C * E) / n
    dyaw = B * D + A * E - n * G
    return np.array([dx, dy, dyaw]) / den


def gen_to_increment(solution: FloatArray) -> FloatArray:
    """(dx, dy, dyaw) from a GEN solution (dx, dy, c, s): dyaw = atan2(s, c)."""
    return np.array([solution[0], solution[1], np.arctan2(solution[3], solution[2])])
