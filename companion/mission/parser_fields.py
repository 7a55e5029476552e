"""Reading and range-checking a mission element's attributes, with errors naming the line and field
(`companion.mission.parser`, step 5)."""

from __future__ import annotations

import math
from typing import Any

from lxml import etree

from companion.errors import MissionError
from companion.mission.model import MissionLimits


class _Element:
    """Attribute access of one element with errors naming the line and field."""

    def __init__(self, elem: etree._Element, source: str) -> None:
        self.elem = elem
        self.tag = str(elem.tag)
        line: Any = elem.sourceline
        self.line = int(line) if isinstance(line, int) and line > 0 else 1
        self.source = source

    def error(self, attribute: str | None, message: str) -> MissionError:
        field = f"{self.tag}.{attribute}" if attribute else self.tag
        return MissionError(f"{self.source}:{self.line}: {field}: {message}")

    def has(self, attribute: str) -> bool:
        return self.elem.get(attribute) is not None

    def text(self, attribute: str) -> str | None:
        value = self.elem.get(attribute)
        return None if value is None else str(value).strip()

    def number(self, attribute: str) -> float | None:
        raw = self.text(attribute)
        if raw is None:
            return None
        try:
            value = float(raw)
        except ValueError:
            raise self.error(attribute, f"'{raw[:40]}' is not a number") from None
        if not math.isfinite(value):
            raise self.error(attribute, f"'{raw[:40]}...' is out of the floating-point range")
        return value

    def number_or(self, attribute: str, default: float) -> float:
        value = self.number(attribute)
        return default if value is None else value

    def required(self, attribute: str) -> float:
        value = self.number(attribute)
        if value is None:
            raise self.error(attribute, "required attribute is missing")
        return value

    def check(self, attribute: str, ok: bool, message: str) -> None:
        if not ok:
            raise self.error(attribute, message)


class _Checker:
    """Range checks shared by the header and the actions."""

    def __init__(self, limits: MissionLimits) -> None:
        self.limits = limits

    def speed(self, e: _Element, value: float, attribute: str = "speed") -> float:
        e.check(attribute, value > 0.0, f"{value:g} m/s must be > 0 m/s")
        e.check(
            attribute,
            value <= self.limits.max_speed_m_s,
            f"{value:g} m/s exceeds the vehicle limit {self.limits.max_speed_m_s:g} m/s",
        )
        return value

    def timeout(self, e: _Element, value: float, attribute: str = "timeout") -> float:
        e.check(attribute, value > 0.0, f"{value:g} s must be > 0 s")
        e.check(
            attribute,
            value <= self.limits.max_timeout_s,
            f"{value:g} s exceeds the limit {self.limits.max_timeout_s:g} s",
        )
        return value

    def threshold(self, e: _Element, value: float, attribute: str = "threshold") -> float:
        lo, hi = self.limits.min_threshold_m, self.limits.max_threshold_m
        e.check(attribute, lo <= value <= hi, f"{value:g} m is outside the allowed range {lo:g}..{hi:g} m")
        return value

    def yaw_threshold_deg(self, e: _Element, value_deg: float, attribute: str = "yaw-threshold") -> float:
        lo = math.degrees(self.limits.min_yaw_threshold_rad)
        hi = math.degrees(self.limits.max_yaw_threshold_rad)
        e.check(
            attribute, lo - 1e-9 <= value_deg <= hi + 1e-9,
            f"{value_deg:g} deg is outside the allowed range {lo:g}..{hi:g} deg",
        )
        return math.radians(value_deg)

    def height(self, e: _Element, value: float, attribute: str, label: str | None = None) -> float:
        """Check a height above home / the rack plane (m, up); `label` describes it in messages."""
        lo, hi = self.limits.min_height_m, self.limits.ceiling_m
        label = label if label is not None else f"height {value:g} m"
        e.check(attribute, value <= hi, f"{label} is above the ceiling {hi:g} m")
        e.check(attribute, value >= lo, f"{label} is below the minimum flight height {lo:g} m")
        return value

    def horizontal(self, e: _Element, value: float, attribute: str) -> float:
        hi = self.limits.max_horizontal_m
        e.check(attribute, abs(value) <= hi, f"{value:g} m is outside the geofence +-{hi:g} m")
        return value

    def yaw_deg(self, e: _Element, value_deg: float, attribute: str = "yaw") -> float:
        e.check(attribute, abs(value_deg) <= 360.0, f"{value_deg:g} deg is outside -360..360 deg")
        return math.radians(value_deg)
