"""Autopilot profiles: ArduCopter-like and PX4-like flight modes and their MAVLink encoding.

ArduCopter puts the mode number in HEARTBEAT.custom_mode and in DO_SET_MODE
param2. PX4 packs ``custom_mode = main_mode << 16 | sub_mode << 24`` and takes
DO_SET_MODE param2 = main mode, param3 = sub mode. Each mode maps to one
`Behaviour` of the simulated vehicle.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import InputError

__all__ = ["ARDUPILOT", "PX4", "Behaviour", "ModeDef", "Profile", "profile_by_name", "px4_custom_mode"]


class Behaviour(enum.Enum):
    """What the simulated vehicle does in a mode."""

    MANUAL = "manual"  # no pilot input: hold altitude and attitude level, drift with the wind
    GUIDED = "guided"  # ArduPilot GUIDED: velocity setpoints (3 s timeout), takeoff, else hold position
    OFFBOARD = "offboard"  # PX4 OFFBOARD: follow the setpoint stream; falls back when it stops
    HOLD = "hold"  # hold the position where the mode was entered
    TAKEOFF = "takeoff"  # PX4 AUTO.TAKEOFF: climb to the takeoff height, then AUTO.LOITER
    LAND = "land"  # descend, disarm on the ground
    RTL = "rtl"  # fly home at the current height, then land


@dataclass(frozen=True)
class ModeDef:
    """One flight mode: name, HEARTBEAT custom_mode, behaviour, whether arming is allowed in it,
    whether it needs a position estimate (EKF healthy)."""

    name: str
    custom_mode: int
    behaviour: Behaviour
    armable: bool
    needs_position: bool


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """PX4's HEARTBEAT custom_mode for a main/sub mode pair."""
    return (main_mode << 16) | (sub_mode << 24)


@dataclass(frozen=True)
class Profile:
    """Everything that differs between the ArduPilot-like and the PX4-like fake."""

    name: str
    autopilot: int  # MAV_AUTOPILOT_*
    modes: tuple[ModeDef, ...]
    initial_mode: str
    hold_mode: str
    land_mode: str
    rtl_mode: str
    guided_mode: str  # the mode velocity setpoints are flown in
    takeoff_mode: str | None  # PX4 switches to AUTO.TAKEOFF; ArduPilot takes off inside GUIDED
    arm_denied_result: int  # COMMAND_ACK result for a failed pre-arm check
    mode_denied_result: int  # COMMAND_ACK result for a refused mode change
    statustext_prefix: str  # arming refusals: "Arm: " (ArduPilot, as answered to an ARM command) / "Preflight Fail: "
    mode_checks_when_disarmed: bool  # ArduCopter checks a mode's needs (position) only when armed

    def mode(self, name: str) -> ModeDef:
        """The mode called `name` (case-insensitive); raises InputError if unknown."""
        for m in self.modes:
            if m.name == name.upper():
                return m
        raise InputError(f"profile {self.name} has no mode {name!r}; known: {[m.name for m in self.modes]}")

    def mode_from_custom(self, custom_mode: int) -> ModeDef | None:
        """The mode whose HEARTBEAT custom_mode is `custom_mode` (None if unknown)."""
        for m in self.modes:
            if m.custom_mode == custom_mode:
                return m
        return None

    def mode_from_do_set_mode(self, param1: float, param2: float, param3: float) -> ModeDef | None:
        """Decode MAV_CMD_DO_SET_MODE params (base mode, custom mode, custom sub mode); NaN counts as 0."""
        base, main, sub = (int(x) if math.isfinite(x) else 0 for x in (param1, param2, param3))
        if not base & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return None
        if self.autopilot == mavlink.MAV_AUTOPILOT_PX4:
            return self.mode_from_custom(px4_custom_mode(main, sub))
        return self.mode_from_custom(main)


