"""`companion sim --start-error H,YAW`: start the vehicle away from where the configuration says.

In the field nobody surveys the take-off pose: the drone is put down "somewhere near the rack". The
simulator's configuration says where the vehicle boots (NED origin, heading 0: over the rack's start,
see companion/data/sim_default.toml); with a start error the fake autopilot boots it at a seeded
random pose up to `horizontal_m` metres (uniform over the disc) and `yaw_deg` degrees (uniform) from
there, and the daemon is handed only the configured start as its hint (`DaemonOptions.initial_T_ned_body`),
so it has to find the rack in the image (issue #16). `--seed-true-pose` hands it the true start
instead, for the runs that test something else and need the tracker locked from the first frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError
from companion.geometry import frames, se3

__all__ = ["StartError", "StartPose", "offset_lla", "parse_start_error", "start_hint", "start_pose"]

EARTH_RADIUS_M = 6378137.0  # WGS-84 equatorial radius: metres to degrees near the origin


@dataclass(frozen=True)
class StartError:
    """Largest start error: horizontal offset (m) and heading (deg)."""

    horizontal_m: float = 0.0
    yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("horizontal_m", "yaw_deg"):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v < 0:
                raise InputError(f"--start-error: {name} must be a finite number >= 0, got {v}")
        if self.yaw_deg > 180.0:
            raise InputError(f"--start-error: yaw_deg must be <= 180, got {self.yaw_deg}")

    def text(self) -> str:
        return f"{self.horizontal_m:g},{self.yaw_deg:g}"


@dataclass(frozen=True)
class StartPose:
    """Where the vehicle boots: NED north, east (m) on z = 0 and heading (rad)."""

    north_m: float
    east_m: float
    yaw_rad: float

    @property
    def T_ned_body(self) -> FloatArray:
        """The body pose at rest (level) in NED, 4x4."""
        return se3.make(frames.rotation_from_euler_zyx(0.0, 0.0, self.yaw_rad),
                        np.array([self.north_m, self.east_m, 0.0]))


def parse_start_error(text: str) -> StartError:
    """``METRES,DEGREES`` (e.g. ``1.0,30``) -> `StartError`; raises `InputError` naming the problem."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 2:
        raise InputError(f"--start-error {text!r}: expected METRES,DEGREES, e.g. 1.0,30")
    try:
        h, y = float(parts[0]), float(parts[1])
    except ValueError:
        raise InputError(f"--start-error {text!r}: METRES and DEGREES must be numbers") from None
    return StartError(h, y)


def start_pose(error: StartError, seed: int, nominal: StartPose | None = None) -> StartPose:
    """The seeded true start: `nominal` (default: the origin, heading 0) moved by a random horizontal
    offset (uniform over the disc of radius `error.horizontal_m`) and turned by a random heading
    error (uniform within ±`error.yaw_deg`). The same seed gives the same pose."""
    base = nominal or StartPose(0.0, 0.0, 0.0)
    rng = np.random.default_rng([int(seed), 16])
    r = error.horizontal_m * math.sqrt(float(rng.uniform()))
    bearing = float(rng.uniform(-math.pi, math.pi))
    dyaw = math.radians(error.yaw_deg) * float(rng.uniform(-1.0, 1.0))
    return StartPose(base.north_m + r * math.cos(bearing), base.east_m + r * math.sin(bearing),
                     float(frames.wrap_angle(base.yaw_rad + dyaw)))


def start_hint(true_start: StartPose, nominal: StartPose | None = None, seed_true_pose: bool = False) -> FloatArray:
    """The start pose the daemon is given: the configured one, or the true one with `seed_true_pose`."""
    return true_start.T_ned_body if seed_true_pose else (nominal or StartPose(0.0, 0.0, 0.0)).T_ned_body


def offset_lla(origin_deg: tuple[float, float, float], north_m: float, east_m: float) -> tuple[float, float, float]:
    """(lat deg, lon deg, alt m) `north_m`, `east_m` from `origin_deg` (flat earth: metres around the origin)."""
    lat, lon, alt = (float(v) for v in origin_deg)
    dlat = math.degrees(north_m / EARTH_RADIUS_M)
    dlon = math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat))))
    return lat + dlat, lon + dlon, alt
