"""SO(3): exp/log round trips, singular angles, Jacobians vs central differences, scipy oracle."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from companion.errors import InputError
from companion.geometry import so3
from tests.numdiff import central_jacobian

SINGULAR_ANGLES = [0.0, 1e-12, 1e-8, 1e-5, 1e-3, 0.5, 2.0, np.pi - 1e-3, np.pi - 1e-6, np.pi]
SKEW_AXES = [
    np.array([1.0, 0.0, 0.0]),
    np.array([0.0, 0.0, 1.0]),
    np.array([1.0, 2.0, -3.0]) / np.sqrt(14.0),
    np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0),
    np.array([-0.3, 0.9, 0.1]) / np.linalg.norm([-0.3, 0.9, 0.1]),
]


def random_rotvecs(rng: np.random.Generator, n: int, max_angle: float = np.pi - 1e-9) -> np.ndarray:
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(0.0, max_angle, size=(n, 1))


def test_hat_vee_inverse(rng: np.random.Generator) -> None:
    w = rng.normal(size=(50, 3))
    W = so3.hat(w)
    assert np.allclose(W, -np.swapaxes(W, -1, -2))
    assert np.allclose(so3.vee(W), w)
    p = rng.normal(size=(50, 3))
    assert np.allclose(np.einsum("nij,nj->ni", W, p), np.cross(w, p))


def test_exp_matches_scipy(rng: np.random.Generator) -> None:
    w = random_rotvecs(rng, 1000)
    assert np.abs(so3.exp(w) - Rotation.from_rotvec(w).as_matrix()).max() < 1e-14


def test_log_matches_scipy(rng: np.random.Generator) -> None:
    R = Rotation.random(1000, random_state=7).as_matrix()
    ours = so3.log(R)
    theirs = Rotation.from_matrix(R).as_rotvec()
    assert np.abs(ours - theirs).max() < 1e-12


def test_quaternion_matches_scipy(rng: np.random.Generator) -> None:
    R = Rotation.random(500, random_state=3)
    q_xyzw = R.as_quat()
    q_wxyz = np.concatenate([q_xyzw[:, 3:], q_xyzw[:, :3]], axis=1)
    q_wxyz *= np.sign(q_wxyz[:, :1])
    assert np.abs(so3.quaternion_from_matrix(R.as_matrix()) - q_wxyz).max() < 1e-13
    assert np.abs(so3.matrix_from_quaternion(q_wxyz) - R.as_matrix()).max() < 1e-14


def test_log_exp_roundtrip_random(rng: np.random.Generator) -> None:
    w = random_rotvecs(rng, 10_000)
    assert np.abs(so3.log(so3.exp(w)) - w).max() < 1e-12


@pytest.mark.parametrize("angle", SINGULAR_ANGLES)
@pytest.mark.parametrize("axis", range(len(SKEW_AXES)))
def test_singular_angles(angle: float, axis: int) -> None:
    w = SKEW_AXES[axis] * angle
    R = so3.exp(w)
    assert np.all(np.isfinite(R))
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-15 * 10
    w_back = so3.log(R)
    assert np.all(np.isfinite(w_back))
    if angle < np.pi:
        assert np.abs(w_back - w).max() < 1e-12
    else:
        # At pi both +w and -w are logarithms; either must map back to R.
        assert min(np.abs(w_back - w).max(), np.abs(w_back + w).max()) < 1e-12
    assert np.abs(so3.exp(w_back) - R).max() < 1e-12


def test_exp_log_roundtrip_on_group() -> None:
    R = Rotation.random(2000, random_state=11).as_matrix()
    assert np.abs(so3.exp(so3.log(R)) - R).max() < 1e-12


def _jacobian_points(rng: np.random.Generator) -> list[np.ndarray]:
    pts = [axis * a for axis in SKEW_AXES[2:4] for a in (0.0, 1e-8, 1e-4, 0.3, 2.5, np.pi - 1e-3)]
    pts += list(random_rotvecs(rng, 10, max_angle=3.0))
    return pts


def test_left_right_jacobians_numeric(rng: np.random.Generator) -> None:
    for w in _jacobian_points(rng):
        R = so3.exp(w)
        # exp(w + d) = exp(J_l d) exp(w)  =>  d/dd log(exp(w + d) R^T) = J_l
        Jl_num = central_jacobian(lambda d, w=w, R=R: so3.log(so3.exp(w + d) @ R.T), np.zeros(3))
        Jr_num = central_jacobian(lambda d, w=w, R=R: so3.log(R.T @ so3.exp(w + d)), np.zeros(3))
        assert np.abs(so3.left_jacobian(w) - Jl_num).max() < 1e-6
        assert np.abs(so3.right_jacobian(w) - Jr_num).max() < 1e-6


def test_inverse_jacobians_numeric(rng: np.random.Generator) -> None:
    for w in _jacobian_points(rng):
        R = so3.exp(w)
        # log(exp(d) R) = w + J_l^-1 d ;  log(R exp(d)) = w + J_r^-1 d
        Jli_num = central_jacobian(lambda d, R=R: so3.log(so3.exp(d) @ R), np.zeros(3))
        Jri_num = central_jacobian(lambda d, R=R: so3.log(R @ so3.exp(d)), np.zeros(3))
        assert np.abs(so3.left_jacobian_inverse(w) - Jli_num).max() < 1e-6
        assert np.abs(so3.right_jacobian_inverse(w) - Jri_num).max() < 1e-6
        assert np.abs(so3.left_jacobian_inverse(w) @ so3.left_jacobian(w) - np.eye(3)).max() < 1e-12


def test_batch_shapes(rng: np.random.Generator) -> None:
    w = rng.normal(size=(4, 5, 3))
    assert so3.exp(w).shape == (4, 5, 3, 3)
    assert so3.log(so3.exp(w)).shape == (4, 5, 3)
    assert so3.left_jacobian(w).shape == (4, 5, 3, 3)


def test_bad_shapes_raise() -> None:
    with pytest.raises(InputError, match="w"):
        so3.exp(np.zeros(4))
    with pytest.raises(InputError, match="NaN"):
        so3.exp(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(InputError):
        so3.matrix_from_quaternion(np.zeros(4))


def test_one_matrix_gives_the_array_codes_bits() -> None:
    """`quaternion_from_matrix` and `log` of one (3, 3) matrix take a scalar path; it must give what the array code
    gives for a stack of one, to the bit: rotations of every size, near pi, and not quite orthonormal."""
    rng = np.random.default_rng(7)
    mats = [so3.exp(rng.normal(size=3) * s) for s in (1e-9, 1e-5, 0.01, 1.0, 3.0) for _ in range(200)]
    mats += [so3.exp(v / np.linalg.norm(v) * (np.pi - 10.0 ** -rng.uniform(0, 8))) for v in rng.normal(size=(200, 3))]
    mats += [R + rng.normal(size=(3, 3)) * 1e-6 for R in mats[:200]] + [np.eye(3)]
    for R in mats:
        np.testing.assert_array_equal(so3.quaternion_from_matrix(R), so3.quaternion_from_matrix(R[None])[0])
        np.testing.assert_array_equal(so3.log(R), so3.log(R[None])[0])
