"""The validated mission: limits, rack layout, header and frozen action records (SI units, radians).

Everything here is produced by `companion.mission.parser` from a mission XML file;
degrees exist only in the file. A `Mission` is immutable and complete: the parser
either returns one that passed the schema and every range check, or raises
`MissionError` naming the line and field.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, fields
from typing import ClassVar

from companion.errors import InputError

__all__ = [
    "Action",
    "Frame",
    "GotoXY",
    "GotoZ",
    "Home",
    "Hover",
    "Land",
    "Mission",
    "MissionLimits",
    "RackLayout",
    "Servo",
    "TakePhoto",
    "Takeoff",
]


class Frame(enum.StrEnum):
    """Frame of a mission's gotoxy/gotoz coordinates."""

    NED = "ned"  # autopilot local frame: x north, y east, z down (m)
    RACK = "rack"  # pipe-rack frame: pipes along +y on z = 0, z up (m)


_SITE_FIELDS = ("geofence_min_ned_m", "geofence_max_ned_m", "T_ned_rack")


@dataclass(frozen=True)
class MissionLimits:
    """Vehicle and site limits a mission is checked against before flight.

    max_speed_m_s: highest speed an action may ask for (m/s).
    ceiling_m: highest allowed height above home (NED missions) or above the rack support
        plane z = 0 (rack missions and servo goals) (m).
    min_height_m: lowest height a takeoff/gotoz/servo goal may ask for (m); landing is `land`.
    max_horizontal_m: |x| and |y| bound of every goal coordinate (m): a coarse geofence.
    max_timeout_s, max_hover_s: upper bounds of action timeouts and hover durations (s).
    min_threshold_m, max_threshold_m: allowed range of position thresholds (m).
    min_yaw_threshold_rad, max_yaw_threshold_rad: allowed range of yaw thresholds (rad).
    max_settle_s: upper bound of the settle time a goal must be held (s).
    max_actions: most actions in one mission.
    geofence_min_ned_m, geofence_max_ned_m: the configured NED box (m, the safety manager's
        ``safety.geofence_*``) every goal position must lie in, or None (no box).
    T_ned_rack: the rack placement (4x4 row-major, 16 numbers) rack-frame goals are mapped to
        NED with for the geofence check; None = `frames.default_T_ned_rack()`.
    """

    max_speed_m_s: float = 1.0
    ceiling_m: float = 10.0
    min_height_m: float = 0.2
    max_horizontal_m: float = 100.0
    max_timeout_s: float = 3600.0
    max_hover_s: float = 3600.0
    min_threshold_m: float = 0.02
    max_threshold_m: float = 5.0
    min_yaw_threshold_rad: float = math.radians(0.5)
    max_yaw_threshold_rad: float = math.radians(90.0)
    max_settle_s: float = 30.0
    max_actions: int = 1000
    geofence_min_ned_m: tuple[float, float, float] | None = None
    geofence_max_ned_m: tuple[float, float, float] | None = None
    T_ned_rack: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name in _SITE_FIELDS:
                continue
            value = getattr(self, f.name)
            if not math.isfinite(float(value)) or value <= 0:
                raise InputError(f"MissionLimits.{f.name} must be finite and > 0, got {value!r}")
        if self.min_height_m >= self.ceiling_m:
            raise InputError("MissionLimits.min_height_m must be below ceiling_m")
        if self.min_threshold_m > self.max_threshold_m:
            raise InputError("MissionLimits.min_threshold_m must not exceed max_threshold_m")
        if self.min_yaw_threshold_rad > self.max_yaw_threshold_rad:
            raise InputError("MissionLimits.min_yaw_threshold_rad must not exceed max_yaw_threshold_rad")
        lo, hi = self.geofence_min_ned_m, self.geofence_max_ned_m
        if (lo is None) != (hi is None):
            raise InputError("MissionLimits.geofence_min_ned_m / geofence_max_ned_m: give both or neither")
        if lo is not None and hi is not None:
            if len(lo) != 3 or len(hi) != 3 or not all(math.isfinite(v) for v in (*lo, *hi)):
                raise InputError("MissionLimits.geofence_min_ned_m / geofence_max_ned_m: three finite numbers each")
            if any(a >= b for a, b in zip(lo, hi, strict=True)):
                raise InputError("MissionLimits.geofence_min_ned_m must be below geofence_max_ned_m on every axis")
        if self.T_ned_rack is not None and (
            len(self.T_ned_rack) != 16 or not all(math.isfinite(v) for v in self.T_ned_rack)
        ):
            raise InputError("MissionLimits.T_ned_rack: 16 finite numbers (4x4 row-major)")


