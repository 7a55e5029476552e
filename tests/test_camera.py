"""PinholeCamera against cv2.projectPoints (the oracle), Jacobians, unprojection, YAML files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import CameraError, InputError
from tests.numdiff import central_jacobian

DISTORTIONS = {
    "none": None,
    "k1k2p1p2": (-0.28, 0.09, 1e-3, -5e-4),
    "k1k2p1p2k3": (-0.25, 0.07, 8e-4, 3e-4, -0.01),
    "rational": (0.1, -0.05, 1e-3, 2e-4, 0.01, 0.05, -0.02, 0.004),
    "thin_prism": (-0.2, 0.05, 1e-3, 2e-4, 0.0, 0.0, 0.0, 0.0, 1e-3, -2e-4, 5e-4, 1e-4),
}


def make_cam(dist: tuple[float, ...] | None, skew: float = 0.0) -> PinholeCamera:
    return PinholeCamera(width=720, height=480, fx=630.0, fy=615.0, cx=355.5, cy=242.25, skew=skew, dist=dist)


def points_in_view(rng: np.random.Generator, n: int = 2000) -> np.ndarray:
    z = rng.uniform(0.5, 8.0, size=n)
    x = rng.uniform(-0.5, 0.5, size=n) * z
    y = rng.uniform(-0.35, 0.35, size=n) * z
    return np.stack([x, y, z], axis=1)


@pytest.mark.parametrize("name", list(DISTORTIONS))
def test_project_matches_opencv(name: str, rng: np.random.Generator) -> None:
    cam = make_cam(DISTORTIONS[name])
    p = points_in_view(rng)
    ref, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    assert np.abs(cam.project(p) - ref.reshape(-1, 2)).max() < 1e-9


def test_skew_follows_camera_matrix(rng: np.random.Generator) -> None:
    cam = make_cam(None, skew=2.5)
    p = points_in_view(rng, 100)
    hom = (cam.K @ p.T).T
    assert np.abs(cam.project(p) - hom[:, :2] / hom[:, 2:]).max() < 1e-9


@pytest.mark.parametrize("name", list(DISTORTIONS))
def test_projection_jacobian_numeric(name: str, rng: np.random.Generator) -> None:
    cam = make_cam(DISTORTIONS[name], skew=1.5)
    p = points_in_view(rng, 20)
    _, J = cam.project_with_jacobian(p)
    for i in range(len(p)):
        num = central_jacobian(lambda q: cam.project(q), p[i])
        assert np.abs(J[i] - num).max() < 1e-6 * max(1.0, np.abs(num).max())


@pytest.mark.parametrize("name", list(DISTORTIONS))
def test_unproject_inverts_project(name: str, rng: np.random.Generator) -> None:
    cam = make_cam(DISTORTIONS[name], skew=0.8)
    p = points_in_view(rng, 500)
    rays = cam.unproject(cam.project(p))
    expected = p / np.linalg.norm(p, axis=1, keepdims=True)
    assert np.abs(rays - expected).max() < 1e-10


def test_unproject_matches_opencv_undistort(rng: np.random.Generator) -> None:
    cam = make_cam(DISTORTIONS["k1k2p1p2k3"])
    uv = np.stack([rng.uniform(0, 719, 300), rng.uniform(0, 479, 300)], axis=1)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), cam.K, cam.dist_coeffs, None, None, crit).reshape(-1, 2)
    assert np.abs(cam.normalized(uv) - ref).max() < 1e-8


def test_points_behind_camera_are_nan() -> None:
    cam = make_cam(None)
    uv = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.1, 0.1, 1.0]]))
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()


def test_in_image() -> None:
    cam = make_cam(None)
    uv = np.array([[0.0, 0.0], [-0.6, 10.0], [719.4, 479.4], [719.6, 0.0], [np.nan, 1.0]])
    assert cam.in_image(uv).tolist() == [True, False, True, False, False]
    assert cam.in_image(uv, margin_px=5.0).tolist() == [False, False, False, False, False]


def test_single_point_shapes() -> None:
    cam = make_cam(DISTORTIONS["k1k2p1p2"])
    uv, J = cam.project_with_jacobian(np.array([0.1, -0.2, 2.0]))
    assert uv.shape == (2,) and J.shape == (2, 3)
    assert cam.unproject(uv).shape == (3,)


def test_yaml_roundtrip_and_opencv_readable(tmp_path: Path) -> None:
    cam = make_cam(DISTORTIONS["k1k2p1p2k3"], skew=0.5)
    path = tmp_path / "calib.yaml"
    cam.to_yaml(path)
    assert PinholeCamera.from_yaml(path) == cam
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode("camera_matrix").mat(), cam.K)
    fs.release()


def test_yaml_written_by_hand(tmp_path: Path) -> None:
    path = tmp_path / "cam.yml"
    path.write_text(
        "%YAML:1.0\n---\nimage_width: 752\nimage_height: 480\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 458.6, 0., 367.2, 0., 457.3, 248.4, 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 4\n   dt: d\n"
        "   data: [ -0.2834, 0.0739, 0.0002, 1.76e-05 ]\n"
    )
    cam = PinholeCamera.from_yaml(path)
    assert (cam.width, cam.height, cam.fx, cam.cy) == (752, 480, 458.6, 248.4)
    assert cam.dist == (-0.2834, 0.0739, 0.0002, 1.76e-05)


def test_bad_files_and_values(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="not found"):
        PinholeCamera.from_yaml(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\n---\nimage_width: 10\nimage_height: 10\n")
    with pytest.raises(CameraError, match="camera_matrix"):
        PinholeCamera.from_yaml(bad)
    with pytest.raises(InputError, match="fx"):
        PinholeCamera(width=10, height=10, fx=-1.0, fy=1.0, cx=5.0, cy=5.0)
    with pytest.raises(InputError, match="dist"):
        PinholeCamera(width=10, height=10, fx=1.0, fy=1.0, cx=5.0, cy=5.0, dist=(0.1, 0.2, 0.3))
    with pytest.raises(InputError, match="width"):
        PinholeCamera(width=0, height=10, fx=1.0, fy=1.0, cx=5.0, cy=5.0)


def test_points_behind_the_camera_are_nan_and_the_rest_unchanged() -> None:
    rng = np.random.default_rng(5)
    p = rng.normal(0.0, 1.0, (200, 3)) + np.array([0.0, 0.0, 2.0])
    p[:5, 2] = [-1.0, 0.0, 1e-12, -3.0, 1e-10]  # behind / on the camera plane
    for cam in (PinholeCamera(width=720, height=480, fx=630.0, fy=640.0, cx=355.0, cy=245.0, skew=0.7),
                PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0,
                              dist=(0.1, -0.05, 0.001, 0.002, 0.0))):
        uv, J = cam.project_with_jacobian(p)
        uv_front, J_front = cam.project_with_jacobian(p[5:])
        assert np.all(np.isnan(uv[:5])) and np.all(np.isnan(J[:5]))
        np.testing.assert_array_equal(uv[5:], uv_front)
        np.testing.assert_array_equal(J[5:], J_front)
