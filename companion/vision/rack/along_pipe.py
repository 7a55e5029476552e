"""How well the rack tracker knows its position along the pipes (`RackTracker`'s reported covariance).

The limbs of parallel pipes do not move when the camera slides along them. Along the pipes the
pose comes from texture and ground points, which are tracked from frame to frame and therefore
only carry the position forward (odometry: they hold it, with drift, but never correct it), from
the motion prediction when there are none, and from edges that cross the pipes' direction (a
crossing pipe, a pipe's end), which do correct it. The solver's covariance conditions every frame
on the previous pose, so it says "1 cm" along the pipes while the pose slides by decimetres on a
stretch without texture (`companion sim --appearance field`, 2026-11-26). `along_pipe_std` keeps
the standard deviation of the along-pipe position across frames, the way a Kalman filter with a
one-dimensional state would, and the tracker reports at least that much along the pipes.
"""

from __future__ import annotations

import math

import numpy as np

from companion.checks import FloatArray

__all__ = ["CROSSING_INFO_RATIO", "along_pipe_std", "edge_information_along", "edges_see_along", "widen_along"]

# Edge rows observe the along-pipe position when their information along the pipes is at least this fraction
# of theirs across them. Parallel limbs give none at all; on the stress bench's §V rack, with the crossing
# pipe in view, the ratio was 0.35-0.89 (quartile to 95th percentile), so the threshold is not critical.
CROSSING_INFO_RATIO = 0.05


def edge_information_along(A_edge_m: FloatArray, w_edge: FloatArray, e_cam: FloatArray) -> float:
    """Information of the edge rows about a translation along `e_cam` (unit, camera frame), in the
    solver's units (rows in px, weights as solved): sum of w (a . e)^2 over the rows' translation
    Jacobians `A_edge_m` (N, 3). Zero for the limbs of pipes parallel to `e_cam`."""
    if A_edge_m.shape[0] == 0:
        return 0.0
    d = A_edge_m @ e_cam
    return float(np.sum(w_edge * d * d))


def edges_see_along(A_edge_m: FloatArray, w_edge: FloatArray, R_rack_cam: FloatArray) -> bool:
    """Whether the edge rows (translation Jacobians `A_edge_m` (N, 3), camera frame, weights `w_edge` (N,))
    observe the position along the pipes (rack y) as well as across them (rack x): a crossing pipe or a pipe's
    end in view. `R_rack_cam` the attitude."""
    across = edge_information_along(A_edge_m, w_edge, R_rack_cam[0, :])
    along = edge_information_along(A_edge_m, w_edge, R_rack_cam[1, :])
    return across > 0.0 and along >= CROSSING_INFO_RATIO * across


def along_pipe_std(
    std_prev_m: float,
    dt_s: float,
    moved_along_m: float,
    held_by_points: bool,
    edge_var_m2: float,
    unobserved_speed_m_s: float,
    points_drift: float,
) -> float:
    """The along-pipe standard deviation (m) of this frame's pose.

    Prediction: the previous `std_prev_m` grows by `unobserved_speed_m_s` * `dt_s` when nothing
    holds the along-pipe position (the vehicle may move at that speed unseen), or by
    `points_drift` * |`moved_along_m`| when texture/ground points carry it from the previous frame
    (`held_by_points`). Update: with the edges' own variance along the pipes `edge_var_m2` (inf when
    they do not observe it) as an independent measurement.
    """
    grow = unobserved_speed_m_s * max(dt_s, 0.0) if not held_by_points else points_drift * abs(moved_along_m)
    std_pred = std_prev_m + grow
    if not math.isfinite(edge_var_m2) or edge_var_m2 <= 0.0:
        return std_pred
    return 1.0 / math.sqrt(1.0 / std_pred**2 + 1.0 / edge_var_m2)


def widen_along(covariance: FloatArray, e_cam: FloatArray, std_m: float) -> FloatArray:
    """`covariance` (6x6, translation first, camera frame) with at least `std_m` of standard
    deviation along the unit direction `e_cam`: the missing variance is added as a rank-one term,
    so every other direction keeps its variance."""
    c = float(e_cam @ covariance[:3, :3] @ e_cam)
    extra = std_m * std_m - c
    if extra <= 0.0:
        return covariance
    out = covariance.copy()
    out[:3, :3] += extra * np.outer(e_cam, e_cam)
    return out
