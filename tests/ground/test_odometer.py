"""GroundOdometer end to end on rendered real-texture frames: known motions, failures, inputs."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import ConfigError, InputError
from companion.geometry import frames, se3
from companion.sim.ground_scene import GroundScene
from companion.vision.ground import GroundEstimate, GroundOdometer, GroundOdometerConfig

CAM = PinholeCamera(width=376, height=240, fx=225.0, fy=225.0, cx=187.5, cy=119.5)


@pytest.fixture(scope="module")
def scene() -> GroundScene:
    return GroundScene(CAM, texture="gravel", north_range_m=(-3.0, 3.0), east_range_m=(-3.0, 3.0), seed=3)


def _fly(
    odo: GroundOdometer, scene: GroundScene, poses: np.ndarray, rate_hz: float = 20.0, **render: float
) -> Iterator[GroundEstimate]:
    for k, (x, y, h, r, p, yaw) in enumerate(poses):
        img = scene.render(x, y, h, r, p, yaw, seed=k, **render)
        yield odo.update(img, k / rate_hz, h, r, p)


def _run(odo: GroundOdometer, scene: GroundScene, poses: np.ndarray, **render: float) -> list[GroundEstimate]:
    odo.reset(float(poses[0, 0]), float(poses[0, 1]), float(poses[0, 5]))
    return list(_fly(odo, scene, poses, **render))


def test_first_frame_initializes(scene: GroundScene) -> None:
    odo = GroundOdometer(CAM, GroundOdometerConfig())
    odo.reset(x_m=1.0, y_m=-2.0, yaw_rad=0.5)
    est = odo.update(scene.render(1.0, -2.0, 1.0, yaw_rad=0.5), 0.0, 1.0, 0.0, 0.0)
    assert est.ok and (est.x_m, est.y_m, est.yaw_rad) == (1.0, -2.0, 0.5)
    assert (est.dx_m, est.dy_m, est.dyaw_rad) == (0.0, 0.0, 0.0)
    assert est.covariance.shape == (3, 3)


@pytest.mark.parametrize("kalman", [False, True])
def test_pure_translation(scene: GroundScene, kalman: bool) -> None:
    n = 30
    poses = np.zeros((n, 6))
    poses[:, 0] = np.linspace(0.0, 0.45, n)  # north
    poses[:, 1] = np.linspace(0.0, -0.30, n)  # east
    poses[:, 2] = 1.0
    poses[:, 5] = 0.3
    ests = _run(GroundOdometer(CAM, GroundOdometerConfig(kalman=kalman)), scene, poses)
    assert all(e.ok for e in ests)
    last = ests[-1]
    assert last.x_m == pytest.approx(0.45, abs=0.01)
    assert last.y_m == pytest.approx(-0.30, abs=0.01)
    assert last.yaw_rad == pytest.approx(0.3, abs=math.radians(0.3))
    if not kalman:
        mid = ests[15]
        assert mid.dx_m == pytest.approx(0.45 / (n - 1), abs=1.5e-3)
        assert mid.dy_m == pytest.approx(-0.30 / (n - 1), abs=1.5e-3)
        # The covariance is a proper covariance of (dx, dy, dyaw).
        assert np.all(np.linalg.eigvalsh(mid.covariance) > 0)


@pytest.mark.parametrize("solver", ["gen", "sma"])
def test_pure_yaw(scene: GroundScene, solver: str) -> None:
    n = 30
    poses = np.zeros((n, 6))
    poses[:, 2] = 1.2
    poses[:, 5] = np.linspace(0.0, 1.2, n)  # 2.4 deg per frame
    ests = _run(GroundOdometer(CAM, GroundOdometerConfig(solver=solver, kalman=False)), scene, poses)
    assert all(e.ok for e in ests)
    assert ests[-1].yaw_rad == pytest.approx(1.2, abs=math.radians(0.3))
    assert abs(ests[-1].x_m) < 0.01 and abs(ests[-1].y_m) < 0.01
    assert ests[10].dyaw_rad == pytest.approx(1.2 / (n - 1), abs=math.radians(0.1))


def test_tilted_camera_with_lever_arm_and_attitude(scene: GroundScene) -> None:
    """A camera pitched 15 deg forward, offset from the body origin, on a rolling and pitching body."""
    T_body_cam = se3.make(
        frames.rotation_from_euler_zyx(0.0, math.radians(-15.0), 0.0) @ frames.R_BODY_CAM_DEFAULT, [0.15, 0.05, 0.1]
    )
    tilted = GroundScene(
        CAM, texture="gravel", north_range_m=(-3.0, 3.0), east_range_m=(-3.0, 3.0), T_body_cam=T_body_cam, seed=3
    )
    n = 40
    t = np.arange(n) / 20.0
    poses = np.stack(
        [0.3 * t, 0.1 * t, 1.1 + 0.05 * np.sin(t), 0.08 * np.sin(3 * t), 0.06 * np.cos(2 * t), 0.2 + 0.2 * t], axis=1
    )
    ests = _run(GroundOdometer(CAM, GroundOdometerConfig(kalman=False), T_body_cam=T_body_cam), tilted, poses)
    assert all(e.ok for e in ests)
    last = ests[-1]
    assert last.x_m == pytest.approx(poses[-1, 0], abs=0.01)
    assert last.y_m == pytest.approx(poses[-1, 1], abs=0.01)
    assert last.yaw_rad == pytest.approx(poses[-1, 5], abs=math.radians(0.3))
    # Ignoring the mount gives a clearly wrong answer: the test can fail.
    wrong = _run(GroundOdometer(CAM, GroundOdometerConfig(kalman=False)), tilted, poses)[-1]
    assert math.hypot(wrong.x_m - poses[-1, 0], wrong.y_m - poses[-1, 1]) > 0.03


@pytest.mark.parametrize("kind", ["blank", "blurred", "blurred-noisy"])
def test_blank_or_blurred_frame_is_not_ok_and_pose_is_held(scene: GroundScene, kind: str) -> None:
    odo = GroundOdometer(CAM, GroundOdometerConfig())
    poses = np.zeros((6, 6))
    poses[:, 0] = np.linspace(0.0, 0.1, 6)
    poses[:, 2] = 1.0
    ests = _run(odo, scene, poses[:5])
    held = ests[-1]
    if kind == "blank":
        bad = np.full((CAM.height, CAM.width), 128, dtype=np.uint8)
    elif kind == "blurred":
        bad = scene.render(*poses[5], blur_sigma_px=25.0)
    else:  # sensor noise on a defocused frame: noise corners must not make a motion
        bad = scene.render(*poses[5], blur_sigma_px=25.0, noise_std=4.0, seed=9)
    est = odo.update(bad, 5 / 20.0, 1.0, 0.0, 0.0)
    assert not est.ok
    assert (est.x_m, est.y_m, est.yaw_rad) == (held.x_m, held.y_m, held.yaw_rad)
    assert (est.dx_m, est.dy_m, est.dyaw_rad) == (0.0, 0.0, 0.0)
    # The next textured frame matches the last good one again.
    nxt = odo.update(scene.render(0.125, 0.0, 1.0), 6 / 20.0, 1.0, 0.0, 0.0)
    assert nxt.ok
    assert nxt.x_m == pytest.approx(0.125, abs=0.005)


def test_color_input_and_keyframes(scene: GroundScene) -> None:
    n = 25
    poses = np.zeros((n, 6))
    poses[:, 0] = np.linspace(0.0, 0.3, n)
    poses[:, 2] = 1.0
    odo = GroundOdometer(CAM, GroundOdometerConfig(keyframes=True, kalman=False))
    odo.reset()
    for k in range(n):
        gray = scene.render(*poses[k])
        est = odo.update(np.dstack([gray, gray, gray]), k / 20.0, 1.0, 0.0, 0.0)
        assert est.ok
    assert est.x_m == pytest.approx(0.3, abs=0.005)


@pytest.mark.parametrize("detector", ["orb", "fast-orb", "gftt-orb", "sift", "akaze", "brisk"])
def test_every_detector_tracks(scene: GroundScene, detector: str) -> None:
    n = 6
    poses = np.zeros((n, 6))
    poses[:, 0] = np.linspace(0.0, 0.1, n)
    poses[:, 2] = 1.0
    poses[:, 5] = np.linspace(0.0, 0.05, n)
    ests = _run(GroundOdometer(CAM, GroundOdometerConfig(detector=detector, kalman=False)), scene, poses)
    assert all(e.ok for e in ests)
    assert ests[-1].x_m == pytest.approx(0.1, abs=0.006)


@pytest.mark.parametrize(
    ("args", "name"),
    [
        ((0.0, 0.0, 0.0), "height_m"),
        ((0.0, 150.0, 0.0), "height_m"),
        ((0.0, float("nan"), 0.0), "height_m"),
        ((0.0, 1.0, math.radians(70.0)), "roll_rad"),
        ((0.0, 1.0, float("inf")), "roll_rad"),
    ],
)
def test_input_validation(args: tuple[float, float, float], name: str) -> None:
    odo = GroundOdometer(CAM)
    img = np.zeros((CAM.height, CAM.width), dtype=np.uint8)
    stamp, h, roll = args
    with pytest.raises(InputError, match=name):
        odo.update(img, stamp, h, roll, 0.0)


def test_pitch_stamp_and_image_validation() -> None:
    odo = GroundOdometer(CAM)
    img = np.zeros((CAM.height, CAM.width), dtype=np.uint8)
    with pytest.raises(InputError, match="pitch_rad"):
        odo.update(img, 0.0, 1.0, 0.0, -1.2)
    for bad in (
        np.zeros((10, 10), np.uint8),
        np.zeros((CAM.height, CAM.width), np.float32),
        np.zeros((CAM.height, CAM.width, 4), np.uint8),
        [[0]],
    ):
        with pytest.raises(InputError, match="image"):
            odo.update(bad, 0.0, 1.0, 0.0, 0.0)
    odo.update(img, 1.0, 1.0, 0.0, 0.0)
    with pytest.raises(InputError, match="stamp_s"):
        odo.update(img, 1.0, 1.0, 0.0, 0.0)
    with pytest.raises(InputError, match="T_body_cam"):
        GroundOdometer(CAM, T_body_cam=np.eye(3))


def test_config_validation() -> None:
    with pytest.raises(ConfigError, match="detector"):
        GroundOdometerConfig(detector="surf")
    with pytest.raises(ConfigError, match="solver"):
        GroundOdometerConfig(solver="exact")
    with pytest.raises(ConfigError, match="ratio"):
        GroundOdometerConfig(ratio=1.5)


def test_reset_replays_deterministically(scene: GroundScene) -> None:
    poses = np.zeros((6, 6))
    poses[:, 0] = np.linspace(0.0, 0.1, 6)
    poses[:, 2] = 1.0
    poses[:, 5] = np.linspace(0.0, 0.1, 6)
    odo = GroundOdometer(CAM)
    first = _run(odo, scene, poses)
    second = _run(odo, scene, poses)  # _run resets
    assert [(e.x_m, e.y_m, e.yaw_rad, e.num_inliers) for e in first] == [
        (e.x_m, e.y_m, e.yaw_rad, e.num_inliers) for e in second
    ]


def test_constant_attitude_bias_is_estimated_end_to_end(scene: GroundScene) -> None:
    """Roll/pitch inputs off by (+0.5, -0.4) deg on a curved flight: the odometer estimates the bias
    (`tilt_bias_rad`) from the rendered frames and keeps it out of the yaw."""
    n = 120
    t = np.arange(n) / 20.0
    x, y = np.sin(0.5 * t), 1.0 - np.cos(0.5 * t)
    yaw, h = 0.3 * np.sin(0.5 * t), 1.1 + 0.1 * np.sin(0.4 * t)
    bias = (math.radians(0.5), math.radians(-0.4))
    yaw_err = {}
    for estimate in (True, False):
        odo = GroundOdometer(CAM, GroundOdometerConfig(estimate_tilt_bias=estimate))
        assert odo.tilt_bias_rad == (0.0, 0.0)
        errs = []
        for k in range(n):
            est = odo.update(scene.render(x[k], y[k], h[k], 0.0, 0.0, yaw[k], seed=k), t[k], h[k], *bias)
            assert est.ok
            errs.append(abs(est.yaw_rad - yaw[k]))
        yaw_err[estimate] = float(np.mean(errs))
        if estimate:
            np.testing.assert_allclose(odo.tilt_bias_rad, bias, atol=math.radians(0.2))
    assert yaw_err[True] < 0.5 * yaw_err[False]
