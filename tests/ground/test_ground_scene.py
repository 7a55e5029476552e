"""The ground renderer: exact plane homography, camera mount, distortion, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import frames, se3
from companion.sim.ground_scene import GroundScene, loop_trajectory
from companion.vision.ground import PlanarBaseline

CAM = PinholeCamera(width=320, height=240, fx=260.0, fy=260.0, cx=159.5, cy=119.5)


def _dot_texture() -> np.ndarray:
    """A tile with one smooth bright blob at its centre: identical under every flip/rotation."""
    ys, xs = np.mgrid[0:65, 0:65]
    tile: np.ndarray = np.rint(255 * np.exp(-((xs - 32.0) ** 2 + (ys - 32.0) ** 2) / (2 * 3.0**2))).astype(np.uint8)
    return tile


def _expected_pixel(scene: GroundScene, cam: PinholeCamera, pose: tuple[float, ...], uv_tex: np.ndarray) -> np.ndarray:
    """Independent path: texture pixel -> NED point -> camera frame -> cam.project (with distortion)."""
    ne = scene.texture_to_ned() @ np.array([uv_tex[0], uv_tex[1], 1.0])
    T_ned_cam = scene.T_ned_cam(*pose)
    p_cam = se3.act(se3.inverse(T_ned_cam), np.array([ne[0], ne[1], 0.0]))
    uv: np.ndarray = cam.project(p_cam)
    return uv


@pytest.mark.parametrize("distorted", [False, True])
def test_rendered_blob_lands_where_the_camera_projects_it(distorted: bool) -> None:
    cam = CAM if not distorted else PinholeCamera(320, 240, 260.0, 260.0, 159.5, 119.5, dist=(-0.15, 0.03, 0, 0, 0))
    T_body_cam = se3.make(frames.rotation_from_euler_zyx(0.05, -0.1, 0.2) @ frames.R_BODY_CAM_DEFAULT, [0.1, 0, 0.05])
    scene = GroundScene(
        cam,
        texture=_dot_texture(),
        metres_per_pixel=0.004,
        north_range_m=(-2, 2),
        east_range_m=(-2, 2),
        T_body_cam=T_body_cam,
    )
    pose = (0.13, -0.07, 0.9, 0.06, -0.04, 0.7)
    img = scene.render(*pose).astype(np.float64)
    checked = 0
    for i in range(0, 62):
        for j in range(0, 62):
            uv = _expected_pixel(scene, cam, pose, np.array([32.0 + 65 * j, 32.0 + 65 * i]))
            if not cam.in_image(uv[None], margin_px=40)[0]:  # strong distortion skews blobs at the rim
                continue
            u, v = round(uv[0]), round(uv[1])
            win = img[v - 10 : v + 11, u - 10 : u + 11]
            win = win - np.median(win)  # the equalized tile has a uniform background
            win[win < 0] = 0.0
            ys, xs = np.mgrid[-10:11, -10:11]
            centroid = np.array([(xs * win).sum(), (ys * win).sum()]) / win.sum()
            np.testing.assert_allclose(np.array([u, v]) + centroid, uv, atol=0.1)
            checked += 1
    assert checked >= 4


def test_render_is_deterministic_and_noise_follows_the_seed() -> None:
    a = GroundScene(CAM, texture="grass", north_range_m=(-2, 2), east_range_m=(-2, 2), seed=5)
    b = GroundScene(CAM, texture="grass", north_range_m=(-2, 2), east_range_m=(-2, 2), seed=5)
    c = GroundScene(CAM, texture="grass", north_range_m=(-2, 2), east_range_m=(-2, 2), seed=6)
    args = (0.1, 0.2, 1.0, 0.02, -0.01, 0.5)
    assert np.array_equal(a.render(*args, noise_std=3.0, seed=1), b.render(*args, noise_std=3.0, seed=1))
    assert not np.array_equal(a.render(*args, noise_std=3.0, seed=1), a.render(*args, noise_std=3.0, seed=2))
    assert not np.array_equal(a.render(*args), c.render(*args))  # another tiling
    img = a.render(*args)
    assert img.shape == (240, 320) and img.dtype == np.uint8 and img.std() > 10


def test_exposure_and_blur() -> None:
    scene = GroundScene(CAM, texture="gravel", north_range_m=(-2, 2), east_range_m=(-2, 2))
    base = scene.render(0.0, 0.0, 1.0).astype(np.float64)
    bright = scene.render(0.0, 0.0, 1.0, gain=1.2, offset=10.0).astype(np.float64)
    assert bright.mean() > base.mean() + 15
    blurred = scene.render(0.0, 0.0, 1.0, blur_sigma_px=3.0).astype(np.float64)
    assert np.abs(np.diff(blurred, axis=1)).mean() < 0.5 * np.abs(np.diff(base, axis=1)).mean()


def test_bad_arguments() -> None:
    with pytest.raises(InputError, match="texture"):
        GroundScene(CAM, texture="marble")
    with pytest.raises(InputError, match="metres_per_pixel"):
        GroundScene(CAM, metres_per_pixel=0.0)
    scene = GroundScene(CAM, north_range_m=(-1, 1), east_range_m=(-1, 1))
    with pytest.raises(InputError, match="height_m"):
        scene.render(0.0, 0.0, -1.0)


def test_loop_trajectory_shape() -> None:
    tr = loop_trajectory(2, rate_hz=20.0, seconds_per_loop=20.0, seed=1)
    assert len(tr) == round((2 * 20.0 + 4.0) * 20.0)
    assert tr.x_m.max() - tr.x_m.min() == pytest.approx(5.6, abs=0.05)
    assert tr.y_m.max() - tr.y_m.min() == pytest.approx(2.8, abs=0.05)
    assert tr.height_m.min() >= 1.0 and tr.height_m.max() <= 1.5
    assert np.abs(tr.roll_rad).max() < math.radians(10) and np.abs(tr.pitch_rad).max() < math.radians(10)
    hover = loop_trajectory(0, seconds_per_loop=5.0, seed=2)
    assert np.ptp(hover.x_m) < 0.5


def test_planar_baseline_pure_translation() -> None:
    scene = GroundScene(CAM, texture="gravel", north_range_m=(-2, 2), east_range_m=(-2, 2), seed=1)
    base = PlanarBaseline(CAM)
    base.reset(0.0, 0.0, 0.4)
    for k in range(11):
        est = base.update(scene.render(0.02 * k, -0.01 * k, 1.0, 0.0, 0.0, 0.4), 1.0)
    assert est.ok
    assert est.x_m == pytest.approx(0.2, abs=0.005) and est.y_m == pytest.approx(-0.1, abs=0.005)
    assert est.yaw_rad == pytest.approx(0.4, abs=math.radians(0.2))
