"""The fake autopilot's EKF as seen over MAVLink: alignment on vision, dead reckoning, flags, pre-arm texts.

A synchronous model (no I/O, no clock: every call takes `now_s`). It does not estimate anything: the
vehicle's true state stands for the estimate. What it models is *when* the real EKF has a position,
is ready to arm and what it reports, measured against ArduCopter SITL (EKF3, external navigation):

- a vision pose gives a position at once (EKF_STATUS_REPORT flags 167 → 831 within 0.25 s), but
  pre-arm checks pass only after `alignment_s` of continuous vision (11.8-13.1 s on the SITL);
- when vision stops, the EKF dead-reckons (IMU + baro height) and keeps its flags for
  `vision_timeout_s` (7.07-7.27 s on the SITL), then reports no horizontal position (flags 37, + 64 with
  a valid height above ground);
- EKF_POS_VERT_AGL (64) appears about 1 s after NAV_TAKEOFF and disappears when arming again.

The PX4 profile keeps the fake's earlier model: healthy while a pose is < `vision_timeout_s` old.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

__all__ = ["VISODOM_TIMEOUT_S", "EkfModel", "FsEkfCheck"]

_ATT = mavlink.EKF_ATTITUDE
_VEL_H, _VEL_V = mavlink.EKF_VELOCITY_HORIZ, mavlink.EKF_VELOCITY_VERT
_POS_H_REL, _POS_H_ABS = mavlink.EKF_POS_HORIZ_REL, mavlink.EKF_POS_HORIZ_ABS
_POS_V_ABS, _POS_V_AGL = mavlink.EKF_POS_VERT_ABS, mavlink.EKF_POS_VERT_AGL
_CONST_POS = mavlink.EKF_CONST_POS_MODE
_PRED_H_REL, _PRED_H_ABS = mavlink.EKF_PRED_POS_HORIZ_REL, mavlink.EKF_PRED_POS_HORIZ_ABS
VISODOM_TIMEOUT_S = 0.3  # ArduPilot's AP_VISUALODOM_TIMEOUT_MS: VisOdom is healthy with a pose in the last 300 ms


class EkfModel:
    """When the EKF has a position and is ready (mutable; one per simulated vehicle).

    ``ardupilot``: ArduCopter EKF3 behaviour (alignment, dead reckoning, its flags and texts), else PX4.
    ``require_vision``: without it (GPS configuration) the EKF always has a position and is ready.
    """

    def __init__(self, ardupilot: bool, require_vision: bool, vision_timeout_s: float, alignment_s: float) -> None:
        self.ardupilot = ardupilot
        self.require_vision = require_vision
        self.vision_timeout_s = vision_timeout_s
        self.alignment_s = alignment_s
        self.last_vision_s: float | None = None
        self.had_position = False
        self.height_agl_valid = False
        self._run_start_s: float | None = None  # start of the current uninterrupted run of poses
        self._aligned = False

    def on_vision(self, now_s: float) -> None:
        """A vision pose (or odometry) arrived."""
        if self.last_vision_s is None or now_s - self.last_vision_s > self.vision_timeout_s:
            self._run_start_s = now_s
        self.last_vision_s = now_s
        self.had_position = True

    def has_position(self, now_s: float) -> bool:
        """Whether the EKF reports a horizontal position now (dead reckoning included)."""
        if not self.require_vision:
            return True
        return self.last_vision_s is not None and now_s - self.last_vision_s <= self.vision_timeout_s

    def vision_age_s(self, now_s: float) -> float | None:
        """Seconds since the last pose (None before the first one)."""
        return None if self.last_vision_s is None else now_s - self.last_vision_s

    def aligned(self, now_s: float) -> bool:
        """The EKF has had `alignment_s` of continuous vision (latched) and has a position now."""
        if not self.has_position(now_s):
            return False
        if not self.require_vision:
            return True
        if not self._aligned and self._run_start_s is not None and now_s - self._run_start_s >= self.alignment_s:
            self._aligned = True
        return self._aligned

    def flags(self, now_s: float, origin_set: bool) -> int:
        """EKF_STATUS_REPORT.flags."""
        if not self.ardupilot:
            if self.has_position(now_s):
                flags = _ATT | _VEL_H | _VEL_V | _POS_H_REL | _POS_V_ABS | _POS_V_AGL | _PRED_H_REL
                return int(flags | (_POS_H_ABS | _PRED_H_ABS if origin_set else 0))
            return int(_ATT | _VEL_V | _POS_V_ABS | _CONST_POS)
        agl = _POS_V_AGL if self.height_agl_valid else 0
        if self.has_position(now_s):
            flags = _ATT | _VEL_H | _VEL_V | _POS_H_REL | _POS_V_ABS | _PRED_H_REL
            return int(flags | agl | (_POS_H_ABS | _PRED_H_ABS if origin_set else 0))
        if self.had_position:  # lost after dead reckoning: no horizontal velocity or position at all
            return int(_ATT | _VEL_V | _POS_V_ABS | agl)
        return int(_ATT | _VEL_H | _VEL_V | _POS_V_ABS | _CONST_POS | agl)  # never had one: constant-position mode

    def variances(self, now_s: float) -> tuple[float, float]:
        """EKF_STATUS_REPORT (velocity, horizontal position) variances: small with a position, growing
        while dead reckoning, over FS_EKF_THRESH once it is lost."""
        age = self.vision_age_s(now_s)
        if not self.require_vision or (age is not None and age <= 0.3):
            return 0.05, 0.05
        if age is not None and self.has_position(now_s):
            grow = min(age / max(self.vision_timeout_s, 1e-6), 1.0)
            return 0.05 + 0.5 * grow, 0.05 + 0.7 * grow
        return 1.2, 1.2

    def prearm_failures(self, now_s: float, home_set: bool) -> list[str]:
        """ArduPilot's pre-arm failures from the EKF side, in its words (without the "Arm: " prefix)."""
        if not self.require_vision:
            return []
        failures = []
        if not home_set:
            failures.append("AHRS: waiting for home")
        age = self.vision_age_s(now_s)
        if age is None or age > VISODOM_TIMEOUT_S:
            failures.append("VisOdom: not healthy")
        elif not self.aligned(now_s):
            failures.append("AHRS: not healthy")  # the SITL says "Gyros inconsistent" here: see docs
        return failures


class FsEkfCheck:
    """ArduCopter's FS_EKF check (ekf_check.cpp, 10 Hz): the caller says whether the EKF fails (no
    position) at each step; `update` returns "triggered" when the failsafe starts, "cleared" after
    1 s of passing checks again, else None."""

    def __init__(self) -> None:
        self.active = False
        self._ok_since_s: float | None = None

    def update(self, now_s: float, failing: bool, has_position: bool) -> str | None:
        if failing:
            self._ok_since_s = None
            if self.active:
                return None
            self.active = True
            return "triggered"
        if not self.active or not has_position:
            return None
        if self._ok_since_s is None:
            self._ok_since_s = now_s
        elif now_s - self._ok_since_s >= 1.0:
            self.active = False
            return "cleared"
        return None
