"""Servo law: closed-loop convergence, saturation, yaw wrap-around, rate limits, log Jacobians."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.control import ServoController, ServoGains, ServoLaw, VelocityCommand
from companion.errors import InputError
from companion.geometry import se3
from companion.geometry.frames import rotation_from_euler_zyx, wrap_angle, yaw_from_rotation
from tests.numdiff import central_jacobian


def pose(x: float, y: float, z: float, yaw: float, roll: float = 0.0, pitch: float = 0.0) -> np.ndarray:
    return se3.make(rotation_from_euler_zyx(roll, pitch, yaw), np.array([x, y, z]))


def random_pose(rng: np.random.Generator, xy_range: tuple[float, float], z_range: tuple[float, float],
                yaw_range: tuple[float, float] = (-np.pi, np.pi)) -> np.ndarray:
    x, y = rng.uniform(*xy_range, 2)
    return pose(float(x), float(y), float(rng.uniform(*z_range)), float(rng.uniform(*yaw_range)))


def integrate(T: np.ndarray, cmd: VelocityCommand, dt: float) -> np.ndarray:
    """Kinematic multirotor: NED velocity and yaw rate integrated exactly over dt (roll = pitch = 0)."""
    yaw = float(yaw_from_rotation(T[:3, :3])) + cmd.yaw_rate_rad_s * dt
    p = T[:3, 3] + dt * np.array([cmd.vx_m_s, cmd.vy_m_s, cmd.vz_m_s])
    return pose(p[0], p[1], p[2], yaw)


def test_zero_error_gives_zero_command() -> None:
    T = pose(1.0, -2.0, -3.0, 0.7)
    cmd = ServoLaw().command(T, T)
    assert max(abs(cmd.vx_m_s), abs(cmd.vy_m_s), abs(cmd.vz_m_s), abs(cmd.yaw_rate_rad_s)) < 1e-12
    assert cmd.frame == "ned"


def test_pure_translation_points_at_goal_in_ned() -> None:
    gains = ServoGains(k_linear_per_s=0.5, max_speed_m_s=10.0, max_vertical_speed_m_s=10.0)
    T = pose(0.0, 0.0, -2.0, 1.1)
    T_goal = pose(0.4, -0.2, -2.6, 1.1)
    cmd = ServoLaw(gains).command(T, T_goal)
    assert np.allclose([cmd.vx_m_s, cmd.vy_m_s, cmd.vz_m_s], 0.5 * np.array([0.4, -0.2, -0.6]), atol=1e-12)


def test_saturation_keeps_direction_and_limits(rng: np.random.Generator) -> None:
    law = ServoLaw()  # paper defaults: 0.5 m/s, 0.2 rad/s
    for _ in range(200):
        T = random_pose(rng, (-20, 20), (-20, 20))
        T_goal = random_pose(rng, (-20, 20), (-20, 20))
        cmd = law.command(T, T_goal)
        v = np.array([cmd.vx_m_s, cmd.vy_m_s, cmd.vz_m_s])
        assert np.linalg.norm(v) <= 0.5 + 1e-12
        assert abs(cmd.yaw_rate_rad_s) <= 0.2 + 1e-12
    T = pose(0.0, 0.0, 0.0, 0.0)
    cmd = law.command(T, pose(30.0, 40.0, 0.0, 0.0))
    assert np.allclose([cmd.vx_m_s, cmd.vy_m_s], [0.3, 0.4])
    cmd = law.command(T, pose(3.0, 4.0, 0.0, 0.0), max_speed_m_s=0.25)
    assert np.allclose([cmd.vx_m_s, cmd.vy_m_s], [0.15, 0.2])
    cmd = law.command(T, pose(0.0, 0.0, -5.0, 0.0))
    assert cmd.vz_m_s == pytest.approx(-0.5)


@pytest.mark.parametrize(
    ("yaw", "yaw_goal", "sign"),
    [(math.radians(179), math.radians(-179), 1.0), (math.radians(-179), math.radians(179), -1.0),
     (math.radians(10), math.radians(-10), -1.0), (3.0, -3.0, 1.0)],
)
def test_yaw_wraps_the_short_way(yaw: float, yaw_goal: float, sign: float) -> None:
    gains = ServoGains(k_yaw_per_s=1.0, max_yaw_rate_rad_s=10.0)
    cmd = ServoLaw(gains).command(pose(0, 0, 0, yaw), pose(0, 0, 0, yaw_goal))
    expected = float(wrap_angle(yaw_goal - yaw))
    assert cmd.yaw_rate_rad_s == pytest.approx(expected, abs=1e-9)
    assert np.sign(cmd.yaw_rate_rad_s) == sign


def test_roll_and_pitch_are_ignored() -> None:
    law = ServoLaw(ServoGains(max_speed_m_s=10.0, max_vertical_speed_m_s=10.0, max_yaw_rate_rad_s=10.0))
    T_goal = pose(1.0, 2.0, -3.0, 0.4)
    flat = law.command(pose(0.0, 0.0, -2.0, 0.1), T_goal)
    tilted = law.command(pose(0.0, 0.0, -2.0, 0.1, roll=0.2, pitch=-0.15), pose(1.0, 2.0, -3.0, 0.4, roll=-0.3))
    assert np.allclose(
        [flat.vx_m_s, flat.vy_m_s, flat.vz_m_s, flat.yaw_rate_rad_s],
        [tilted.vx_m_s, tilted.vy_m_s, tilted.vz_m_s, tilted.yaw_rate_rad_s],
    )


def test_closed_loop_converges_from_seeded_arbitrary_starts(rng: np.random.Generator) -> None:
    law = ServoLaw()
    dt = 0.1
    for _ in range(10):
        T = random_pose(rng, (-5, 5), (-4, -0.5))
        T_goal = random_pose(rng, (-5, 5), (-4, -0.5))
        previous = VelocityCommand.zero()
        for _ in range(int(60 / dt)):
            previous = law.command(T, T_goal, dt_s=dt, previous=previous)
            T = integrate(T, previous, dt)
        err = se3.log(se3.inverse(T) @ T_goal)
        assert np.linalg.norm(err[:3]) < 1e-3
        assert abs(err[5]) < 1e-3


def test_unsaturated_loop_follows_the_geodesic() -> None:
    gains = ServoGains(k_linear_per_s=1.0, k_yaw_per_s=1.0, max_speed_m_s=100.0, max_vertical_speed_m_s=100.0,
                       max_yaw_rate_rad_s=100.0)
    law = ServoLaw(gains)
    T = pose(0.0, 0.0, -1.0, 0.0)
    T_goal = pose(2.0, 1.0, -2.0, 1.2)
    xi0 = law.error_twist(T, T_goal)
    dt, steps = 1e-3, 1000
    for _ in range(steps):
        T = integrate(T, law.command(T, T_goal), dt)
    assert np.allclose(law.error_twist(T, T_goal), math.exp(-dt * steps) * xi0, atol=2e-3)


def test_rate_limit_bounds_command_jumps() -> None:
    gains = ServoGains(max_accel_m_s2=1.0, max_yaw_accel_rad_s2=0.5)
    law = ServoLaw(gains)
    prev = VelocityCommand(0.5, 0.0, 0.0, 0.2)
    cmd = law.command(pose(0, 0, 0, 0), pose(-10, 0, 0, 0.0), dt_s=0.1, previous=prev)
    assert math.hypot(cmd.vx_m_s - 0.5, cmd.vy_m_s) <= 0.1 + 1e-12
    assert cmd.vx_m_s == pytest.approx(0.4)
    assert cmd.yaw_rate_rad_s == pytest.approx(0.15)
    with pytest.raises(InputError):
        law.command(pose(0, 0, 0, 0), pose(1, 0, 0, 0), dt_s=-1.0, previous=prev)


def test_controller_ramps_up_from_rest_and_resets() -> None:
    ctl = ServoController(ServoGains(max_accel_m_s2=1.0))
    T, T_goal = pose(0, 0, -2, 0), pose(10, 0, -2, 0)
    speeds = []
    for k in range(10):
        cmd = ctl.update(T, T_goal, now_s=0.1 * k)
        speeds.append(cmd.vx_m_s)
    assert speeds[0] == pytest.approx(0.1)
    assert np.all(np.diff(speeds) <= 0.1 + 1e-9)
    assert speeds[-1] == pytest.approx(0.5)
    ctl.hold(1.0)
    assert ctl.update(T, T_goal, now_s=1.1).vx_m_s == pytest.approx(0.1)
    ctl.reset()
    assert ctl.previous is None


def test_controller_gap_restarts_from_rest_and_steps_are_bounded() -> None:
    """A pause (no commands while the autopilot held) never lets the next command jump to the stale one."""
    ctl = ServoController(ServoGains(max_accel_m_s2=1.0))
    T, T_goal = pose(0, 0, -2, 0), pose(10, 0, -2, 0)
    for k in range(10):
        cmd = ctl.update(T, T_goal, now_s=0.1 * k)
    assert cmd.vx_m_s == pytest.approx(0.5)
    # 30 s later (pause, safety hold), heading the other way: ramps from rest, not from +0.5 m/s.
    after = ctl.update(T, pose(-10, 0, -2, 0), now_s=30.0)
    assert after.vx_m_s == pytest.approx(-0.1)
    # A late but short gap (0.4 s) is rate limited over at most max_step_s = 0.2 s.
    late = ctl.update(T, T_goal, now_s=30.4)
    assert late.vx_m_s == pytest.approx(-0.1 + 0.2)


def test_controller_ramps_from_the_sent_command_when_a_clamp_releases() -> None:
    """A safety filter clamps the climb to 0; once released, the climb ramps from 0, not from the clamped-away value."""
    ctl = ServoController(ServoGains(max_accel_m_s2=1.0, max_vertical_speed_m_s=0.5))
    T, T_goal = pose(0, 0, -2, 0), pose(0, 0, -8, 0)  # 6 m up
    for k in range(10):
        cmd = ctl.update(T, T_goal, now_s=0.1 * k)
        assert cmd.vz_m_s < 0.0  # the law wants to climb ...
        ctl.record_sent(VelocityCommand(cmd.vx_m_s, cmd.vy_m_s, 0.0, cmd.yaw_rate_rad_s), 0.1 * k)  # ... clamped
    assert ctl.previous is not None and ctl.previous.vz_m_s == 0.0
    released = ctl.update(T, T_goal, now_s=1.0)
    assert released.vz_m_s == pytest.approx(-0.1)  # one acceleration step from what was sent
    ctl.record_sent(None, 1.1)  # nothing sent (stream stopped): at rest
    assert ctl.update(T, T_goal, now_s=1.2).vz_m_s == pytest.approx(-0.1)
    with pytest.raises(InputError):
        ctl.record_sent((0.0, 0.0, 0.0, 0.0), 1.3)  # type: ignore[arg-type]
    with pytest.raises(InputError):
        ctl.record_sent(None, math.nan)


def test_bad_gains_and_inputs_rejected() -> None:
    with pytest.raises(InputError, match="max_speed_m_s"):
        ServoGains(max_speed_m_s=0.0)
    with pytest.raises(InputError, match="k_yaw_per_s"):
        ServoGains(k_yaw_per_s=float("nan"))
    with pytest.raises(InputError, match="T_ned_body"):
        ServoLaw().command(np.eye(3), np.eye(4))
    with pytest.raises(InputError, match="vx_m_s"):
        VelocityCommand(float("inf"), 0.0, 0.0, 0.0)
    with pytest.raises(InputError, match="frame"):
        VelocityCommand(0.0, 0.0, 0.0, 0.0, frame="enu")


def random_twist(rng: np.random.Generator) -> np.ndarray:
    xi = rng.normal(size=6)
    xi[3:] *= 1.0 / np.linalg.norm(xi[3:]) * rng.uniform(0.1, 2.5)
    return xi


def test_log_jacobians_match_central_differences(rng: np.random.Generator) -> None:
    for _ in range(10):
        xi = random_twist(rng)
        T = se3.exp(xi)
        def right(d: np.ndarray, T: np.ndarray = T) -> np.ndarray:
            return se3.log(T @ se3.exp(d))

        def left(d: np.ndarray, T: np.ndarray = T) -> np.ndarray:
            return se3.log(se3.exp(d) @ T)

        J_r_num = central_jacobian(right, np.zeros(6))
        J_l_num = central_jacobian(left, np.zeros(6))
        assert np.allclose(J_r_num, se3.right_jacobian_inverse(xi), atol=1e-6)
        assert np.allclose(J_l_num, se3.left_jacobian_inverse(xi), atol=1e-6)


def test_servo_error_jacobian_matches_central_differences(rng: np.random.Generator) -> None:
    law = ServoLaw()
    for _ in range(10):
        T = random_pose(rng, (-3, 3), (-3, 3), yaw_range=(-3.0, 3.0))
        T_goal = random_pose(rng, (-3, 3), (-3, 3), yaw_range=(-3.0, 3.0))

        def err(d: np.ndarray, T: np.ndarray = T, T_goal: np.ndarray = T_goal) -> np.ndarray:
            # Perturb within the heading-only manifold the law sees (x, y, z, yaw).
            d6 = np.array([d[0], d[1], d[2], 0.0, 0.0, d[3]])
            return law.error_twist(T @ se3.exp(d6), T_goal)

        J_num = central_jacobian(err, np.zeros(4))
        J = law.error_jacobian(T, T_goal)[:, [0, 1, 2, 5]]
        assert np.allclose(J_num, J, atol=1e-6)
