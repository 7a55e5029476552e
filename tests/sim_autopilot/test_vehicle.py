"""Vehicle dynamics: ground contact, first-order velocity response, tilt from acceleration, IMU consistency."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.errors import InputError
from companion.geometry import frames
from companion.sim.autopilot.vehicle import (
    GRAVITY_M_S2,
    MotionCommand,
    VehicleParams,
    VehicleState,
    initial_vehicle,
    step_vehicle,
)

DT = 1.0 / 400.0
CALM = (0.0, 0.0, 0.0)


def _run(
    state: VehicleState,
    command: MotionCommand,
    seconds: float,
    wind: tuple[float, float, float] = CALM,
    params: VehicleParams | None = None,
) -> list[VehicleState]:
    p = params or VehicleParams()
    out = []
    for _ in range(round(seconds / DT)):
        state = step_vehicle(state, command, wind, p, DT)
        out.append(state)
    return out


def _airborne(height_m: float = 5.0) -> VehicleState:
    climb = _run(initial_vehicle(), MotionCommand((0.0, 0.0, -2.0), 0.0, True), height_m / 2.0)
    hover = _run(climb[-1], MotionCommand((0.0, 0.0, 0.0), 0.0, True), 3.0)
    return hover[-1]


def test_disarmed_vehicle_rests_on_the_ground_reading_minus_g() -> None:
    s = _run(initial_vehicle(1.0, 2.0, 0.5), MotionCommand(), 1.0)[-1]
    assert s.on_ground
    assert s.position_ned_m == (1.0, 2.0, 0.0)
    assert s.specific_force_body_m_s2 == pytest.approx((0.0, 0.0, -GRAVITY_M_S2))
    assert s.yaw_rad == pytest.approx(0.5)


def test_motors_on_without_climb_stays_on_ground_and_horizontal_commands_are_ignored() -> None:
    s = _run(initial_vehicle(), MotionCommand((2.0, 0.0, 0.0), 0.0, True), 1.0)[-1]
    assert s.on_ground
    assert s.position_ned_m == (0.0, 0.0, 0.0)


def test_climb_leaves_the_ground_and_hover_is_steady() -> None:
    s = _airborne(5.0)
    assert not s.on_ground
    assert s.height_m > 4.0
    assert np.allclose(s.velocity_ned_m_s, 0.0, atol=1e-3)
    assert s.thrust_ratio == pytest.approx(1.0, abs=1e-3)
    assert abs(s.roll_rad) < 1e-6 and abs(s.pitch_rad) < 1e-6


def test_velocity_response_is_first_order_like_with_the_configured_time_constant() -> None:
    params = VehicleParams()
    s0 = _airborne()
    states = _run(s0, MotionCommand((2.0, 0.0, 0.0), 0.0, True), 4.0)
    vx = np.array([s.velocity_ned_m_s[0] for s in states])
    assert vx[-1] == pytest.approx(2.0, abs=0.02)
    # 63 % of the step after about tau (plus the attitude lag), no large overshoot.
    t63 = (np.argmax(vx >= 0.632 * 2.0) + 1) * DT
    assert params.tau_velocity_h_s <= t63 <= params.tau_velocity_h_s + 3 * params.tau_attitude_s
    assert vx.max() < 2.0 * 1.1


def test_accelerating_north_pitches_nose_down_and_east_rolls_right() -> None:
    s0 = _airborne()
    north = _run(s0, MotionCommand((3.0, 0.0, 0.0), 0.0, True), 0.3)[-1]
    assert north.pitch_rad < -0.05 and abs(north.roll_rad) < 1e-6
    east = _run(s0, MotionCommand((0.0, 3.0, 0.0), 0.0, True), 0.3)[-1]
    assert east.roll_rad > 0.05 and abs(east.pitch_rad) < 1e-6
    # Tilt is limited.
    hard = _run(s0, MotionCommand((50.0, 0.0, 0.0), 0.0, True), 1.0)
    assert max(abs(s.pitch_rad) for s in hard) <= VehicleParams().max_tilt_rad + 1e-9


def test_horizontal_acceleration_matches_the_tilt() -> None:
    s0 = _airborne()
    s = _run(s0, MotionCommand((3.0, -1.0, 0.0), 0.0, True), 0.5)[-1]
    # With the vertical acceleration near zero, a_h = g tan(tilt) along the thrust direction.
    R = frames.rotation_from_euler_zyx(s.roll_rad, s.pitch_rad, s.yaw_rad)
    thrust_dir = -R[:, 2]
    a = np.array(s.accel_ned_m_s2)
    # Specific force = thrust + drag; take the drag (computed at the previous velocity) out.
    v_prev = np.array(s.velocity_ned_m_s) - a * DT
    f_thrust = a - np.array([0.0, 0.0, GRAVITY_M_S2]) + VehicleParams().drag_per_s * v_prev
    cos = float(f_thrust @ thrust_dir) / float(np.linalg.norm(f_thrust))
    assert cos == pytest.approx(1.0, abs=1e-9)


def test_imu_integrates_to_the_true_velocity_and_attitude() -> None:
    s0 = _airborne()
    commands = [MotionCommand((2.0, 1.0, -0.5), 0.4, True), MotionCommand((-1.0, 0.5, 0.3), -0.3, True)]
    states = [s0]
    for cmd in commands:
        states += _run(states[-1], cmd, 1.5)
    g = np.array([0.0, 0.0, GRAVITY_M_S2])
    v = np.array(s0.velocity_ned_m_s)
    R = s0.R_ned_body()
    for s in states[1:]:
        R_next = s.R_ned_body()
        v = v + (R_next @ np.array(s.specific_force_body_m_s2) + g) * DT
        R = R @ _so3_exp(np.array(s.rates_body_rad_s) * DT)
    assert np.allclose(v, states[-1].velocity_ned_m_s, atol=1e-9)
    angle_err = np.linalg.norm(frames.euler_zyx_from_rotation(R.T @ states[-1].R_ned_body()))
    assert angle_err < 2e-3


def _so3_exp(w: np.ndarray) -> np.ndarray:
    from companion.geometry import so3

    return np.asarray(so3.exp(w))


def test_yaw_rate_follows_command_and_wraps() -> None:
    s0 = _airborne()
    states = _run(s0, MotionCommand((0.0, 0.0, 0.0), 1.0, True), 4.0)
    assert states[-1].yaw_rate_rad_s == pytest.approx(1.0, abs=1e-3)
    assert all(-math.pi <= s.yaw_rad <= math.pi for s in states)


def test_descent_touches_down_and_stops() -> None:
    s0 = _airborne(2.0)
    states = _run(s0, MotionCommand((0.0, 0.0, 1.0), 0.0, True), 5.0)
    assert states[-1].on_ground
    assert states[-1].position_ned_m[2] == 0.0
    assert all(s.position_ned_m[2] <= 0.0 for s in states)


def test_motors_off_in_the_air_falls() -> None:
    s0 = _airborne(5.0)
    states = _run(s0, MotionCommand(), 0.5)
    k = VehicleParams().drag_per_s
    assert states[-1].velocity_ned_m_s[2] == pytest.approx(GRAVITY_M_S2 * (1.0 - math.exp(-k * 0.5)) / k, rel=0.01)
    # Free fall: the accelerometer only feels the air drag.
    vz_prev = states[-2].velocity_ned_m_s[2]
    assert states[-1].specific_force_body_m_s2 == pytest.approx((0.0, 0.0, -k * vz_prev), abs=1e-6)


def test_wind_pushes_then_the_controller_compensates() -> None:
    s0 = _airborne()
    wind = (4.0, 0.0, 0.0)
    states = _run(s0, MotionCommand((0.0, 0.0, 0.0), 0.0, True), 12.0, wind=wind)
    vx = np.array([s.velocity_ned_m_s[0] for s in states])
    assert vx.max() > 0.1  # the gust moves the vehicle downwind
    assert abs(vx[-1]) < 0.05  # the disturbance observer cancels the steady part
    assert states[-1].pitch_rad > 0.05  # leaning into the wind (nose up to push south against a northward wind)


def test_step_rejects_nonpositive_dt() -> None:
    with pytest.raises(InputError):
        step_vehicle(initial_vehicle(), MotionCommand(), CALM, VehicleParams(), 0.0)
    with pytest.raises(InputError):
        VehicleParams(tau_attitude_s=0.0)
