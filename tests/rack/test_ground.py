"""Ground-plane reference: rows against numeric differences; plane intersection; detection outside the pipes."""

from __future__ import annotations

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import se3, so3
from companion.vision.rack.ground import detect_ground_points, ground_mask, ground_rows, plane_points
from tests.numdiff import central_jacobian

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def test_plane_points_lie_on_the_plane_and_on_their_rays(rng: np.random.Generator) -> None:
    o = np.array([0.5, 4.0, 2.4])
    d = CAM.unproject(rng.uniform([0, 0], [719, 479], (20, 2))) @ (so3.exp([0.05, -0.03, 0.2]) @ R_DOWN).T
    X, dX = plane_points(o, d, -2.0)
    np.testing.assert_allclose(X[:, 2], -2.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(X - o, d), 0.0, atol=1e-12)
    X2, _ = plane_points(o, d, -2.0 + 1e-6)
    np.testing.assert_allclose((X2 - X) / 1e-6, dX, rtol=1e-5)
    up = plane_points(o, -d, -2.0)[0]  # rays pointing up never reach the ground
    assert np.all(np.isnan(up))


def test_ground_rows_match_central_differences(rng: np.random.Generator) -> None:
    T = se3.make(so3.exp(rng.normal(0, 0.05, 3)) @ R_DOWN, [0.6, 4.0, 2.3])
    T_prev = T @ se3.exp(rng.normal(0, 0.02, 6))
    uv_prev = rng.uniform([50, 50], [670, 430], (6, 2))
    d = CAM.unproject(uv_prev) @ T_prev[:3, :3].T
    uv_meas = rng.uniform([50, 50], [670, 430], (6, 2))
    z0 = -2.1

    def residual(p: np.ndarray) -> np.ndarray:
        X, dX = plane_points(T_prev[:3, 3], d, z0 + p[6])
        return ground_rows(T @ se3.exp(p[:6]), CAM, X, dX, uv_meas)[1]

    X, dX = plane_points(T_prev[:3, 3], d, z0)
    A, r = ground_rows(T, CAM, X, dX, uv_meas)
    np.testing.assert_allclose(r, residual(np.zeros(7)))
    # r = measured - predicted, so dr/dp = -(d predicted / dp) = -A.
    np.testing.assert_allclose(-A, central_jacobian(residual, np.zeros(7)), rtol=1e-5, atol=1e-4)


def test_ground_corners_are_found_outside_the_pipes_only(rng: np.random.Generator) -> None:
    gray = np.clip(120 + 40 * rng.standard_normal((240, 360)), 0, 255).astype(np.uint8)
    pipe = np.array([[100.0, 0.0], [180.0, 0.0], [180.0, 239.0], [100.0, 239.0]])
    uv = detect_ground_points(gray, [pipe], np.zeros((0, 2)), 50, 8.0, 6.0, 0.0)
    assert uv.shape[0] == 50
    assert not np.any((uv[:, 0] > 100 - 6) & (uv[:, 0] < 180 + 6))  # the pipe and a 6 px margin around it
    assert np.all((uv >= 10) & (uv <= np.array([349, 229])))


def test_ground_corners_with_a_floor_are_opencvs_then_the_floor(rng: np.random.Generator) -> None:
    # The one-pass detector (`corners.strong_corners`) must give exactly the former two passes: OpenCV's
    # Shi-Tomasi corners (quality 0.01) in the mask, the floor at each, the first max_new kept.
    for k in range(12):
        img = rng.uniform(0, 255, (240, 360)) if k % 3 else np.full((240, 360), 120.0) + rng.normal(0, 3, (240, 360))
        if k % 3 == 0:
            for _ in range(30):
                centre = (int(rng.integers(5, 355)), int(rng.integers(5, 235)))
                cv2.circle(img, centre, 2, float(rng.uniform(30, 90)), -1)
        gray = np.clip(cv2.GaussianBlur(img, (0, 0), 1.0 + 0.2 * k), 0, 255).astype(np.uint8)
        pipes = [np.array([[60.0, 0.0], [110.0, 0.0], [130.0, 239.0], [70.0, 239.0]]) + [90.0 * j, 0.0]
                 for j in range(k % 3)]
        existing = rng.uniform([0, 0], [360, 240], (int(rng.integers(0, 20)), 2))
        max_new, min_d, ratio = int(rng.integers(3, 60)), float(rng.uniform(5.0, 15.0)), float(rng.choice([1.5, 4.0]))
        got = detect_ground_points(gray, pipes, existing, max_new, min_d, 6.0, ratio)
        mask = ground_mask(gray.shape, pipes, 6.0)
        for q in existing:
            cv2.circle(mask, (round(q[0]), round(q[1])), int(min_d), 0, -1)
        found = cv2.goodFeaturesToTrack(gray, maxCorners=2 * max_new, qualityLevel=0.01, minDistance=min_d,
                                        mask=mask, blockSize=7)
        want = np.zeros((0, 2)) if found is None else found.reshape(-1, 2).astype(np.float64)
        ev = cv2.cornerMinEigenVal(gray, 7, ksize=3)
        c = np.rint(want).astype(np.intp)
        want = want[ev[c[:, 1], c[:, 0]] >= ratio * float(np.median(ev[mask > 0]))][:max_new]
        np.testing.assert_array_equal(got, want)


