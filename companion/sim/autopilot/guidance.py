"""Pure guidance helpers of the fake autopilot: holding a point, ArduPilot's shaping of GUIDED velocities."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["ShapedVelocity", "hold_velocity", "shape_velocity_ne"]


@dataclass(frozen=True)
class ShapedVelocity:
    """The shaped horizontal velocity command (m/s, NED north/east) and its acceleration (m/s²)."""

    velocity_ne_m_s: tuple[float, float]
    accel_ne_m_s2: tuple[float, float]


def shape_velocity_ne(
    state: ShapedVelocity, target_ne_m_s: tuple[float, float], accel_max_m_s2: float, jerk_max_m_s3: float, dt_s: float
) -> ShapedVelocity:
    """One step of a jerk- and acceleration-limited approach of `target_ne_m_s` (like ArduPilot's
    `shape_vel_accel`): the wanted acceleration points at the target, no larger than `accel_max_m_s2`
    nor than what still stops on the target (sqrt controller); the acceleration moves toward it at
    most at `jerk_max_m_s3`. The velocity never passes the target."""
    (vn, ve), (an, ae) = state.velocity_ne_m_s, state.accel_ne_m_s2
    en, ee = target_ne_m_s[0] - vn, target_ne_m_s[1] - ve
    err = math.hypot(en, ee)
    if err < 1e-9:
        return ShapedVelocity(target_ne_m_s, (0.0, 0.0))
    want = min(accel_max_m_s2, math.sqrt(2.0 * jerk_max_m_s3 * err))
    dn, de = want * en / err - an, want * ee / err - ae
    step = math.hypot(dn, de)
    limit = jerk_max_m_s3 * dt_s
    if step > limit:
        dn, de = dn * limit / step, de * limit / step
    an, ae = an + dn, ae + de
    vn, ve = vn + an * dt_s, ve + ae * dt_s
    if (target_ne_m_s[0] - vn) * en + (target_ne_m_s[1] - ve) * ee < 0.0:
        return ShapedVelocity(target_ne_m_s, (0.0, 0.0))
    return ShapedVelocity((vn, ve), (an, ae))


def hold_velocity(
    position_ned_m: tuple[float, float, float],
    target_ned_m: tuple[float, float, float],
    gain_per_s: float,
    max_speed_m_s: float,
) -> tuple[float, float, float]:
    """Velocity (m/s, NED) toward a held point: proportional, horizontal speed capped, vertical to ±1 m/s."""
    vx = gain_per_s * (target_ned_m[0] - position_ned_m[0])
    vy = gain_per_s * (target_ned_m[1] - position_ned_m[1])
    vz = gain_per_s * (target_ned_m[2] - position_ned_m[2])
    speed = math.hypot(vx, vy)
    if speed > max_speed_m_s:
        vx, vy = vx * max_speed_m_s / speed, vy * max_speed_m_s / speed
    return (vx, vy, max(-1.0, min(1.0, vz)))
