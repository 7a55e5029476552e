"""Autopilot profiles: mode names, mode-change and takeoff parameters (ArduPilot copter, PX4).

Mode names are what the rest of the product speaks (`link.set_mode("GUIDED")`); the numbers on
the wire live here and nowhere else.

- ArduPilot copter: HEARTBEAT.custom_mode is the copter mode number; MAV_CMD_DO_SET_MODE takes
  param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 = mode number.
- PX4: HEARTBEAT.custom_mode packs ``main << 16 | sub << 24``; MAV_CMD_DO_SET_MODE takes
  param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 = main mode, param3 = sub mode.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from companion.errors import InputError

__all__ = [
    "ARDUPILOT_COPTER",
    "MAV_AUTOPILOT_ARDUPILOTMEGA",
    "MAV_AUTOPILOT_PX4",
    "PX4",
    "AutopilotProfile",
    "profile_for_autopilot",
    "profile_named",
]

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1

_ARDUCOPTER_MODES: dict[str, int] = {
    "STABILIZE": 0,
    "ACRO": 1,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "CIRCLE": 7,
    "LAND": 9,
    "DRIFT": 11,
    "SPORT": 13,
    "FLIP": 14,
    "AUTOTUNE": 15,
    "POSHOLD": 16,
    "BRAKE": 17,
    "THROW": 18,
    "AVOID_ADSB": 19,
    "GUIDED_NOGPS": 20,
    "SMART_RTL": 21,
    "FLOWHOLD": 22,
    "FOLLOW": 23,
    "ZIGZAG": 24,
    "SYSTEMID": 25,
    "AUTOROTATE": 26,
    "AUTO_RTL": 27,
}

# PX4 main modes and AUTO sub modes (px4_custom_mode.h).
_PX4_MAIN = {
    "MANUAL": 1,
    "ALTCTL": 2,
    "POSCTL": 3,
    "AUTO": 4,
    "ACRO": 5,
    "OFFBOARD": 6,
    "STABILIZED": 7,
    "RATTITUDE": 8,
}
_PX4_AUTO_SUB = {
    "READY": 1,
    "TAKEOFF": 2,
    "LOITER": 3,
    "MISSION": 4,
    "RTL": 5,
    "LAND": 6,
    "RTGS": 7,
    "FOLLOW_TARGET": 8,
    "PRECLAND": 9,
}


def _px4_modes() -> dict[str, int]:
    modes = {name: main << 16 for name, main in _PX4_MAIN.items() if name != "AUTO"}
    for sub_name, sub in _PX4_AUTO_SUB.items():
        modes[f"AUTO.{sub_name}"] = (_PX4_MAIN["AUTO"] << 16) | (sub << 24)
    return modes


@dataclass(frozen=True)
class AutopilotProfile:
    """How one autopilot family names its modes and takes commands.

    ``modes`` maps a mode name to the HEARTBEAT ``custom_mode`` value. ``guided_mode`` is the mode
    that accepts velocity setpoints, ``hold_mode`` stops and holds position, ``land_mode`` lands,
    ``takeoff_mode`` (if any) must be active before MAV_CMD_NAV_TAKEOFF is sent.
    ``takeoff_param7_is_amsl``: PX4 reads the takeoff altitude as AMSL (NaN = its default height);
    ArduPilot reads it as metres above home.
    """

    name: str
    autopilot_enum: int
    modes: Mapping[str, int]
    guided_mode: str
    hold_mode: str
    land_mode: str
    takeoff_mode: str | None
    takeoff_param7_is_amsl: bool
    _by_value: Mapping[int, str] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        modes = MappingProxyType({k.upper(): int(v) for k, v in self.modes.items()})
        object.__setattr__(self, "modes", modes)
        object.__setattr__(self, "_by_value", MappingProxyType({v: k for k, v in modes.items()}))
        for role in (self.guided_mode, self.hold_mode, self.land_mode, self.takeoff_mode):
            if role is not None and role not in modes:
                raise InputError(f"profile {self.name}: role mode {role!r} is not in its mode table")

    def custom_mode(self, name: str) -> int:
        """HEARTBEAT custom_mode of the mode called ``name`` (case-insensitive); InputError if unknown."""
        key = name.strip().upper()
        if key not in self.modes:
            raise InputError(f"{self.name} has no mode {name!r}; known: {', '.join(sorted(self.modes))}")
        return self.modes[key]

    def mode_name(self, custom_mode: int) -> str:
        """Name of a HEARTBEAT custom_mode; unknown values read ``UNKNOWN(<n>)``."""
        if self.autopilot_enum == MAV_AUTOPILOT_PX4:
            main = (custom_mode >> 16) & 0xFF
            sub = (custom_mode >> 24) & 0xFF
            key = (main << 16) | (sub << 24) if main == _PX4_MAIN["AUTO"] else main << 16
            return self._by_value.get(key, f"UNKNOWN({custom_mode})")
        return self._by_value.get(int(custom_mode), f"UNKNOWN({custom_mode})")

    def set_mode_params(self, name: str) -> tuple[float, float, float]:
        """(param1, param2, param3) of MAV_CMD_DO_SET_MODE for mode ``name``."""
        value = self.custom_mode(name)
        if self.autopilot_enum == MAV_AUTOPILOT_PX4:
            return float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float((value >> 16) & 0xFF), float((value >> 24) & 0xFF)
        return float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(value), 0.0

    def takeoff_param7(self, height_m: float, origin_alt_m: float | None) -> float:
        """MAV_CMD_NAV_TAKEOFF param7 for a climb to ``height_m`` above the take-off point.

        PX4 wants AMSL: origin altitude + height when the EKF origin is known, else NaN (its default).
        """
        if not math.isfinite(height_m) or height_m <= 0.0:
            raise InputError(f"takeoff height_m must be finite and > 0, got {height_m!r}")
        if self.takeoff_param7_is_amsl:
            return float("nan") if origin_alt_m is None else float(origin_alt_m + height_m)
        return float(height_m)


ARDUPILOT_COPTER = AutopilotProfile(
    name="ardupilot",
    autopilot_enum=MAV_AUTOPILOT_ARDUPILOTMEGA,
    modes=_ARDUCOPTER_MODES,
    guided_mode="GUIDED",
    hold_mode="BRAKE",
    land_mode="LAND",
    takeoff_mode="GUIDED",
    takeoff_param7_is_amsl=False,
)

PX4 = AutopilotProfile(
    name="px4",
    autopilot_enum=MAV_AUTOPILOT_PX4,
    modes=_px4_modes(),
    guided_mode="OFFBOARD",
    hold_mode="AUTO.LOITER",
    land_mode="AUTO.LAND",
    takeoff_mode=None,
    takeoff_param7_is_amsl=True,
)


def profile_for_autopilot(autopilot_enum: int) -> AutopilotProfile | None:
    """Profile for a HEARTBEAT ``autopilot`` value, None if neither ArduPilot nor PX4."""
    if autopilot_enum == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return ARDUPILOT_COPTER
    if autopilot_enum == MAV_AUTOPILOT_PX4:
        return PX4
    return None


def profile_named(name: str) -> AutopilotProfile:
    """Profile by name ("ardupilot" or "px4"); InputError otherwise."""
    key = name.strip().lower()
    if key == "ardupilot":
        return ARDUPILOT_COPTER
    if key == "px4":
        return PX4
    raise InputError(f"unknown autopilot profile {name!r} (ardupilot, px4)")
