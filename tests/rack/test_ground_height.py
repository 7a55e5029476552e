"""The ground's height from long sideways baselines: derivative, fit, outlier test, filter, and in the tracker."""

from __future__ import annotations

import numpy as np
import pytest

from companion import jit
from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import se3, so3
from companion.vision.rack import ground_height_jit
from companion.vision.rack.ground_height import (
    MEMORY,
    GroundHeightFit,
    across_residuals,
    fit_ground_height,
    off_ground,
    rotation_derivative,
    update_ground_height,
)
from tests.numdiff import central_jacobian

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def _two_views(rng: np.random.Generator, shift_m: tuple[float, float], n: int = 60, z_true: float = -2.0,
               noise_px: float = 0.2) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ground points at z_true seen from an anchor pose and from the anchor moved by `shift_m` (rack x, y):
    (current pose, anchor centres (n, 3), anchor rays (n, 3), current pixels (n, 2), the points (n, 3))."""
    T_a = se3.make(so3.exp(np.radians([0.4, -0.3, 3.0])) @ R_DOWN, [0.5, 4.0, 2.4])
    T_b = se3.make(so3.exp(np.radians([-0.2, 0.5, 2.0])) @ R_DOWN, [0.5 + shift_m[0], 4.0 + shift_m[1], 2.38])
    uv_a = rng.uniform([40, 40], [680, 440], (n, 2))
    d = CAM.unproject(uv_a) @ T_a[:3, :3].T
    X = T_a[:3, 3] + ((z_true - T_a[2, 3]) / d[:, 2])[:, None] * d
    uv_b = CAM.project((X - T_b[:3, 3]) @ T_b[:3, :3]) + rng.normal(0.0, noise_px, (n, 2))
    return T_b, np.tile(T_a[:3, 3], (n, 1)), d, uv_b, X


def test_across_residual_derivative_matches_central_differences(rng: np.random.Generator) -> None:
    T, o, d, uv, _ = _two_views(rng, (0.3, 0.1), n=8)
    uv = uv + rng.normal(0.0, 3.0, uv.shape)  # away from the solution, where the derivative matters
    for z in (-2.6, -1.7):
        _, de, ok, direction = across_residuals(T, CAM, o, d, uv, z)
        assert ok.all()
        np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0)

        def e_at(p: np.ndarray, held: np.ndarray = direction) -> np.ndarray:
            return across_residuals(T, CAM, o, d, uv, float(p[0]), held)[0]

        num = central_jacobian(e_at, np.array([z]))
        np.testing.assert_allclose(de, num[:, 0], rtol=1e-6, atol=1e-7)


def test_rotation_derivative_matches_central_differences(rng: np.random.Generator) -> None:
    T, o, d, uv, _ = _two_views(rng, (0.3, 0.1), n=8)
    uv = uv + rng.normal(0.0, 3.0, uv.shape)
    for z in (-2.6, -1.7):
        _, _, ok, direction = across_residuals(T, CAM, o, d, uv, z)
        analytic = rotation_derivative(T, CAM, o, d, z, direction)

        def e_at(w: np.ndarray, held: np.ndarray = direction, z_m: float = z) -> np.ndarray:
            T_w = T.copy()
            T_w[:3, :3] = T[:3, :3] @ so3.exp(w)
            return across_residuals(T_w, CAM, o, d, uv, z_m, held)[0]

        num = central_jacobian(e_at, np.zeros(3))
        assert ok.all()
        np.testing.assert_allclose(analytic, num, rtol=1e-5, atol=1e-6)


def test_a_roll_between_the_two_poses_does_not_pass_for_a_height(rng: np.random.Generator) -> None:
    """The current pose given 0.15 deg of roll about the pipes (rack y) off the pose that saw the points, over a
    15 cm baseline: fitted as a height alone (the poses' attitudes taken as they are) that roll reads as a
    height 0.3 m off, since to first order its flow is the height error's; the fit's own rotation takes it,
    and the height comes out within 6 cm (400 points of 0.2 px noise: 2.8 cm of spread over 30 seeds, unbiased,
    with or without the roll)."""
    T, o, d, uv, _ = _two_views(rng, (0.15, 0.05), n=400)
    T_rolled = T.copy()
    T_rolled[:3, :3] = so3.exp([0.0, np.radians(0.15), 0.0]) @ T[:3, :3]
    fit = fit_ground_height(T_rolled, CAM, o, d, uv, z0_m=-3.0, min_baseline_m=0.1)
    held = fit_ground_height(T_rolled, CAM, o, d, uv, z0_m=-3.0, min_baseline_m=0.1, estimate_rotation=False)
    assert fit is not None and held is not None
    assert abs(fit.z_m + 2.0) < 0.06
    assert abs(held.z_m + 2.0) > 0.3
    # at the true pose the two agree
    exact = fit_ground_height(T, CAM, o, d, uv, z0_m=-3.0, min_baseline_m=0.1, estimate_rotation=False)
    assert exact is not None and abs(exact.z_m + 2.0) < 0.02


def test_a_sideways_baseline_fixes_the_height_from_a_wrong_start(rng: np.random.Generator) -> None:
    """30 cm across the pipes, 200 points with 0.2 px of noise: the plane's height within 4 cm from a start 1.5 m
    off (the fit's own rotation leaves it 1.5 cm of spread over seeds); the variance is at least what a 5 mm
    relative pose error makes over the baseline (the points' number cannot beat the poses' shared error)."""
    T, o, d, uv, _ = _two_views(rng, (0.3, 0.05), n=200)
    fit = fit_ground_height(T, CAM, o, d, uv, z0_m=-3.5, min_baseline_m=0.1)
    assert fit is not None
    assert abs(fit.z_m + 2.0) < 0.04
    assert fit.n_points >= 185
    depth = 2.4 + 2.0
    assert np.sqrt(fit.var_m2) >= 0.99 * depth * 0.005 / 0.3


def test_motion_along_the_pipes_alone_gives_no_height(rng: np.random.Generator) -> None:
    """Along the pipes the tracker's own translation came from this ground's flow: no fit from it."""
    T, o, d, uv, _ = _two_views(rng, (0.02, 0.5))
    assert fit_ground_height(T, CAM, o, d, uv, z0_m=-3.5, min_baseline_m=0.1) is None


def test_points_on_a_nearer_structure_neither_move_the_fit_nor_pass_the_test(rng: np.random.Generator) -> None:
    """A third of the corners on an overhead beam 1.2 m below the camera: the biweight fits the ground through
    them, and from their anchors they miss the ground's projection by far more than the gate plus 30 % of the
    parallax, while the ground's points do not."""
    T, o, d, uv, _ = _two_views(rng, (0.3, 0.05), n=300)
    beam = np.arange(300) < 100
    T_a_o = o[0]
    # the beam's corners: the same anchor rays, met at z = 1.2 instead of the ground
    Xb = T_a_o + ((1.2 - T_a_o[2]) / d[beam, 2])[:, None] * d[beam]
    uv = uv.copy()
    uv[beam] = CAM.project((Xb - T[:3, 3]) @ T[:3, :3])
    fit = fit_ground_height(T, CAM, o, d, uv, z0_m=-2.5, min_baseline_m=0.1)
    assert fit is not None and abs(fit.z_m + 2.0) < 0.04
    flagged = off_ground(T, CAM, o, d, uv, fit.z_m, gate_px=4.0)
    assert flagged[beam].all()
    assert not flagged[~beam].any()


def test_the_filter_discounts_each_fit_gates_outliers_and_restarts_after_a_run_of_them() -> None:
    fit = GroundHeightFit(z_m=-2.0, var_m2=0.01, n_points=40)
    z, var, rej = update_ground_height(-2.5, 0.1, fit, 0)
    k = 0.1 / (0.1 + MEMORY * 0.01)
    assert z == pytest.approx(-2.5 + k * 0.5) and var == pytest.approx((1 - k) * 0.1) and rej == 0
    far = GroundHeightFit(z_m=-0.5, var_m2=0.0001, n_points=40)  # a beam: 1.5 m off, far outside 3 sigma
    z, var, rej = update_ground_height(-2.0, 0.0004, far, 0)
    assert (z, var, rej) == (-2.0, 0.0004, 1)
    for _ in range(23):
        z, var, rej = update_ground_height(z, var, far, rej)
    assert rej == 24 and z == -2.0
    z, var, rej = update_ground_height(z, var, far, rej)  # the 25th in a row: the ground has changed
    assert (z, var, rej) == (-0.5, pytest.approx(MEMORY * 0.0001), 0)


def test_the_tracker_learns_the_grounds_height_flying_across_the_pipes() -> None:
    """Back and forth across three pipes over natural ground 2 m below their support: after the settling frames
    the long-baseline estimate holds the height within 10 cm, where the frame-to-frame z_g started from a
    first guess over a metre off. Off (`ground_height_baseline_m` 0) there is no estimate; a negative
    baseline or floor is refused."""
    from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
    from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig

    model = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.1], length=10.0)
    scene = FieldRackScene(model, seed=6, config=FieldSceneConfig(ground="natural", num_spots=30, ground_z_m=-2.0,
                                                                  jpeg_quality=0))
    T0 = se3.make(so3.exp(np.radians([0.3, -0.2, 2.0])) @ R_DOWN, [0.25, 4.0, 2.3])
    estimates = {}
    for baseline in (0.1, 0.0):
        tr = RackTracker(model, CAM, RackTrackerConfig(ground_height_baseline_m=baseline))
        tr.reset(T0)
        rng = np.random.default_rng(7)
        first_guess = None
        for k in range(110):
            x = 0.3 * np.sin(2 * np.pi * k / 80.0)  # +-30 cm across the pipes, up to 0.6 m/s
            T_k = se3.make(T0[:3, :3], T0[:3, 3] + [x, 0.0, 0.0])
            assert tr.track(scene.render(T_k, CAM, noise_std=3.0, rng=rng), k / 25.0).ok
            if first_guess is None:
                first_guess = tr._z_g
        estimates[baseline] = (first_guess, tr._zf, np.sqrt(tr._zf_var))
    first_guess, zf, zf_std = estimates[0.1]
    assert first_guess is not None and abs(first_guess + 2.0) > 1.0
    assert zf is not None and abs(zf + 2.0) < 0.1 and zf_std < 0.1
    assert estimates[0.0][1] is None
    with pytest.raises(InputError, match="ground_height_baseline_m"):
        RackTrackerConfig(ground_height_baseline_m=-0.1)
    with pytest.raises(InputError, match="ground_height_floor_m"):
        RackTrackerConfig(ground_height_floor_m=-1.0)


