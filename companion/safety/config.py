"""The safety manager's configuration: thresholds, timeouts and gains, checked when built."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from companion.errors import ConfigError

__all__ = ["SafetyConfig"]


def _check_positive(cfg: Any, name: str, allow_none: bool = False) -> None:
    value = getattr(cfg, name)
    if value is None and allow_none:
        return
    if value is None or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"safety.{name}: must be a finite number > 0, got {value!r}")


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds, timeouts and gains of the safety behaviours (SI units; None disables a check).

    ceiling_m: highest allowed height above ground (m); climbing is limited to
        ceiling_gain_per_s * (ceiling_m - height) and the vehicle is pushed down above it.
    ceiling_hysteresis_m: the CEILING fault clears below ceiling_m - this (m).
    min_ceiling_clearance_m: smallest allowed distance to an overhead obstacle measured by an
        upward rangefinder (m); climbing limited like the ceiling.
    battery_low_v / battery_low_pct: land when below either for battery_low_debounce_s (s).
    battery_critical_v / battery_critical_pct: land now when below either for
        battery_critical_debounce_s (s).
    battery_hysteresis_v / battery_hysteresis_pct: a debounce restarts only once the reading is
        back above threshold + hysteresis.
    gcs_timeout_s: no GCS heartbeat for this long -> hover; gcs_land_timeout_s -> land.
        Only after a first GCS heartbeat was seen (a vehicle flown without a GCS is not "lost").
    vision_timeout_s: no fresh pose for this long -> stop poses, hover; vision_land_timeout_s -> land.
    vision_auto_resume_s: when set, a vision hover ends by itself after poses have been fresh for
        this long (s); None = only `operator_resume` ends it.
    gcs_auto_resume_s: when set, a GCS-loss hover (not a landing) ends by itself after GCS
        heartbeats have been back for this long (s); None = only `operator_resume` ends it.
    autopilot_timeout_s: no autopilot heartbeat for this long -> STOP_COMMANDS.
    geofence_min_ned_m / geofence_max_ned_m: NED box (m) or None; velocities toward a face are
        limited to geofence_gain_per_s * distance to it.
    watchdog_stale_s: `filter` blocks every command when the last `step` is older than this (s)
        or `step` never ran: commands only pass while the watchdog is alive.
    """

    ceiling_m: float = 10.0
    ceiling_hysteresis_m: float = 0.3
    ceiling_gain_per_s: float = 1.0
    min_ceiling_clearance_m: float | None = 1.0
    battery_low_v: float | None = 14.0
    battery_low_pct: float | None = 20.0
    battery_critical_v: float | None = 13.2
    battery_critical_pct: float | None = 8.0
    battery_low_debounce_s: float = 3.0
    battery_critical_debounce_s: float = 1.0
    battery_hysteresis_v: float = 0.2
    battery_hysteresis_pct: float = 2.0
    gcs_timeout_s: float | None = 5.0
    gcs_land_timeout_s: float | None = 30.0
    vision_timeout_s: float = 0.5
    vision_land_timeout_s: float | None = 10.0
    vision_auto_resume_s: float | None = None
    gcs_auto_resume_s: float | None = None
    autopilot_timeout_s: float = 3.0
    geofence_min_ned_m: tuple[float, float, float] | None = None
    geofence_max_ned_m: tuple[float, float, float] | None = None
    geofence_gain_per_s: float = 1.0
    watchdog_stale_s: float = 1.0

    def __post_init__(self) -> None:
        optional = {
            "min_ceiling_clearance_m", "battery_low_v", "battery_low_pct", "battery_critical_v",
            "battery_critical_pct", "gcs_timeout_s", "gcs_land_timeout_s", "vision_land_timeout_s",
            "vision_auto_resume_s", "gcs_auto_resume_s",
        }
        for f in fields(self):
            if f.name.startswith("geofence_") and f.name != "geofence_gain_per_s":
                continue
            _check_positive(self, f.name, allow_none=f.name in optional)
        for low, crit in (("battery_low_v", "battery_critical_v"), ("battery_low_pct", "battery_critical_pct")):
            lo, cr = getattr(self, low), getattr(self, crit)
            if lo is not None and cr is not None and cr > lo:
                raise ConfigError(f"safety.{crit}: {cr} must not exceed safety.{low} ({lo})")
        for hover, land in (("gcs_timeout_s", "gcs_land_timeout_s"), ("vision_timeout_s", "vision_land_timeout_s")):
            h, ld = getattr(self, hover), getattr(self, land)
            if h is not None and ld is not None and ld < h:
                raise ConfigError(f"safety.{land}: {ld} s must not be shorter than safety.{hover} ({h} s)")
        if (self.geofence_min_ned_m is None) != (self.geofence_max_ned_m is None):
            raise ConfigError("safety.geofence_min_ned_m / geofence_max_ned_m: give both or neither")
        if self.geofence_min_ned_m is not None and self.geofence_max_ned_m is not None:
            lo_arr = np.asarray(self.geofence_min_ned_m, dtype=np.float64)
            hi_arr = np.asarray(self.geofence_max_ned_m, dtype=np.float64)
            if lo_arr.shape != (3,) or hi_arr.shape != (3,) or not np.all(np.isfinite(lo_arr + hi_arr)):
                raise ConfigError("safety.geofence_min_ned_m / geofence_max_ned_m: three finite numbers each")
            if np.any(lo_arr >= hi_arr):
                raise ConfigError("safety.geofence_min_ned_m: every component must be below geofence_max_ned_m")
