"""SE(3): round trips over 10,000 seeded twists, singular cases, adjoint identity, Jacobians."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.errors import InputError
from companion.geometry import se3, so3
from tests.numdiff import central_jacobian

ANGLES = [0.0, 1e-12, 1e-8, 1e-5, 1e-3, 0.7, np.pi - 1e-6, np.pi]
AXES = [np.array([0.0, 0.0, 1.0]), np.array([1.0, 2.0, -3.0]) / np.sqrt(14.0), np.array([1.0, 1.0, 1.0]) / np.sqrt(3)]


def random_twists(rng: np.random.Generator, n: int, max_angle: float = np.pi - 1e-9) -> np.ndarray:
    xi = np.empty((n, 6))
    xi[:, :3] = rng.normal(scale=2.0, size=(n, 3))
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    xi[:, 3:] = axes * rng.uniform(0.0, max_angle, size=(n, 1))
    return xi


def singular_twists() -> np.ndarray:
    v = np.array([0.4, -1.2, 0.3])
    return np.array([np.concatenate([v, a * ax]) for a in ANGLES for ax in AXES])


def test_hat_vee(rng: np.random.Generator) -> None:
    xi = rng.normal(size=(20, 6))
    assert np.allclose(se3.vee(se3.hat(xi)), xi)
    G = se3.generators()
    assert G.shape == (6, 4, 4)
    assert np.allclose(se3.vee(G), np.eye(6))


def test_log_exp_roundtrip_10000_including_singular(rng: np.random.Generator) -> None:
    xi = np.concatenate([random_twists(rng, 10_000 - len(singular_twists())), singular_twists()])
    xi_back = se3.log(se3.exp(xi))
    err = np.abs(xi_back - xi).max(axis=1)
    at_pi = np.isclose(np.linalg.norm(xi[:, 3:], axis=1), np.pi)
    assert err[~at_pi].max() < 1e-12
    # At exactly pi the rotation axis sign is ambiguous: compare on the group.
    assert np.abs(se3.exp(xi_back[at_pi]) - se3.exp(xi[at_pi])).max() < 1e-12


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    st.lists(st.floats(-5.0, 5.0, allow_nan=False), min_size=3, max_size=3),
    st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=3, max_size=3),
    st.floats(0.0, np.pi - 1e-7),
)
def test_roundtrip_property(v: list[float], axis: list[float], angle: float) -> None:
    a = np.asarray(axis)
    n = np.linalg.norm(a)
    w = np.zeros(3) if n < 1e-6 else a / n * angle
    xi = np.concatenate([np.asarray(v), w])
    assert np.abs(se3.log(se3.exp(xi)) - xi).max() < 1e-12


def test_exp_log_on_group(rng: np.random.Generator) -> None:
    T = se3.exp(random_twists(rng, 2000))
    assert np.abs(se3.exp(se3.log(T)) - T).max() < 1e-12


def test_exp_matches_matrix_exponential(rng: np.random.Generator) -> None:
    from scipy.linalg import expm

    for xi in random_twists(rng, 20):
        assert np.abs(se3.exp(xi) - expm(se3.hat(xi))).max() < 1e-12


def test_inverse_and_compose(rng: np.random.Generator) -> None:
    T = se3.exp(random_twists(rng, 100))
    assert np.abs(se3.compose(T, se3.inverse(T)) - np.eye(4)).max() < 1e-12
    p = rng.normal(size=(100, 3))
    assert np.allclose(se3.act(se3.inverse(T), se3.act(T, p)), p)


def test_adjoint_identity(rng: np.random.Generator) -> None:
    T = se3.exp(random_twists(rng, 200))
    xi = random_twists(rng, 200, max_angle=2.0)
    lhs = T @ se3.exp(xi) @ se3.inverse(T)
    rhs = se3.exp(np.einsum("nij,nj->ni", se3.adjoint(T), xi))
    assert np.abs(lhs - rhs).max() < 1e-11


def test_curly_hat_is_adjoint_derivative(rng: np.random.Generator) -> None:
    xi = rng.normal(size=6)
    eta = rng.normal(size=6)
    num = central_jacobian(lambda t: se3.adjoint(se3.exp(t[0] * xi)) @ eta, np.zeros(1))[:, 0]
    assert np.abs(se3.curly_hat(xi) @ eta - num).max() < 1e-7


def _jacobian_points(rng: np.random.Generator) -> list[np.ndarray]:
    v = np.array([0.5, -0.2, 1.1])
    pts = [np.concatenate([v, ax * a]) for ax in AXES[1:] for a in (0.0, 1e-8, 1e-4, 0.5, 2.8, np.pi - 1e-3)]
    return pts + list(random_twists(rng, 10, max_angle=3.0))


def test_left_right_jacobians_numeric(rng: np.random.Generator) -> None:
    for xi in _jacobian_points(rng):
        T = se3.exp(xi)
        Ti = se3.inverse(T)
        Jl_num = central_jacobian(lambda d, xi=xi, Ti=Ti: se3.log(se3.exp(xi + d) @ Ti), np.zeros(6))
        Jr_num = central_jacobian(lambda d, xi=xi, Ti=Ti: se3.log(Ti @ se3.exp(xi + d)), np.zeros(6))
        assert np.abs(se3.left_jacobian(xi) - Jl_num).max() < 1e-6
        assert np.abs(se3.right_jacobian(xi) - Jr_num).max() < 1e-6


def test_inverse_jacobians_numeric(rng: np.random.Generator) -> None:
    for xi in _jacobian_points(rng):
        T = se3.exp(xi)
        Jli_num = central_jacobian(lambda d, T=T: se3.log(se3.exp(d) @ T), np.zeros(6))
        Jri_num = central_jacobian(lambda d, T=T: se3.log(T @ se3.exp(d)), np.zeros(6))
        assert np.abs(se3.left_jacobian_inverse(xi) - Jli_num).max() < 1e-6
        assert np.abs(se3.right_jacobian_inverse(xi) - Jri_num).max() < 1e-6
        assert np.abs(se3.left_jacobian_inverse(xi) @ se3.left_jacobian(xi) - np.eye(6)).max() < 1e-12


def test_jacobian_blocks_relation(rng: np.random.Generator) -> None:
    # J_l(xi) = Ad(exp(xi)) J_r(xi)
    for xi in random_twists(rng, 20):
        assert np.abs(se3.left_jacobian(xi) - se3.adjoint(se3.exp(xi)) @ se3.right_jacobian(xi)).max() < 1e-12


def test_rotation_block_is_so3(rng: np.random.Generator) -> None:
    xi = random_twists(rng, 50)
    assert np.abs(se3.exp(xi)[:, :3, :3] - so3.exp(xi[:, 3:])).max() == 0.0


def test_bad_input() -> None:
    with pytest.raises(InputError, match="xi"):
        se3.exp(np.zeros(5))
    with pytest.raises(InputError, match="T"):
        se3.log(np.eye(3))


def test_exp_one_matches_exp() -> None:
    rng = np.random.default_rng(41)
    twists = [np.zeros(6), np.array([0.1, -0.2, 0.3, 0.0, 0.0, 1e-9]), np.array([0.0, 0.0, 0.0, 5e-4, -3e-4, 2e-4])]
    twists += [rng.normal(0.0, s, 6) for s in (1e-4, 1e-3, 0.01, 0.3, 1.0) for _ in range(3)]
    twists.append(np.array([0.2, 0.1, -0.3, np.pi - 1e-6, 0.0, 0.0]))
    for xi in twists:
        assert np.allclose(se3.exp_one(xi), se3.exp(xi), rtol=0.0, atol=1e-15), xi


def test_log_one_equals_log_bit_for_bit() -> None:
    rng = np.random.default_rng(42)
    transforms = [np.eye(4)]
    # every quaternion branch and both angle branches: tiny rotations (series), moderate, near and at pi
    for s in (1e-9, 1e-6, 1e-4, 1e-3, 2e-3, 0.1, 1.0, 3.0):
        transforms += [se3.exp(np.concatenate([rng.normal(0.0, 1.0, 3), rng.normal(0.0, s, 3)])) for _ in range(200)]
    for angle in (np.pi, np.pi - 1e-6, 1e-12):
        for axis in list(np.eye(3)) + [rng.normal(size=3) for _ in range(10)]:
            w = angle * axis / np.linalg.norm(axis)
            transforms.append(se3.exp(np.concatenate([rng.normal(size=3), w])))
    for T in transforms:
        np.testing.assert_array_equal(se3.log_one(T), se3.log(T))
