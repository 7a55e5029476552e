"""Back-projection to the ground against an independent ray-plane intersection in NED."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.geometry import frames, se3
from companion.vision.ground.backproject import ground_points_level, rays_from_pixels


def _independent(cam: PinholeCamera, uv: np.ndarray, T_body_cam: np.ndarray, pose: tuple[float, ...]) -> np.ndarray:
    """Ground hits in NED (N, 2) from a camera at body pose (x, y, height, roll, pitch, yaw)."""
    x, y, h, roll, pitch, yaw = pose
    R_ned_body = frames.rotation_from_euler_zyx(roll, pitch, yaw)
    T_ned_body = se3.make(R_ned_body, np.zeros(3))
    T_ned_cam = T_ned_body @ T_body_cam
    centre = T_ned_cam[:3, 3]
    # Put the ground h below the optical centre; the body origin is at (x, y).
    origin = np.array([x, y, 0.0]) + centre
    d = cam.unproject(uv) @ T_ned_cam[:3, :3].T
    t = h / d[:, 2]
    hits = origin + t[:, None] * d
    out: np.ndarray = hits[:, :2]
    return out


@pytest.mark.parametrize(
    "T_body_cam",
    [
        frames.default_T_body_cam(),
        se3.make(
            frames.rotation_from_euler_zyx(0.0, math.radians(20.0), 0.1) @ frames.R_BODY_CAM_DEFAULT, [0.1, -0.05, 0.08]
        ),
    ],
)
def test_matches_ray_plane_intersection(rng: np.random.Generator, T_body_cam: np.ndarray) -> None:
    cam = PinholeCamera(752, 480, 450.0, 455.0, 370.0, 245.0, dist=(-0.2, 0.05, 0.001, -0.001, 0.0))
    uv = rng.uniform([0, 0], [751, 479], (200, 2))
    for _ in range(5):
        pose = (
            rng.normal(0, 2),
            rng.normal(0, 2),
            rng.uniform(0.5, 3.0),
            rng.normal(0, 0.2),
            rng.normal(0, 0.2),
            rng.uniform(-3, 3),
        )
        expected = _independent(cam, uv, T_body_cam, pose)
        q, valid = ground_points_level(cam.unproject(uv), pose[2], pose[3], pose[4], T_body_cam)
        assert valid.all()
        c, s = math.cos(pose[5]), math.sin(pose[5])
        got = np.array(pose[:2]) + q @ np.array([[c, -s], [s, c]]).T
        np.testing.assert_allclose(got, expected, atol=1e-9)


def test_rays_above_the_horizon_are_invalid() -> None:
    rays = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    T = se3.make(frames.R_BODY_CAM_DEFAULT, np.zeros(3))
    q, valid = ground_points_level(rays, 1.0, 0.0, 0.0, T)
    assert valid.tolist() == [True, False, False]
    assert np.isnan(q[1:]).all()
    np.testing.assert_allclose(q[0], [0.0, 0.0])


def test_fast_path_rays_match_camera_unproject(rng: np.random.Generator) -> None:
    cam = PinholeCamera(640, 480, 500.0, 510.0, 320.0, 240.0, skew=0.5)
    uv = rng.uniform(0, 480, (50, 2))
    r = rays_from_pixels(cam.fx, cam.fy, cam.cx, cam.cy, cam.skew, uv)
    u = cam.unproject(uv)
    np.testing.assert_allclose(r / np.linalg.norm(r, axis=1, keepdims=True), u, atol=1e-12)
