"""Levenberg-Marquardt refinement of (dx, dy, dyaw) (paper eq. 26), hand-written, 3 parameters.

Residuals r_i = d + R(dyaw) b_i - a_i (N, 2), metres, NED-aligned (see `closed_form`).

Re-exports, by concern: `refine_rigid` (the rigid model and its LM loop), `refine_tilt_fields`
(first-order tilt/height warp fields as nuisance parameters), `tilt_reprojection` (exactly
tilt/height-corrected ground points) and `refine_exact_tilt` (the exact-tilt MAP refinement).
"""

from __future__ import annotations

from companion.vision.ground.refine_exact_tilt import _instrument_system as _instrument_system
from companion.vision.ground.refine_exact_tilt import _stacked_maps as _stacked_maps
from companion.vision.ground.refine_exact_tilt import refine_tilt_exact, residuals_and_jacobian_exact
from companion.vision.ground.refine_rigid import RefineResult, evaluate, refine, residuals_and_jacobian
from companion.vision.ground.refine_tilt_fields import (
    NuisanceResult,
    refine_with_nuisance,
    refine_with_tilt,
    residuals_and_jacobian_nuisance,
    residuals_and_jacobian_tilt,
    tilt_fields,
)
from companion.vision.ground.tilt_reprojection import _corrected_points as _corrected_points
from companion.vision.ground.tilt_reprojection import tilt_corrected_points

__all__ = [
    "NuisanceResult",
    "RefineResult",
    "evaluate",
    "refine",
    "refine_tilt_exact",
    "refine_with_nuisance",
    "refine_with_tilt",
    "residuals_and_jacobian",
    "residuals_and_jacobian_exact",
    "residuals_and_jacobian_nuisance",
    "residuals_and_jacobian_tilt",
    "tilt_corrected_points",
    "tilt_fields",
]
