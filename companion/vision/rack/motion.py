"""Image motion fields of the SE(3) generators and of the gap parameters, and the IRLS solve.

Pose perturbation convention (used everywhere in the rack tracker): a right perturbation in
the camera frame, twist δ = (v, w) (m, rad):  T_rack_cam' = T_rack_cam @ se3.exp(δ).
A point fixed in the rack frame then moves in the camera frame as
    p_cam' = exp(-δ) p_cam ≈ p_cam - v + p_cam × w,
so d p_cam / d δ = [-I, hat(p_cam)] and the image motion field of generator i (the paper's
ξ_i, eq. 8-9) is J_uv_pcam @ column i. Projected on a measurement's unit normal n it gives
σ_i = ξ_iᵀ n (eq. 15). A cumulative gap d̄_k moves the points of parallel pipe k+1 along the
rack +x axis (eq. 23-26): d p_cam / d d̄_k = R_cam_rack e_x.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError
from companion.vision.rack.rack_jit import kernels


def pose_jacobian(J_uv_pcam: FloatArray, p_cam: FloatArray) -> FloatArray:
    """Image motion fields (N, 2, 6) of the six generators (right perturbation, cam frame)."""
    ks = kernels()
    if ks is not None and J_uv_pcam.dtype == np.float64 and p_cam.dtype == np.float64:
        return np.asarray(ks.pose_jacobian(J_uv_pcam, p_cam))  # the same arithmetic, compiled (`rack_jit.py`)
    x, y, z = p_cam[:, None, 0], p_cam[:, None, 1], p_cam[:, None, 2]
    J0, J1, J2 = J_uv_pcam[:, :, 0], J_uv_pcam[:, :, 1], J_uv_pcam[:, :, 2]
    # J @ [-I, hat(p)] with hat(p) = [[0, -z, y], [z, 0, -x], [-y, x, 0]], column by column.
    out = np.empty((p_cam.shape[0], 2, 6))
    out[:, :, :3] = -J_uv_pcam
    out[:, :, 3] = J1 * z - J2 * y
    out[:, :, 4] = J2 * x - J0 * z
    out[:, :, 5] = J0 * y - J1 * x
    return out


def gap_jacobian(J_uv_pcam: FloatArray, R_cam_rack: FloatArray) -> FloatArray:
    """Image motion (N, 2) of a point when its pipe shifts along rack +x (per metre)."""
    return np.asarray(np.einsum("nij,j->ni", J_uv_pcam, R_cam_rack[:, 0]))


def median_1d(a: FloatArray) -> float:
    """`np.median` of a non-empty 1-D float array (the same value, NaN if any) with one partition."""
    ks = kernels()
    if ks is not None and a.dtype == np.float64 and a.ndim == 1:
        return float(ks.median(a))  # the same value, compiled (`rack_jit.py`)
    n = a.size
    h = n // 2
    p = np.partition(a, (h - 1, h, n - 1) if n % 2 == 0 else (h, n - 1))
    if np.isnan(p[-1]):
        return float("nan")
    return float(p[h]) if n % 2 else float((p[h - 1] + p[h]) / 2.0)


def strength_weights(strength: FloatArray, power: float, lo: float = 0.05, hi: float = 4.0) -> FloatArray:
    """Weights (N,) of edge rows by their gradient strength (N,) (grey levels): (strength / its median) ** power,
    clipped to [lo, hi]; ones when `power` is 0 or there are no rows.

    A limb's edge bias from the brightness structure beside it (the ground's texture, its shading) scales with
    the inverse of the limb's contrast (docs/acquire.md, "What one image allows"): weak limbs count less.
    """
    if power == 0.0 or strength.size == 0:
        return np.ones(strength.size)
    med = median_1d(strength)
    return np.asarray(np.clip((strength / max(med, 1e-6)) ** power, lo, hi))


def robust_weights(
    r: FloatArray, kind: str, nu_px: float, gate_px: float | None = None, max_scale_px: float | None = None
) -> FloatArray:
    """IRLS weights of residuals r (px).

    kind "paper": s(e) = 1 / (ν + |e|) (eq. 29); "tukey": Tukey biweight with c = 4.685 × the
    MAD scale (floored at ν / 2, capped at `max_scale_px` when given); "l2": ones. Residuals beyond
    `gate_px` get weight 0.
    """
    a = np.abs(r)
    if kind == "paper":
        w = 1.0 / (nu_px + a)
    elif kind == "tukey":
        scale = max(1.4826 * median_1d(a) if a.size else 0.0, 0.5 * nu_px)
        if max_scale_px is not None:
            # Half the rows on one coherent wrong edge (a paving joint beside every limb) make the MAD as wide
            # as their offset: the biweight then weighs them as inliers and the solve settles between the two.
            scale = min(scale, max_scale_px)
        c = 4.685 * scale
        w = np.where(a < c, (1.0 - (a / c) ** 2) ** 2, 0.0)
    elif kind == "l2":
        w = np.ones_like(a)
    else:
        raise InputError(f"robust: expected 'paper', 'tukey' or 'l2', got {kind!r}")
    if gate_px is not None:
        w = np.where(a <= gate_px, w, 0.0)
    return np.asarray(w, dtype=np.float64)


def gated_residual_variance(w: FloatArray, r_gate: FloatArray, r: FloatArray, gate_px: float, n_free: int) -> float:
    """Weighted residual variance sum(w r^2) / (rows - n_free) over the rows whose `r_gate` (px) lies within
    `gate_px` and whose weight `w` is not zero (at least one degree of freedom): the solver's residual scale
    (px^2 in the IRLS weights' units) without the far outliers a wide first search lets in."""
    inside = np.where(np.abs(r_gate) <= gate_px, w, 0.0)
    return float(inside @ (r * r)) / max(int(np.count_nonzero(inside)) - n_free, 1)


def solve_normal_equations(
    A: FloatArray,
    r: FloatArray,
    w: FloatArray,
    prior_information: FloatArray,
    anchor_information: FloatArray | None = None,
    anchor: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Weighted, damped least squares (eq. 16-18 and 27-28 with damping and a prior):

    minimise Σ w (r - A x)² + xᵀ diag(prior) x + (x - anchor)ᵀ diag(anchor_information) (x - anchor).
    Returns (x, H_data = Aᵀ W A, H = H_data + diag(prior) + diag(anchor_information)).
    """
    Aw = A * w[:, None]
    H_data = A.T @ Aw
    g = Aw.T @ r
    H = H_data + np.diag(prior_information)
    if anchor_information is not None and anchor is not None:
        H = H + np.diag(anchor_information)
        g = g + anchor_information * anchor
    try:
        x = np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(H, g, rcond=None)[0]
    return np.asarray(x), np.asarray(H_data), np.asarray(H)


def information_condition(H: FloatArray, basis: Any = None) -> float:
    """Condition number of the column-normalised information matrix (optionally in a subspace)."""
    M = H if basis is None else basis.T @ H @ basis
    d = np.sqrt(np.maximum(np.diag(M), 0.0))
    if np.any(d <= 1e-12):
        return float("inf")
    C = M / np.outer(d, d)
    ev = np.linalg.eigvalsh(C)
    if ev[0] <= 0.0:
        return float("inf")
    return float(ev[-1] / ev[0])


def gravity_rows(R_rack_cam: FloatArray, R_rack_cam_prior: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Residual (3,) and Jacobian (3, 6) of the gravity direction of an attitude prior.

    The rack's up axis seen in the camera frame is g = R_rack_camᵀ e_z; the prior's is
    g_p = R_rack_cam_priorᵀ e_z (only this direction is used: the prior's heading is ignored).
    Residual r = g_p - g (unitless, ≈ the tilt difference in rad); under the right perturbation
    R' = R exp(w), g' = exp(-w) g ≈ g + hat(g) w, so d g / d δ = [0, hat(g)] and the rows are
    r ≈ A δ with A = [0, hat(g)] (rank 2: rotations about g do not change it).
    """
    g = np.asarray(R_rack_cam, dtype=np.float64)[2, :]  # = R_rack_camᵀ e_z
    g_p = np.asarray(R_rack_cam_prior, dtype=np.float64)[2, :]
    A = np.zeros((3, 6))
    A[:, 3:] = [[0.0, -g[2], g[1]], [g[2], 0.0, -g[0]], [-g[1], g[0], 0.0]]
    return g_p - g, A
