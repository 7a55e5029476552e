"""Multirotor dynamics for the fake autopilot: a pure step function on frozen states (NED, SI units).

Model (per step of `dt_s`):
- the velocity controller asks for ``a_ctrl = (v_cmd - v) / tau`` (per axis group) plus a
  feed-forward of its own still-air drag, minus its estimate of the wind disturbance (a slow
  disturbance observer, like an integrator); in still air the response is exactly first order
  (apart from the attitude lag);
- the thrust direction needed for ``a_ctrl`` gives the desired roll/pitch at the current yaw
  (tilt from acceleration), clipped to `max_tilt_rad`; the attitude follows with a first-order lag;
- thrust magnitude keeps the vertical acceleration; the horizontal acceleration comes from the
  actual tilt, so attitude and acceleration stay consistent;
- the wind acts as aerodynamic drag ``drag_per_s (w_air - v)``;
- yaw rate follows the command with a first-order lag;
- the ground is the plane z = 0 (NED, down positive): on contact the vehicle stops and levels.

The state carries the true kinematic acceleration and the body rates of the step, from which the
IMU's specific force (body FRD, ``R_ned_bodyᵀ (a - g)``) and gyro follow exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError
from companion.geometry import frames, se3

__all__ = ["GRAVITY_M_S2", "MotionCommand", "VehicleParams", "VehicleState", "initial_vehicle", "step_vehicle"]

GRAVITY_M_S2 = 9.80665

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class VehicleParams:
    """Dynamics constants (s, m/s, rad, 1/s)."""

    tau_velocity_h_s: float = 0.45
    tau_velocity_v_s: float = 0.3
    tau_attitude_s: float = 0.1
    tau_yaw_rate_s: float = 0.12
    tau_disturbance_s: float = 1.5
    drag_per_s: float = 0.3
    max_tilt_rad: float = math.radians(35.0)
    max_speed_h_m_s: float = 5.0
    max_climb_m_s: float = 3.0
    max_descent_m_s: float = 2.0
    max_yaw_rate_rad_s: float = math.radians(90.0)

    def __post_init__(self) -> None:
        for name in ("tau_velocity_h_s", "tau_velocity_v_s", "tau_attitude_s", "tau_yaw_rate_s", "tau_disturbance_s"):
            if not getattr(self, name) > 0.0:
                raise InputError(f"VehicleParams.{name} must be > 0, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class MotionCommand:
    """What the flight logic asks of the airframe: NED velocity (m/s), yaw rate (rad/s), motors on/off."""

    velocity_ned_m_s: Vec3 = (0.0, 0.0, 0.0)
    yaw_rate_rad_s: float = 0.0
    motors_on: bool = False


@dataclass(frozen=True)
class VehicleState:
    """True vehicle state.

    position/velocity/acceleration in NED (m, m/s, m/s²), Euler ZYX angles (rad) of R_ned_body,
    `rates_body_rad_s` the body FRD angular velocity, `specific_force_body_m_s2` what an ideal
    accelerometer reads (body FRD), `disturbance_estimate_ned_m_s2` the controller's integrator,
    `thrust_ratio` = thrust / weight, `on_ground` true when resting on z = 0.
    """

    position_ned_m: Vec3
    velocity_ned_m_s: Vec3
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    yaw_rate_rad_s: float
    rates_body_rad_s: Vec3
    accel_ned_m_s2: Vec3
    specific_force_body_m_s2: Vec3
    disturbance_estimate_ned_m_s2: Vec3
    thrust_ratio: float
    on_ground: bool

    @property
    def height_m(self) -> float:
        """Height above the ground plane (m)."""
        return -self.position_ned_m[2]

    def R_ned_body(self) -> FloatArray:
        """Rotation body FRD -> NED (3x3)."""
        return frames.rotation_from_euler_zyx(self.roll_rad, self.pitch_rad, self.yaw_rad)

    def T_ned_body(self) -> FloatArray:
        """Pose of the body in NED (4x4)."""
        return se3.make(self.R_ned_body(), np.asarray(self.position_ned_m, dtype=float))


def initial_vehicle(north_m: float = 0.0, east_m: float = 0.0, yaw_rad: float = 0.0) -> VehicleState:
    """The vehicle resting on the ground at (north, east), heading `yaw_rad`."""
    return VehicleState(
        position_ned_m=(float(north_m), float(east_m), 0.0),
        velocity_ned_m_s=(0.0, 0.0, 0.0),
        roll_rad=0.0,
        pitch_rad=0.0,
        yaw_rad=float(yaw_rad),
        yaw_rate_rad_s=0.0,
        rates_body_rad_s=(0.0, 0.0, 0.0),
        accel_ned_m_s2=(0.0, 0.0, 0.0),
        specific_force_body_m_s2=(0.0, 0.0, -GRAVITY_M_S2),
        disturbance_estimate_ned_m_s2=(0.0, 0.0, 0.0),
        thrust_ratio=0.0,
        on_ground=True,
    )


def _clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def _rotation(roll: float, pitch: float, yaw: float) -> tuple[Vec3, Vec3, Vec3]:
    """Rows of R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return (
        (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        (-sp, cp * sr, cp * cr),
    )


def _to_body(R: tuple[Vec3, Vec3, Vec3], v_ned: Vec3) -> Vec3:
    return (
        R[0][0] * v_ned[0] + R[1][0] * v_ned[1] + R[2][0] * v_ned[2],
        R[0][1] * v_ned[0] + R[1][1] * v_ned[1] + R[2][1] * v_ned[2],
        R[0][2] * v_ned[0] + R[1][2] * v_ned[1] + R[2][2] * v_ned[2],
    )


def step_vehicle(
    state: VehicleState, command: MotionCommand, wind_ned_m_s: Vec3, params: VehicleParams, dt_s: float
) -> VehicleState:
    """Advance the true vehicle by `dt_s` seconds under `command` in the air velocity `wind_ned_m_s` (NED, m/s)."""
    if not dt_s > 0.0:
        raise InputError(f"dt_s must be > 0, got {dt_s!r}")
    g = GRAVITY_M_S2
    p = params
    vx, vy, vz = state.velocity_ned_m_s
    airborne = not state.on_ground
    dn, de, dd = state.disturbance_estimate_ned_m_s2

    if command.motors_on:
        cx, cy_, cz = command.velocity_ned_m_s
        speed_h = math.hypot(cx, cy_)
        if speed_h > p.max_speed_h_m_s:
            cx, cy_ = cx * p.max_speed_h_m_s / speed_h, cy_ * p.max_speed_h_m_s / speed_h
        cz = _clip(cz, -p.max_climb_m_s, p.max_descent_m_s)
        if not airborne:
            cx = cy_ = 0.0  # on the ground only a climb command matters
        # Feed-forward of the vehicle's own still-air drag, minus the estimated wind disturbance.
        ff = p.drag_per_s if airborne else 0.0
        ax_c = (cx - vx) / p.tau_velocity_h_s + ff * vx - dn
        ay_c = (cy_ - vy) / p.tau_velocity_h_s + ff * vy - de
        az_c = (cz - vz) / p.tau_velocity_v_s + ff * vz - dd
        az_c = _clip(az_c, -0.8 * g, 0.8 * g)
        # Desired thrust direction: body z (down) along -(a_ctrl - g).
        fx, fy, fz = ax_c, ay_c, az_c - g
        norm = math.sqrt(fx * fx + fy * fy + fz * fz)
        b3 = (-fx / norm, -fy / norm, -fz / norm)
        cyaw, syaw = math.cos(state.yaw_rad), math.sin(state.yaw_rad)
        b3x = cyaw * b3[0] + syaw * b3[1]  # in the yaw-rotated frame
        b3y = -syaw * b3[0] + cyaw * b3[1]
        roll_des = math.asin(_clip(-b3y, -1.0, 1.0))
        pitch_des = math.atan2(b3x, b3[2])
        roll_des = _clip(roll_des, -p.max_tilt_rad, p.max_tilt_rad)
        pitch_des = _clip(pitch_des, -p.max_tilt_rad, p.max_tilt_rad)
        if not airborne:
            roll_des = pitch_des = 0.0
        yaw_rate_cmd = _clip(command.yaw_rate_rad_s, -p.max_yaw_rate_rad_s, p.max_yaw_rate_rad_s)
    else:
        roll_des = pitch_des = 0.0
        yaw_rate_cmd = 0.0
        az_c = 0.0

    k_att = 1.0 - math.exp(-dt_s / p.tau_attitude_s)
    k_yaw = 1.0 - math.exp(-dt_s / p.tau_yaw_rate_s)
    roll = state.roll_rad + (roll_des - state.roll_rad) * k_att
    pitch = state.pitch_rad + (pitch_des - state.pitch_rad) * k_att
    yaw_rate = state.yaw_rate_rad_s + (yaw_rate_cmd - state.yaw_rate_rad_s) * k_yaw
    if not airborne and not command.motors_on:
        yaw_rate = 0.0
    yaw = math.atan2(math.sin(state.yaw_rad + yaw_rate * dt_s), math.cos(state.yaw_rad + yaw_rate * dt_s))

    R = _rotation(roll, pitch, yaw)
    if command.motors_on:
        # Thrust magnitude that gives the commanded vertical acceleration along the actual body axis.
        b3z = R[2][2]
        thrust = max(0.0, (g - az_c) / max(b3z, 0.2))
        thrust = min(thrust, 2.5 * g)
    else:
        thrust = 0.0
    # Thrust acts along -body z.
    ax = -thrust * R[0][2]
    ay = -thrust * R[1][2]
    az = -thrust * R[2][2] + g
    if airborne or command.motors_on:
        wx, wy, wz = wind_ned_m_s
        drag = p.drag_per_s
        dist = (drag * (wx - vx), drag * (wy - vy), drag * (wz - vz)) if airborne else (0.0, 0.0, 0.0)
        ax += dist[0]
        ay += dist[1]
        az += dist[2]
    else:
        dist = (0.0, 0.0, 0.0)

    nvx, nvy, nvz = vx + ax * dt_s, vy + ay * dt_s, vz + az * dt_s
    px, py, pz = state.position_ned_m
    npx, npy, npz = px + nvx * dt_s, py + nvy * dt_s, pz + nvz * dt_s
    on_ground = False
    if npz >= 0.0 and nvz >= 0.0:
        # Ground contact: stop, level out.
        npz = 0.0
        nvx = nvy = nvz = 0.0
        npx, npy = px, py
        on_ground = True
    elif not airborne and npz >= 0.0:
        npz = 0.0
    ax, ay, az = (nvx - vx) / dt_s, (nvy - vy) / dt_s, (nvz - vz) / dt_s

    if on_ground:
        ndn = nde = ndd = 0.0
    else:
        # The observer tracks the wind part of the drag (its own still-air drag is fed forward).
        k_d = dt_s / p.tau_disturbance_s
        wx, wy, wz = wind_ned_m_s
        ndn = dn + (p.drag_per_s * wx - dn) * k_d
        nde = de + (p.drag_per_s * wy - de) * k_d
        ndd = dd + (p.drag_per_s * wz - dd) * k_d

    # Body rates from the Euler-angle rates over this step (ZYX kinematics).
    droll = (roll - state.roll_rad) / dt_s
    dpitch = (pitch - state.pitch_rad) / dt_s
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    rates = (droll - sp * yaw_rate, cr * dpitch + sr * cp * yaw_rate, -sr * dpitch + cr * cp * yaw_rate)
    f_body = _to_body(R, (ax, ay, az - g))
    return VehicleState(
        position_ned_m=(npx, npy, npz),
        velocity_ned_m_s=(nvx, nvy, nvz),
        roll_rad=roll,
        pitch_rad=pitch,
        yaw_rad=yaw,
        yaw_rate_rad_s=yaw_rate,
        rates_body_rad_s=rates,
        accel_ned_m_s2=(ax, ay, az),
        specific_force_body_m_s2=f_body,
        disturbance_estimate_ned_m_s2=(ndn, nde, ndd),
        thrust_ratio=thrust / g,
        on_ground=on_ground,
    )
