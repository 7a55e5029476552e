"""`PinholeCamera.from_yaml`: OpenCV FileStorage YAML, ROS camera_info YAML, and one-line refusals."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import CameraError

ROS_YAML = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [500.5, 0.0, 321.25, 0.0, 502.0, 239.5, 0.0, 0.0, 1.0]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {n}
  data: [{dist}]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [500.5, 0, 321.25, 0, 0, 502.0, 239.5, 0, 0, 0, 1, 0]
"""


DIST5 = (-0.21, 0.05, 0.001, -0.002, 0.01)


def _ros(tmp_path: Path, model: str = "plumb_bob", dist: tuple[float, ...] = DIST5) -> Path:
    path = tmp_path / "ost.yaml"
    path.write_text(ROS_YAML.format(model=model, n=len(dist), dist=", ".join(repr(d) for d in dist)))
    return path


def test_ros_camera_info_plumb_bob(tmp_path: Path) -> None:
    cam = PinholeCamera.from_yaml(_ros(tmp_path))
    assert (cam.width, cam.height) == (640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.skew) == (500.5, 502.0, 321.25, 239.5, 0.0)
    assert cam.dist == (-0.21, 0.05, 0.001, -0.002, 0.01)


def test_ros_rational_polynomial_keeps_eight_terms(tmp_path: Path) -> None:
    dist = (-0.2, 0.05, 0.001, -0.002, 0.01, 0.1, 0.02, 0.003)
    cam = PinholeCamera.from_yaml(_ros(tmp_path, "rational_polynomial", dist))
    assert cam.dist == dist


def test_ros_and_opencv_files_of_one_camera_project_alike(tmp_path: Path) -> None:
    ros = PinholeCamera.from_yaml(_ros(tmp_path))
    ros.to_yaml(tmp_path / "cv.yaml")
    cv = PinholeCamera.from_yaml(tmp_path / "cv.yaml")
    assert cv == ros
    p_cam = np.random.default_rng(3).uniform([-1, -1, 2], [1, 1, 4], size=(20, 3))
    np.testing.assert_allclose(cv.project(p_cam), ros.project(p_cam), atol=1e-12)


def test_opencv_file_written_by_opencv_itself(tmp_path: Path) -> None:
    path = tmp_path / "opencv.yml"
    K = np.array([[610.0, 0.0, 355.0], [0.0, 612.0, 241.0], [0.0, 0.0, 1.0]])
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 720)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array([[0.1, -0.2, 0.0, 0.0, 0.05]]))
    fs.release()
    cam = PinholeCamera.from_yaml(path)
    np.testing.assert_array_equal(cam.K, K)
    assert cam.dist == (0.1, -0.2, 0.0, 0.0, 0.05)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("camera_matrix: [1, 2\nfoo: {", "not an OpenCV or ROS calibration YAML"),  # raised SystemError before
        ("", "empty calibration file"),
        ("image_width: 640\nimage_height: 480\n", "camera_matrix: required"),
        ("image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 2, 3]\n",
         "camera_matrix: data must hold rows x cols numbers"),
        (ROS_YAML.format(model="equidistant", n=4, dist="0.1, 0.01, 0.0, 0.0"), "distortion_model: 'equidistant'"),
        (ROS_YAML.format(model="plumb_bob", n=4, dist="0, 0, 0, 0").replace("image_width: 640\n", ""),
         "image_width and image_height: required"),
    ],
)
def test_unreadable_files_raise_one_line(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "calib.yaml"
    path.write_text(text)
    with pytest.raises(CameraError) as info:
        PinholeCamera.from_yaml(path)
    message = str(info.value)
    assert fragment in message
    assert "\n" not in message and message.startswith(str(path))


def test_binary_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "calib.yaml"
    path.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(CameraError, match="not UTF-8"):
        PinholeCamera.from_yaml(path)