@pytest.mark.skipif(ground_height_jit.kernels() is None, reason="numba not available here")
@pytest.mark.parametrize("estimate_rotation", [True, False])
def test_the_compiled_fit_gives_the_numpy_fits_bits(rng: np.random.Generator, estimate_rotation: bool,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """`ground_height_jit._fit` against `_iterate` on 20 seeded two-view cases of up to `MAX_POINTS` points
    (outliers among them, some cases with too few points left on the baseline): the same fits to the bit."""
    fits = 0
    for case in range(20):
        n = int(rng.integers(6, ground_height_jit.MAX_POINTS + 1))
        T, o, d, uv, _ = _two_views(rng, (rng.uniform(0.05, 0.4), rng.uniform(-0.2, 0.2)), n=n)
        uv[: n // 8] += rng.normal(0.0, 8.0, (n // 8, 2))  # outliers: zero biweights
        o = o + np.column_stack([rng.uniform(-0.3, 0.3, n), np.zeros(n), np.zeros(n)])  # baselines differ
        args = (T, CAM, o, d, uv, float(rng.uniform(-3.5, -1.0)), 0.1, estimate_rotation)
        compiled = fit_ground_height(*args)
        with monkeypatch.context() as m:
            m.setattr(jit, "_compiled", {**jit._compiled, "rack.ground_height": None})
            plain = fit_ground_height(*args)
        assert compiled == plain, case
        fits += compiled is not None
    assert 10 <= fits < 20  # both outcomes exercised


def test_the_fits_scalar_steps_agree_with_numpy(rng: np.random.Generator) -> None:
    """`solve4` against `np.linalg.solve` / `inv` and `turn` against `so3.exp` (small and large angles)."""
    for _ in range(10):
        M = rng.normal(size=(4, 4))
        H = M @ M.T + np.eye(4)
        b = rng.normal(size=4)
        step = np.empty(4)
        var = ground_height_jit.solve4(H, b, step)
        np.testing.assert_allclose(step, -np.linalg.solve(H, b), rtol=1e-10, atol=1e-12)
        assert var == pytest.approx(np.linalg.inv(H)[0, 0], rel=1e-10)
        for scale in (1e-5, 0.3):
            w = rng.normal(size=3) * scale
            R = so3.exp(rng.normal(size=3))
            R_turned = R.copy()
            ground_height_jit.turn(R_turned, *w)
            np.testing.assert_allclose(R_turned, R @ so3.exp(w), rtol=0.0, atol=1e-14)
    assert np.isnan(ground_height_jit.solve4(np.zeros((4, 4)), np.ones(4), np.empty(4)))
