"""Analytic Jacobians of the navigation filter against central differences."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from companion.estimation import model
from companion.geometry import frames, se3, so3
from tests.numdiff import central_jacobian

EPS = 1e-6


def random_state(rng: np.random.Generator) -> np.ndarray:
    R = so3.exp(rng.normal(size=3) * 0.6)
    Rc = so3.exp(rng.normal(size=3) * 0.6)
    x = model.new_state(rng.normal(size=3), rng.normal(size=3), R, rng.normal(size=3) * 0.02,
                        rng.normal(size=3) * 0.2)
    x[model.PC_SL] = rng.normal(size=3)
    x[model.RC_SL] = Rc.ravel()
    return x


def numeric_jacobian(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray, n_out: int, n_in: int) -> np.ndarray:
    """d fun(x [+] eps) / d eps (n_out, n_in) by central differences over the first n_in error coordinates."""

    def on_error(eps: np.ndarray) -> np.ndarray:
        e = np.zeros(model.ERROR_SIZE)
        e[:n_in] = eps
        return fun(model.boxplus(x, e))

    J = central_jacobian(on_error, np.zeros(n_in), EPS)
    assert J.shape == (n_out, n_in)
    return J


def test_boxplus_boxminus_round_trip() -> None:
    rng = np.random.default_rng(0)
    x = random_state(rng)
    dx = rng.normal(size=model.ERROR_SIZE) * 0.3
    np.testing.assert_allclose(model.boxminus(model.boxplus(x, dx), x), dx, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dt", [0.005, 0.02])
def test_propagation_jacobian(seed: int, dt: float) -> None:
    rng = np.random.default_rng(seed)
    x0 = random_state(rng)
    gyro = rng.normal(size=3) * 1.5
    accel = rng.normal(size=3) * 3.0 + np.array([0.0, 0.0, -9.8])
    F = model.new_transition()
    # The buffer is reused: a first call with other inputs must not leak into the second.
    model.propagate_in_place(x0.copy(), -gyro, 2 * accel, 3 * dt, 9.80665, F)
    x1 = x0.copy()
    model.propagate_in_place(x1, gyro, accel, dt, 9.80665, F)

    def prop(x: np.ndarray) -> np.ndarray:
        y = x.copy()
        model.propagate_in_place(y, gyro, accel, dt, 9.80665, model.new_transition())
        return model.boxminus(y, x1)

    F_num = numeric_jacobian(prop, x0, 21, 21)
    np.testing.assert_allclose(F, F_num, atol=1e-8)
    # The clone does not move and does not depend on the navigation states.
    np.testing.assert_array_equal(x1[21:], x0[21:])


def test_propagation_small_and_zero_rotation() -> None:
    """The Taylor branch (|w dt| < 1e-4) and exactly zero rate agree with the closed form."""
    x0 = model.new_state(np.zeros(3), np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3))
    for w in (np.zeros(3), np.array([1e-4, -2e-4, 3e-5]), np.array([0.3, -0.2, 0.1])):
        x = x0.copy()
        F = model.new_transition()
        model.propagate_in_place(x, w, np.array([0.0, 0.0, -9.80665]), 0.01, 9.80665, F)
        np.testing.assert_allclose(model.rotation(x), so3.exp(w * 0.01), atol=1e-15)
        np.testing.assert_allclose(F[6:9, 9:12], -0.01 * so3.right_jacobian(w * 0.01), atol=1e-15)


def test_propagation_matches_closed_form_for_constant_rates() -> None:
    """Constant body rate and zero specific force in NED: exact rotation, free fall under gravity."""
    x = model.new_state(np.zeros(3), np.array([1.0, 0.0, 0.0]), np.eye(3), np.zeros(3), np.zeros(3))
    F = model.new_transition()
    w = np.array([0.0, 0.0, 0.5])
    for _ in range(100):
        model.propagate_in_place(x, w, np.zeros(3), 0.01, 9.80665, F)
    np.testing.assert_allclose(model.rotation(x), so3.exp(w * 1.0), atol=1e-12)
    np.testing.assert_allclose(x[model.P_SL], [1.0, 0.0, 0.5 * 9.80665], atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_absolute_pose_jacobian(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = random_state(rng)
    T_meas = se3.make(model.rotation(x), x[model.P_SL]) @ se3.exp(rng.normal(size=6) * 0.3)
    _, H = model.absolute_pose_residual(x, T_meas[:3, :3], T_meas[:3, 3])
    H_num = -numeric_jacobian(lambda y: model.absolute_pose_residual(y, T_meas[:3, :3], T_meas[:3, 3])[0], x, 6, 21)
    np.testing.assert_allclose(H, H_num, atol=1e-7)


def test_absolute_pose_residual_is_the_right_perturbation_twist() -> None:
    """For a small body-frame twist d: T_meas = T exp(d) gives r ~= d (to first order)."""
    rng = np.random.default_rng(5)
    x = random_state(rng)
    d = rng.normal(size=6) * 1e-4
    T_meas = se3.make(model.rotation(x), x[model.P_SL]) @ se3.exp(d)
    r, _ = model.absolute_pose_residual(x, T_meas[:3, :3], T_meas[:3, 3])
    np.testing.assert_allclose(r, d, atol=1e-7)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_relative_pose_jacobian(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = random_state(rng)
    z = rng.normal(size=3) * 0.2
    _, H = model.relative_pose_residual(x, *z)
    H_num = -numeric_jacobian(lambda y: model.relative_pose_residual(y, *z)[0], x, 3, 21)
    np.testing.assert_allclose(H, H_num, atol=1e-7)


def test_relative_yaw_residual_wraps() -> None:
    x = model.new_state(np.zeros(3), np.zeros(3), frames.rotation_from_euler_zyx(0.0, 0.0, 3.1), np.zeros(3),
                        np.zeros(3))
    x[model.RC_SL] = frames.rotation_from_euler_zyx(0.0, 0.0, -3.1).ravel()
    r, _ = model.relative_pose_residual(x, 0.0, 0.0, 6.2 - 2 * np.pi)
    assert abs(r[2]) < 1e-9


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_range_jacobian(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = random_state(rng)
    x[model.R_SL] = frames.rotation_from_euler_zyx(*(rng.normal(size=3) * 0.3)).ravel()
    x[2] = -3.0
    _, H = model.range_residual(x, 2.9, 0.0)
    H_num = -numeric_jacobian(lambda y: model.range_residual(y, 2.9, 0.0)[0], x, 1, 21)
    np.testing.assert_allclose(H, H_num, atol=1e-7)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_euler_rate_matrix(seed: int) -> None:
    """E maps a right attitude perturbation to (roll, pitch, yaw) differences."""
    rng = np.random.default_rng(seed)
    R = frames.rotation_from_euler_zyx(*(rng.uniform(-1.0, 1.0, 3)))
    E_num = np.zeros((3, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = EPS
        d = frames.euler_zyx_from_rotation(R @ so3.exp(e)) - frames.euler_zyx_from_rotation(R @ so3.exp(-e))
        E_num[:, i] = frames.wrap_angle(d) / (2 * EPS)
    np.testing.assert_allclose(model.euler_rate_matrix(R), E_num, atol=1e-7)


def test_body_to_error_pose_covariance_matches_sampling() -> None:
    """Samples T exp(d) with d ~ N(0, C) have (dp_ned, dtheta) covariance J C J^T."""
    rng = np.random.default_rng(3)
    R = so3.exp(rng.normal(size=3))
    T = se3.make(R, rng.normal(size=3))
    A = rng.normal(size=(6, 6)) * 0.01
    C = A @ A.T + np.eye(6) * 1e-5
    d = rng.multivariate_normal(np.zeros(6), C, size=20000)
    Ts = T @ se3.exp(d)
    errs = np.concatenate([Ts[:, :3, 3] - T[:3, 3], so3.log(R.T @ Ts[:, :3, :3])], axis=1)
    expected = model.body_to_error_pose_covariance(R, C)
    # Whitened: L^-1 cov L^-T ~= I within the sampling error (~ sqrt(2 / n) = 0.01).
    L_inv = np.linalg.inv(np.linalg.cholesky(expected))
    np.testing.assert_allclose(L_inv @ np.cov(errs.T) @ L_inv.T, np.eye(6), atol=0.04)
    # A wrong frame (body instead of NED for dp) is far outside that tolerance.
    wrong = C.copy()
    assert np.abs(L_inv @ wrong @ L_inv.T - np.eye(6)).max() > 0.2


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 1.4e-3, 0.3, 2.0, np.pi - 0.2, np.pi - 1e-3, np.pi - 1e-7])
def test_fast_log_and_left_jacobian_inverse_match_the_geometry_package(angle: float) -> None:
    rng = np.random.default_rng(int(angle * 1000))
    axis = rng.normal(size=3)
    w = axis / np.linalg.norm(axis) * angle
    R = so3.exp(w)
    np.testing.assert_allclose(model.log_so3(R), so3.log(R), atol=1e-9)
    if angle < 3.0:
        np.testing.assert_allclose(model.left_jacobian_inverse_so3(w), so3.left_jacobian_inverse(w), atol=1e-12)