@dataclass(frozen=True)
class RackLayout:
    """Parallel pipes of a rack in the rack frame (the paper's model, as in `RackModel.parallel`).

    radii_m[k] is the radius of pipe k+1 (m); gaps_m[k] the surface-to-surface gap between
    pipe k+1 and pipe k+2 (m); pipes rest on z = 0, pipe 1's left surface is at x = 0, and they
    run along +y from y = 0 to y = length_m.
    """

    radii_m: tuple[float, ...]
    gaps_m: tuple[float, ...]
    length_m: float

    def __post_init__(self) -> None:
        if not self.radii_m:
            raise InputError("RackLayout.radii_m: at least one pipe")
        if len(self.gaps_m) != len(self.radii_m) - 1:
            raise InputError("RackLayout.gaps_m: expected one gap fewer than pipes")
        if any(not (math.isfinite(r) and r > 0) for r in self.radii_m):
            raise InputError("RackLayout.radii_m: radii must be finite and > 0")
        if any(not (math.isfinite(g) and g >= 0) for g in self.gaps_m):
            raise InputError("RackLayout.gaps_m: gaps must be finite and >= 0")
        if not (math.isfinite(self.length_m) and self.length_m > 0):
            raise InputError("RackLayout.length_m must be finite and > 0")

    @property
    def count(self) -> int:
        """Number of pipes."""
        return len(self.radii_m)

    def _check_index(self, pipe: int) -> int:
        if not 1 <= pipe <= self.count:
            raise InputError(f"pipe: index {pipe} outside 1..{self.count}")
        return pipe - 1

    def pipe_axis_x_m(self, pipe: int) -> float:
        """x of the axis of pipe `pipe` (1-based) in the rack frame (m)."""
        k = self._check_index(pipe)
        x = sum(2.0 * self.radii_m[j] + self.gaps_m[j] for j in range(k))
        return x + self.radii_m[k]

    def pipe_top_z_m(self, pipe: int) -> float:
        """z of the top of pipe `pipe` (1-based) in the rack frame (m): its diameter."""
        return 2.0 * self.radii_m[self._check_index(pipe)]


@dataclass(frozen=True, kw_only=True)
class _ActionBase:
    """Fields every action has: source line, id (unique in the mission) and timeout (s)."""

    line: int
    id: str
    timeout_s: float


@dataclass(frozen=True, kw_only=True)
class Takeoff(_ActionBase):
    """Arm if needed and take off to height_m above home (m); done when within threshold_m."""

    tag: ClassVar[str] = "takeoff"
    height_m: float
    threshold_m: float


@dataclass(frozen=True, kw_only=True)
class GotoXY(_ActionBase):
    """Fly to (x_m, y_m) in the mission frame at the current height.

    yaw_rad: goal heading (rad; NED: from north toward east; rack: from rack +y toward +x),
    None keeps the heading at the start of the action.
    """

    tag: ClassVar[str] = "gotoxy"
    x_m: float
    y_m: float
    yaw_rad: float | None
    speed_m_s: float
    threshold_m: float
    yaw_threshold_rad: float


@dataclass(frozen=True, kw_only=True)
class GotoZ(_ActionBase):
    """Change height keeping x, y and heading.

    Exactly one of z_m (a coordinate of the mission frame: NED z is down, rack z is up) and
    height_m (above home, up) is set.
    """

    tag: ClassVar[str] = "gotoz"
    z_m: float | None
    height_m: float | None
    speed_m_s: float
    threshold_m: float


@dataclass(frozen=True, kw_only=True)
class TakePhoto(_ActionBase):
    """Hold position and take one photo with the named camera."""

    tag: ClassVar[str] = "take-photo"
    camera: str


@dataclass(frozen=True, kw_only=True)
class Hover(_ActionBase):
    """Hold the position reached for duration_s seconds."""

    tag: ClassVar[str] = "hover"
    duration_s: float


@dataclass(frozen=True, kw_only=True)
class Servo(_ActionBase):
    """Servo to a pose relative to the rack: height_m above the top of pipe `pipe` (1-based),
    at y_m along the pipes, heading yaw_rad relative to the rack (from +y toward +x)."""

    tag: ClassVar[str] = "servo"
    pipe: int
    height_m: float
    y_m: float
    yaw_rad: float
    speed_m_s: float
    threshold_m: float
    yaw_threshold_rad: float


@dataclass(frozen=True, kw_only=True)
class Home(_ActionBase):
    """Fly back above the home position (horizontal) at the current height and heading."""

    tag: ClassVar[str] = "home"
    speed_m_s: float
    threshold_m: float


@dataclass(frozen=True, kw_only=True)
class Land(_ActionBase):
    """Land where the vehicle is (the autopilot's land mode); done when landed."""

    tag: ClassVar[str] = "land"


Action = Takeoff | GotoXY | GotoZ | TakePhoto | Hover | Servo | Home | Land


@dataclass(frozen=True)
class Mission:
    """A validated mission.

    name: mission name; frame: frame of gotoxy/gotoz coordinates; timeout_s: default action
    timeout (s); speed_m_s, threshold_m, yaw_threshold_rad: defaults of the motion actions;
    settle_s: how long a goal must be held within its thresholds to count as reached (s);
    limits: the limits it was validated against; rack: the declared rack layout or None;
    actions: the actions in order; source_name: file name used in messages.
    """

    name: str
    frame: Frame
    timeout_s: float
    speed_m_s: float
    threshold_m: float
    yaw_threshold_rad: float
    settle_s: float
    limits: MissionLimits
    rack: RackLayout | None
    actions: tuple[Action, ...]
    source_name: str = "<string>"

    def __len__(self) -> int:
        return len(self.actions)

    def summary(self) -> str:
        """One line: name, frame and the action count."""
        return f"mission '{self.name}' ({self.frame.value} frame): {len(self.actions)} actions"