_AP_MODES = (
    ModeDef("STABILIZE", 0, Behaviour.MANUAL, armable=True, needs_position=False),
    ModeDef("ALT_HOLD", 2, Behaviour.MANUAL, armable=True, needs_position=False),
    ModeDef("GUIDED", 4, Behaviour.GUIDED, armable=True, needs_position=True),
    ModeDef("LOITER", 5, Behaviour.HOLD, armable=True, needs_position=True),
    ModeDef("RTL", 6, Behaviour.RTL, armable=False, needs_position=True),
    ModeDef("LAND", 9, Behaviour.LAND, armable=False, needs_position=False),
    ModeDef("POSHOLD", 16, Behaviour.HOLD, armable=True, needs_position=True),
    ModeDef("BRAKE", 17, Behaviour.HOLD, armable=False, needs_position=True),
)

_PX4_MAIN_MANUAL, _PX4_MAIN_ALTCTL, _PX4_MAIN_POSCTL, _PX4_MAIN_AUTO = 1, 2, 3, 4
_PX4_MAIN_OFFBOARD, _PX4_MAIN_STABILIZED = 6, 7
_PX4_SUB_TAKEOFF, _PX4_SUB_LOITER, _PX4_SUB_RTL, _PX4_SUB_LAND = 2, 3, 5, 6

_PX4_MODES = (
    ModeDef("MANUAL", px4_custom_mode(_PX4_MAIN_MANUAL), Behaviour.MANUAL, armable=True, needs_position=False),
    ModeDef("STABILIZED", px4_custom_mode(_PX4_MAIN_STABILIZED), Behaviour.MANUAL, armable=True, needs_position=False),
    ModeDef("ALTCTL", px4_custom_mode(_PX4_MAIN_ALTCTL), Behaviour.MANUAL, armable=True, needs_position=False),
    ModeDef("POSCTL", px4_custom_mode(_PX4_MAIN_POSCTL), Behaviour.HOLD, armable=True, needs_position=True),
    ModeDef(
        "AUTO.TAKEOFF",
        px4_custom_mode(_PX4_MAIN_AUTO, _PX4_SUB_TAKEOFF),
        Behaviour.TAKEOFF,
        armable=True,
        needs_position=True,
    ),
    ModeDef(
        "AUTO.LOITER",
        px4_custom_mode(_PX4_MAIN_AUTO, _PX4_SUB_LOITER),
        Behaviour.HOLD,
        armable=True,
        needs_position=True,
    ),
    ModeDef(
        "AUTO.RTL", px4_custom_mode(_PX4_MAIN_AUTO, _PX4_SUB_RTL), Behaviour.RTL, armable=False, needs_position=True
    ),
    ModeDef(
        "AUTO.LAND", px4_custom_mode(_PX4_MAIN_AUTO, _PX4_SUB_LAND), Behaviour.LAND, armable=False, needs_position=False
    ),
    ModeDef("OFFBOARD", px4_custom_mode(_PX4_MAIN_OFFBOARD), Behaviour.OFFBOARD, armable=True, needs_position=True),
)

ARDUPILOT = Profile(
    name="ardupilot",
    autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    modes=_AP_MODES,
    initial_mode="STABILIZE",
    hold_mode="LOITER",
    land_mode="LAND",
    rtl_mode="RTL",
    guided_mode="GUIDED",
    takeoff_mode=None,
    arm_denied_result=mavlink.MAV_RESULT_FAILED,
    mode_denied_result=mavlink.MAV_RESULT_FAILED,
    statustext_prefix="Arm: ",
    mode_checks_when_disarmed=False,
)

PX4 = Profile(
    name="px4",
    autopilot=mavlink.MAV_AUTOPILOT_PX4,
    modes=_PX4_MODES,
    initial_mode="POSCTL",
    hold_mode="AUTO.LOITER",
    land_mode="AUTO.LAND",
    rtl_mode="AUTO.RTL",
    guided_mode="OFFBOARD",
    takeoff_mode="AUTO.TAKEOFF",
    arm_denied_result=mavlink.MAV_RESULT_DENIED,
    mode_denied_result=mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
    statustext_prefix="Preflight Fail: ",
    mode_checks_when_disarmed=True,
)


def profile_by_name(name: str) -> Profile:
    """`ARDUPILOT` for "ardupilot" (or "apm", "arducopter"), `PX4` for "px4"."""
    key = name.strip().lower()
    if key in ("ardupilot", "apm", "arducopter"):
        return ARDUPILOT
    if key == "px4":
        return PX4
    raise InputError(f"unknown autopilot profile {name!r}; use 'ardupilot' or 'px4'")