def test_ground_points_earn_their_weight_frame_by_frame() -> None:
    """Each accepted frame a kept ground point has fitted the plane once more (its rows' weight grows
    with that count up to `ground_trust_frames`); a new one starts at 0; a lost frame forgets them."""
    from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
    from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig

    model = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.1], length=10.0)
    scene = FieldRackScene(model, seed=3, config=FieldSceneConfig(ground="natural", num_spots=20, jpeg_quality=0))
    tr = RackTracker(model, CAM, RackTrackerConfig(ground_trust_frames=10))
    rng = np.random.default_rng(3)
    T = se3.make(so3.exp(np.radians([0.3, -0.2, 2.0])) @ R_DOWN, [0.55, 4.0, 2.2])
    tr.reset(T)
    ages = []
    for k in range(6):
        Tk = T @ se3.make(np.eye(3), [0.0, -0.02 * k, 0.0])  # 0.5 m/s along the pipes (camera -y = rack +y)
        assert tr.track(scene.render(Tk, CAM, noise_std=3.0, rng=rng), k / 25.0).ok
        ages.append(tr._ground_age.copy())
    assert ages[0].size and np.all(ages[0] == 0)
    assert ages[-1].max() == 5 and np.median(ages[-1]) >= 3
    tr.track(np.zeros((CAM.height, CAM.width), dtype=np.uint8), 6 / 25.0)  # nothing to see: lost
    assert tr._ground_age.size == 0


def test_a_known_ground_height_holds_the_along_pipe_position_without_texture() -> None:
    """Flying 0.8 m along the pipes with no spot in view only the ground's flow sees the motion, and it
    gives the speed over the ground's depth: with the depth from the first guess (the online estimate
    cannot observe it) the along-pipe position drifts by the guess's error; with `ground_height_m` it holds.
    A ground above the support plane, or a zero std, is refused."""
    import pytest

    from companion.errors import InputError
    from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
    from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig

    model = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.1], length=10.0)
    scene = FieldRackScene(model, seed=4, config=FieldSceneConfig(ground="natural", num_spots=0, ground_z_m=-2.0,
                                                                  jpeg_quality=0))
    T = se3.make(so3.exp(np.radians([0.3, -0.2, 2.0])) @ R_DOWN, [0.55, 3.0, 2.3])
    along_err_m = {}
    for known in (None, -2.0):
        tr = RackTracker(model, CAM, RackTrackerConfig(ground_height_m=known))
        tr.reset(T)
        rng = np.random.default_rng(5)
        for k in range(41):
            T_k = T @ se3.make(np.eye(3), [0.0, -0.02 * k, 0.0])  # 0.5 m/s along the pipes (camera -y = rack +y)
            est = tr.track(scene.render(T_k, CAM, noise_std=3.0, rng=rng), k / 25.0)
        along_err_m[known] = abs(float(est.T_rack_cam[1, 3] - T_k[1, 3]))
    assert along_err_m[-2.0] < 0.02
    assert along_err_m[None] > 3 * along_err_m[-2.0]
    with pytest.raises(InputError, match="ground_height_m"):
        RackTrackerConfig(ground_height_m=0.5)
    with pytest.raises(InputError, match="ground_height_std_m"):
        RackTrackerConfig(ground_height_m=-2.0, ground_height_std_m=0.0)


def test_the_ground_height_is_kept_across_a_reset() -> None:
    """A re-seed (`reset`) forgets the ground points, which belong to the image, but not the ground's height,
    which belongs to the scene (`ground_height_kept_on_reset`); with the option off the next frame starts it
    again from the rough first guess."""
    from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
    from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig

    model = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.1], length=10.0)
    scene = FieldRackScene(model, seed=4, config=FieldSceneConfig(ground="natural", num_spots=20, ground_z_m=-2.0,
                                                                  jpeg_quality=0))
    T = se3.make(so3.exp(np.radians([0.3, -0.2, 2.0])) @ R_DOWN, [0.3, 3.0, 2.3])
    heights = {}
    for kept in (True, False):
        tr = RackTracker(model, CAM, RackTrackerConfig(ground_height_kept_on_reset=kept))
        tr.reset(T)
        rng = np.random.default_rng(6)
        for k in range(60):
            T_k = T @ se3.make(np.eye(3), [0.015 * k, 0.0, 0.0])  # across the pipes: the ground's depth shows
            assert tr.track(scene.render(T_k, CAM, noise_std=3.0, rng=rng), k / 25.0).ok
        z_before = float(tr._z_g)
        tr.reset(T_k)
        assert tr._ground_uv.shape[0] == 0  # the points are the image's: gone
        T_next = T_k @ se3.make(np.eye(3), [0.015, 0.0, 0.0])
        assert tr.track(scene.render(T_next, CAM, noise_std=3.0, rng=rng), 60 / 25.0).ok
        heights[kept] = (z_before, float(tr._z_g))
    (before, after), (_before_off, after_off) = heights[True], heights[False]
    assert abs(before + 2.0) < 0.1  # learnt over the flight across the pipes (-1.995 m when written)
    assert abs(after - before) < 0.05  # kept (the same value when written)
    assert abs(after_off + 2.0) > 1.0  # off: the first guess again (-3.40 m when written)
