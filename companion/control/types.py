"""Control command types shared by the servo law, the safety manager and the MAVLink link."""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.errors import InputError

__all__ = ["VelocityCommand"]

_FRAMES = ("ned",)


@dataclass(frozen=True)
class VelocityCommand:
    """Velocity + yaw-rate setpoint.

    ``vx_m_s, vy_m_s, vz_m_s`` are the body-origin velocity in the local NED frame (m/s, z down);
    ``yaw_rate_rad_s`` is the yaw rate about NED down (rad/s, positive = clockwise seen from above).
    ``frame`` is always ``"ned"`` for now.
    """

    vx_m_s: float
    vy_m_s: float
    vz_m_s: float
    yaw_rate_rad_s: float
    frame: str = "ned"

    def __post_init__(self) -> None:
        for name in ("vx_m_s", "vy_m_s", "vz_m_s", "yaw_rate_rad_s"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise InputError(f"VelocityCommand.{name} must be finite, got {value!r}")
            object.__setattr__(self, name, value)
        if self.frame not in _FRAMES:
            raise InputError(f"VelocityCommand.frame must be one of {_FRAMES}, got {self.frame!r}")

    @property
    def horizontal_speed_m_s(self) -> float:
        """Horizontal speed |(vx, vy)| (m/s)."""
        return math.hypot(self.vx_m_s, self.vy_m_s)

    @classmethod
    def zero(cls) -> VelocityCommand:
        """All-zero command (hover in place)."""
        return cls(0.0, 0.0, 0.0, 0.0)
