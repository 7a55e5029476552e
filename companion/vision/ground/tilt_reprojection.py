"""Exact tilt and height correction of one frame's ground points, re-projected from its rays.

Rays at unit depth in the frame's (measured) level frame; points (N, 2) in metres in that level frame.
"""

from __future__ import annotations

import math

import numpy as np

from companion.checks import FloatArray
from companion.geometry import so3

# d omega / d (e_0, e_1): the level-frame rotation that undoes a tilt error with field coefficients
# (e_0, e_1) (`tilt_fields`: the points move by -omega_x field 0 + omega_y field 1 to first order).
_OMEGA_OF_E = np.array([[-1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])


def tilt_corrected_points(
    rays_level: FloatArray, height_m: float, nadir_level_m: FloatArray, e: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Ground points of one frame re-projected with a tilt and height correction, exactly.

    `rays_level` (N, 3): the frame's rays in its (measured) level frame at unit depth
    (`backproject.ground_rays_level`); `e` = (e_0, e_1, s): the rays are rotated by
    omega = (-e_0, e_1, 0) (so e_0, e_1 are the coefficients of `tilt_fields` 0 and 1 to first
    order) and the height scaled by (1 + s). The uniform shift of the camera nadir that the rotation
    causes is removed (it cannot be told from a translation; left in the data it telescopes
    between consecutive increments), so e = 0 gives nadir + h * ray[:2] and the first-order change
    is e_0 field 0 + e_1 field 1 + s field 2.
    Returns the points (N, 2), metres, and their Jacobian d points / d e (N, 2, 3).
    """
    omega = _OMEGA_OF_E @ e[:2]
    R = so3.exp(omega)
    M = so3.left_jacobian(omega) @ _OMEGA_OF_E  # (3, 2): d omega_eff / d (e_0, e_1)
    H = height_m * (1.0 + e[2])
    p = rays_level @ R.T
    nad = R[:, 2]
    pz = p[:, 2:3]
    u = p[:, :2] / pz - nad[:2] / nad[2]
    points = nadir_level_m + H * u
    J = np.empty((rays_level.shape[0], 2, 3))
    for j in range(2):
        dp = np.cross(M[:, j], p)  # d p / d e_j = (M e_j) x p
        dn = np.cross(M[:, j], nad)
        du = (dp[:, :2] * pz - p[:, :2] * dp[:, 2:3]) / (pz * pz) - (dn[:2] * nad[2] - nad[:2] * dn[2]) / nad[2] ** 2
        J[:, :, j] = H * du
    J[:, :, 2] = height_m * u
    return points, J


def _rotation_xy_rows(wx: float, wy: float) -> list[list[float]]:
    """Rodrigues rotation of the vector (wx, wy, 0) as nested lists, with scalar math (hot path)."""
    t2 = wx * wx + wy * wy
    if t2 < 1e-12:
        A, B = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        A, B = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    # W = hat((wx, wy, 0)); W^2 = w w^T - t2 I.
    return [
        [1.0 + B * (wx * wx - t2), B * wx * wy, A * wy],
        [B * wx * wy, 1.0 + B * (wy * wy - t2), -A * wx],
        [-A * wy, A * wx, 1.0 - B * t2],
    ]


def _corrected_stack(rays_level: FloatArray, heights_m: FloatArray, nadirs_m: FloatArray, e: FloatArray) -> FloatArray:
    """`tilt_corrected_points` of F frames at once, without the Jacobian (hot path): rays (F, N, 3),
    heights (F,), nadirs (F, 2), e (F, 3) -> points (F, N, 2)."""
    # The per-frame scalars with Python floats (the same IEEE operations as the array expressions
    # H = h (1 + s), offset = nadir - (H / R_22) R_:2,2).
    rows = []
    heights = []
    offsets = []
    for ef, h, nad in zip(e.tolist(), heights_m.tolist(), nadirs_m.tolist(), strict=True):
        Rf = _rotation_xy_rows(-ef[0], ef[1])
        Hf = h * (1.0 + ef[2])
        k = Hf / Rf[2][2]
        rows.append(Rf)
        heights.append([[Hf]])
        offsets.append([[nad[0] - k * Rf[0][2], nad[1] - k * Rf[1][2]]])
    R = np.array(rows)  # (F, 3, 3)
    p = rays_level @ np.transpose(R, (0, 2, 1))
    out: FloatArray = p[:, :, :2] * (np.array(heights) / p[:, :, 2:3]) + np.array(offsets)
    return out


def _corrected_points(rays_level: FloatArray, height_m: float, nadir_level_m: FloatArray, e: FloatArray) -> FloatArray:
    """`tilt_corrected_points` without the Jacobian (hot path)."""
    out: FloatArray = _corrected_stack(
        rays_level[None], np.array([height_m]), np.asarray(nadir_level_m)[None], np.asarray(e)[None]
    )[0]
    return out
