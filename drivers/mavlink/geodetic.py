"""Flat-earth conversions between geodetic coordinates (degrees, metres AMSL) and local NED offsets (m)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from companion.checks import FloatArray

__all__ = ["EARTH_RADIUS_M", "geodetic_from_ned", "ned_from_geodetic"]

EARTH_RADIUS_M = 6378137.0


def ned_from_geodetic(
    lat_deg: float, lon_deg: float, alt_m: float, lat0_deg: float, lon0_deg: float, alt0_m: float
) -> FloatArray:
    """Flat-earth (equirectangular) NED offset (m) of a geodetic point from an origin; fine over a few km."""
    north = math.radians(lat_deg - lat0_deg) * EARTH_RADIUS_M
    east = math.radians(lon_deg - lon0_deg) * EARTH_RADIUS_M * math.cos(math.radians(lat0_deg))
    return np.array([north, east, alt0_m - alt_m], dtype=np.float64)


def geodetic_from_ned(p_ned_m: Any, lat0_deg: float, lon0_deg: float, alt0_m: float) -> tuple[float, float, float]:
    """Inverse of `ned_from_geodetic`: (lat_deg, lon_deg, alt_m)."""
    n, e, d = (float(x) for x in np.asarray(p_ned_m, dtype=np.float64).reshape(3))
    lat = lat0_deg + math.degrees(n / EARTH_RADIUS_M)
    lon = lon0_deg + math.degrees(e / (EARTH_RADIUS_M * math.cos(math.radians(lat0_deg))))
    return lat, lon, alt0_m - d
