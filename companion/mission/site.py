"""Goal positions of a mission against the site's NED geofence, before flight (pure).

`check_geofence(mission)` raises `MissionError` ("SOURCE:LINE: element.attribute: message",
the parser's format) for the first goal that lies outside ``mission.limits``'s geofence box.
The parser calls it last, so `companion mission validate --config`, the control API's upload
check and the daemon's start all refuse such a mission with the same line.

What a goal fixes before flight, and so what is checked:
- NED gotoxy (x north, y east): the horizontal point; gotoz z: the NED z.
- rack gotoxy: the horizontal NED point of rack (x, y) at every height the vehicle may have
  then (rack z from `min_height_m` to `ceiling_m`: both ends inside the box means the
  whole segment is, the box being convex).
- rack gotoz z: the NED z, when the rack's z axis is vertical (its x, y are the vehicle's).
- servo (with a declared `<rack>`): the full NED goal point.
Heights above home (takeoff, gotoz height) and `home` depend on where the vehicle takes off:
the ceiling check (parser) bounds them, the geofence is not checked for them here.
"""

from __future__ import annotations

import numpy as np

from companion.checks import FloatArray
from companion.errors import MissionError
from companion.geometry.frames import default_T_ned_rack
from companion.mission.model import Frame, GotoXY, GotoZ, Mission, MissionLimits, Servo

__all__ = ["check_geofence", "limits_T_ned_rack"]

_AXES = ("north", "east", "down")
_VERTICAL_TOL = 1e-9


def limits_T_ned_rack(limits: MissionLimits) -> FloatArray:
    """The 4x4 rack placement of `limits` (the default alignment when it has none)."""
    if limits.T_ned_rack is None:
        return default_T_ned_rack()
    return np.asarray(limits.T_ned_rack, dtype=np.float64).reshape(4, 4)


def _fence_text(lo: FloatArray, hi: FloatArray, axes: tuple[int, ...]) -> str:
    return ", ".join(f"{_AXES[k]} {lo[k]:g}..{hi[k]:g}" for k in axes)


def _outside(p_ned: FloatArray, lo: FloatArray, hi: FloatArray, axes: tuple[int, ...]) -> tuple[int, list[int]]:
    """The first of the points (N, 3) outside the box on an axis of `axes` and those axes, or (-1, [])."""
    cols = list(axes)
    out = (p_ned[:, cols] < lo[cols] - 1e-9) | (p_ned[:, cols] > hi[cols] + 1e-9)
    rows = np.flatnonzero(out.any(axis=1))
    if rows.size == 0:
        return -1, []
    row = int(rows[0])
    return row, [k for k, flag in zip(cols, out[row], strict=True) if flag]


def _point_text(p: FloatArray, axes: tuple[int, ...]) -> str:
    return "(" + ", ".join(f"{_AXES[k]} {p[k]:.3g}" for k in axes) + ") m"


def check_geofence(mission: Mission) -> None:
    """Raise `MissionError` naming line and attribute for the first goal outside the geofence (see module doc)."""
    limits = mission.limits
    if limits.geofence_min_ned_m is None or limits.geofence_max_ned_m is None:
        return
    lo = np.asarray(limits.geofence_min_ned_m, dtype=np.float64)
    hi = np.asarray(limits.geofence_max_ned_m, dtype=np.float64)
    T = limits_T_ned_rack(limits)
    rack_z_vertical = bool(np.all(np.abs(T[2, :2]) < _VERTICAL_TOL))
    for action in mission.actions:
        where = f"{mission.source_name}:{action.line}: {action.tag}"
        points: FloatArray | None = None
        axes: tuple[int, ...] = ()
        attribute = ""
        if isinstance(action, GotoXY):
            attribute, axes = "x/y", (0, 1)
            if mission.frame is Frame.NED:
                points = np.array([[action.x_m, action.y_m, 0.0]])
            else:
                p_rack = np.array([[action.x_m, action.y_m, limits.min_height_m, 1.0],
                                   [action.x_m, action.y_m, limits.ceiling_m, 1.0]])
                points = (p_rack @ T.T)[:, :3]
        elif isinstance(action, GotoZ) and action.z_m is not None:
            attribute, axes = "z", (2,)
            if mission.frame is Frame.NED:
                points = np.array([[0.0, 0.0, action.z_m]])
            elif rack_z_vertical:
                points = np.array([[0.0, 0.0, T[2, 2] * action.z_m + T[2, 3]]])
        elif isinstance(action, Servo) and mission.rack is not None:
            attribute, axes = "y/height", (0, 1, 2)
            rack = mission.rack
            p_rack = np.array([rack.pipe_axis_x_m(action.pipe), action.y_m,
                               rack.pipe_top_z_m(action.pipe) + action.height_m, 1.0])
            points = (T @ p_rack)[None, :3]
        if points is None:
            continue
        row, bad = _outside(points, lo, hi, axes)
        if bad:
            frame = "" if mission.frame is Frame.NED and not isinstance(action, Servo) else " in NED"
            raise MissionError(
                f"{where}.{attribute}: goal{frame} {_point_text(points[row], axes)} is outside the geofence "
                f"({_fence_text(lo, hi, tuple(bad))} m, safety.geofence_min_ned_m/geofence_max_ned_m)"
            )
