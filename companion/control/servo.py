"""SE(3)-log visual-servo law (Lippiello & Cacace, section IV) for an underactuated multirotor.

The pose error is H_e = T_ned_body^-1 @ T_ned_body_goal and the commanded twist is
V = K log(H_e) (twist ordered (v, w), translation first). A multirotor only controls
its yaw among the rotations, so both poses are first reduced to their heading
(roll and pitch are dropped): the rotation part of the error is then a pure yaw
rotation, wrapped to (-pi, pi] by the SO(3) log. The body-frame linear velocity is
rotated into NED with the current heading, saturated (0.5 m/s and 0.2 rad/s by
default, the paper's cruise limits) and, given the previous command and the time
step, rate limited so successive commands never jump by more than the
acceleration limits.

With equal linear and yaw gains and no saturation the closed loop on a kinematic
vehicle follows the SE(3) geodesic: log(H_e(t)) = exp(-k t) log(H_e(0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.checks import FloatArray, check_last_two_dims
from companion.control.types import VelocityCommand
from companion.errors import InputError
from companion.geometry import se3
from companion.geometry.frames import yaw_from_rotation

__all__ = ["ServoController", "ServoGains", "ServoLaw", "flatten_to_yaw"]


def _positive(value: float, name: str, owner: str = "ServoGains") -> float:
    value = float(value)
    if not math.isfinite(value) or value <= 0.0:
        raise InputError(f"{owner}.{name} must be finite and > 0, got {value!r}")
    return value


@dataclass(frozen=True)
class ServoGains:
    """Gains and limits of the servo law.

    k_linear_per_s: proportional gain on the translation part of log(H_e) (1/s).
    k_yaw_per_s: proportional gain on the yaw part of log(H_e) (1/s).
    max_speed_m_s: saturation of |(vx, vy, vz)| (m/s); direction is kept.
    max_vertical_speed_m_s: extra saturation of |vz| (m/s), applied after the norm limit.
    max_yaw_rate_rad_s: saturation of |yaw rate| (rad/s).
    max_accel_m_s2: bound on |v_k - v_{k-1}| / dt (m/s^2) when a previous command and dt are given.
    max_yaw_accel_rad_s2: bound on |yaw_rate_k - yaw_rate_{k-1}| / dt (rad/s^2).
    """

    k_linear_per_s: float = 0.8
    k_yaw_per_s: float = 0.8
    max_speed_m_s: float = 0.5
    max_vertical_speed_m_s: float = 0.5
    max_yaw_rate_rad_s: float = 0.2
    max_accel_m_s2: float = 1.0
    max_yaw_accel_rad_s2: float = 0.5

    def __post_init__(self) -> None:
        for name in (
            "k_linear_per_s",
            "k_yaw_per_s",
            "max_speed_m_s",
            "max_vertical_speed_m_s",
            "max_yaw_rate_rad_s",
            "max_accel_m_s2",
            "max_yaw_accel_rad_s2",
        ):
            object.__setattr__(self, name, _positive(getattr(self, name), name))


def flatten_to_yaw(T_ned_body: Any) -> FloatArray:
    """The pose (4, 4) with the same position and heading but zero roll and pitch (NED)."""
    T = check_last_two_dims(T_ned_body, 4, 4, "T_ned_body")
    if T.shape != (4, 4):
        raise InputError(f"T_ned_body: expected shape (4, 4), got {T.shape}")
    yaw_rad = float(yaw_from_rotation(T[:3, :3]))
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return se3.make(R, T[:3, 3])


class ServoLaw:
    """Pure SE(3)-log servo law: pose and goal in, saturated NED velocity + yaw rate out."""

    def __init__(self, gains: ServoGains | None = None) -> None:
        self.gains = gains if gains is not None else ServoGains()

    def error_twist(self, T_ned_body: Any, T_ned_body_goal: Any) -> FloatArray:
        """log(flat(T_ned_body)^-1 @ flat(T_ned_body_goal)) (6,): (v body-level m, w rad), w = (0, 0, dyaw)."""
        T_c = flatten_to_yaw(T_ned_body)
        T_g = flatten_to_yaw(T_ned_body_goal)
        return se3.log(se3.inverse(T_c) @ T_g)

    def error_jacobian(self, T_ned_body: Any, T_ned_body_goal: Any) -> FloatArray:
        """d log(H_e) / d delta (6, 6) for a right perturbation T_c -> T_c exp(delta) of the (flattened) pose.

        H_e = exp(-delta) H_e0, so the Jacobian is -J_l^-1(log H_e0).
        """
        return -se3.left_jacobian_inverse(self.error_twist(T_ned_body, T_ned_body_goal))

    def command(
        self,
        T_ned_body: Any,
        T_ned_body_goal: Any,
        *,
        max_speed_m_s: float | None = None,
        dt_s: float | None = None,
        previous: VelocityCommand | None = None,
    ) -> VelocityCommand:
        """Velocity command (NED, m/s) and yaw rate (rad/s) driving T_ned_body toward T_ned_body_goal.

        max_speed_m_s: an action's own speed limit, applied on top of the gains' saturation.
        dt_s, previous: when both are given, the change from `previous` is bounded by the
        acceleration limits times dt_s (smooth commands at action changes).
        """
        g = self.gains
        T_c = flatten_to_yaw(T_ned_body)
        xi = se3.log(se3.inverse(T_c) @ flatten_to_yaw(T_ned_body_goal))
        v_ned = T_c[:3, :3] @ (g.k_linear_per_s * xi[:3])
        yaw_rate = g.k_yaw_per_s * float(xi[5])

        speed_limit = g.max_speed_m_s
        if max_speed_m_s is not None:
            speed_limit = min(speed_limit, _positive(max_speed_m_s, "max_speed_m_s"))
        v_ned = _saturate_norm(v_ned, speed_limit)
        if abs(v_ned[2]) > g.max_vertical_speed_m_s:
            v_ned = v_ned * (g.max_vertical_speed_m_s / abs(v_ned[2]))
        yaw_rate = float(np.clip(yaw_rate, -g.max_yaw_rate_rad_s, g.max_yaw_rate_rad_s))

        if previous is not None and dt_s is not None:
            dt = float(dt_s)
            if not math.isfinite(dt) or dt < 0.0:
                raise InputError(f"dt_s must be finite and >= 0, got {dt_s!r}")
            v_prev = np.array([previous.vx_m_s, previous.vy_m_s, previous.vz_m_s])
            v_ned = v_prev + _saturate_norm(v_ned - v_prev, g.max_accel_m_s2 * dt)
            max_dyaw = g.max_yaw_accel_rad_s2 * dt
            yaw_rate = previous.yaw_rate_rad_s + float(
                np.clip(yaw_rate - previous.yaw_rate_rad_s, -max_dyaw, max_dyaw)
            )
        return VelocityCommand(float(v_ned[0]), float(v_ned[1]), float(v_ned[2]), yaw_rate)


def _saturate_norm(v: FloatArray, limit: float) -> FloatArray:
    norm = float(np.linalg.norm(v))
    if norm > limit:
        return v * (limit / norm)
    return v


class ServoController:
    """Stateful wrapper of `ServoLaw` that remembers the last command and time for rate limiting.

    `update(T_ned_body, T_ned_body_goal, now_s)` returns the next command; `reset()` forgets the
    history (the next command starts from zero velocity, as after a hover); `hold(now_s)` records
    an explicit zero command (e.g. while the autopilot holds) so the next motion ramps up from rest.

    The rate limit uses the time since the previous command, at most `max_step_s`; after a gap
    longer than `max_gap_s` (a pause, a safety hold, a stalled loop: the vehicle was not following
    the stale command) the next command ramps up from rest as after `reset()`, so no gap ever
    lets a command jump by more than max_accel * max_step_s.
    """

    NOMINAL_STEP_S = 0.1  # step assumed for the first command from rest (s)

    def __init__(self, gains: ServoGains | None = None, *, max_step_s: float = 0.2, max_gap_s: float = 0.5) -> None:
        self.law = ServoLaw(gains)
        self.max_step_s = _positive(max_step_s, "max_step_s", "ServoController")
        self.max_gap_s = _positive(max_gap_s, "max_gap_s", "ServoController")
        self._previous: VelocityCommand | None = None
        self._previous_s: float | None = None

    @property
    def previous(self) -> VelocityCommand | None:
        """The last command returned (None after reset)."""
        return self._previous

    def reset(self) -> None:
        """Forget the previous command; the next update ramps up from zero velocity."""
        self._previous = None
        self._previous_s = None

    def hold(self, now_s: float) -> VelocityCommand:
        """Record and return a zero command at now_s (rate limiting continues from rest)."""
        self._previous = VelocityCommand.zero()
        self._previous_s = float(now_s)
        return self._previous

    def record_sent(self, command: VelocityCommand | None, now_s: float) -> None:
        """Record the command actually sent at now_s (s) as the base of the next rate limit.

        A safety filter may clamp (or drop) what `update` returned; the vehicle follows what was sent,
        so the next command must ramp from that, not from the unclamped value, or it jumps when the
        clamp releases. None means nothing was sent (the vehicle is at rest): like `hold`.
        """
        if command is None:
            command = VelocityCommand.zero()
        elif not isinstance(command, VelocityCommand) or command.frame != "ned":
            raise InputError(f"record_sent takes a NED VelocityCommand or None, got {command!r}")
        now = float(now_s)
        if not math.isfinite(now):
            raise InputError(f"now_s must be finite, got {now_s!r}")
        self._previous = command
        self._previous_s = now

    def update(
        self, T_ned_body: Any, T_ned_body_goal: Any, now_s: float, *, max_speed_m_s: float | None = None
    ) -> VelocityCommand:
        """Next rate-limited command at time now_s (s, monotonic)."""
        now = float(now_s)
        if self._previous is None or self._previous_s is None or now - self._previous_s > self.max_gap_s:
            # First command from rest: one nominal step.
            previous, dt_s = VelocityCommand.zero(), self.NOMINAL_STEP_S
        else:
            previous, dt_s = self._previous, min(max(0.0, now - self._previous_s), self.max_step_s)
        cmd = self.law.command(
            T_ned_body, T_ned_body_goal, max_speed_m_s=max_speed_m_s, dt_s=dt_s, previous=previous
        )
        self._previous = cmd
        self._previous_s = now
        return cmd
