"""Fixed frames and convention conversions (MAVLink quaternions, ZYX Euler, NED/ENU)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from companion.geometry import frames, se3


def test_default_mount_axes() -> None:
    R = frames.default_T_body_cam()[:3, :3]
    # x_cam = y_body, y_cam = -x_body, z_cam = z_body (columns are cam axes in body)
    assert np.allclose(R[:, 0], [0, 1, 0]) and np.allclose(R[:, 1], [-1, 0, 0]) and np.allclose(R[:, 2], [0, 0, 1])
    assert np.isclose(np.linalg.det(R), 1.0)


def test_default_rack_alignment() -> None:
    R = frames.default_T_ned_rack()[:3, :3]
    # rack +y is north, rack +x is east, rack +z is up (= -down)
    assert np.allclose(R @ [0, 1, 0], [1, 0, 0]) and np.allclose(R @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(R @ [0, 0, 1], [0, 0, -1])
    assert np.isclose(np.linalg.det(R), 1.0)


def test_ned_enu_roundtrip() -> None:
    p = np.array([[1.0, 2.0, 3.0]])
    assert np.allclose(frames.ned_to_enu(p), [[2.0, 1.0, -3.0]])
    assert np.allclose(frames.enu_to_ned(frames.ned_to_enu(p)), p)


def test_euler_matches_scipy(rng: np.random.Generator) -> None:
    rpy = np.stack([rng.uniform(-3, 3, 500), rng.uniform(-1.5, 1.5, 500), rng.uniform(-3, 3, 500)], axis=1)
    R = frames.rotation_from_euler_zyx(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    ref = Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix()
    assert np.abs(R - ref).max() < 1e-14
    assert np.abs(frames.euler_zyx_from_rotation(R) - rpy).max() < 1e-12


def test_euler_gimbal_lock_is_finite() -> None:
    R = frames.rotation_from_euler_zyx(0.3, np.pi / 2, 0.2)
    rpy = frames.euler_zyx_from_rotation(R)
    assert np.all(np.isfinite(rpy))
    assert np.allclose(frames.rotation_from_euler_zyx(*rpy), R, atol=1e-9)


def test_quaternion_wxyz_convention() -> None:
    # 90 deg yaw: body x (forward) points east.
    q = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    R = frames.rotation_from_quaternion_wxyz(q)
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(frames.quaternion_wxyz_from_rotation(R), q)


def test_wrap_angle() -> None:
    a = frames.wrap_angle(np.array([0.0, np.pi, -np.pi, 3 * np.pi, 2 * np.pi + 0.1, -0.1]))
    assert np.allclose(a, [0.0, np.pi, np.pi, np.pi, 0.1, -0.1])


def test_worked_example_of_conventions() -> None:
    # The worked example of docs/CONVENTIONS.md: camera 2 m above the rack origin, looking down,
    # body nose along rack +y (north), gives T_ned_body at 2 m altitude with zero attitude.
    # x_cam = y_body = east = rack +x, y_cam = -x_body = south = rack -y, z_cam = down = rack -z.
    T_rack_cam = se3.make(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 2.0])
    T_ned_body = frames.T_ned_body_from_T_rack_cam(T_rack_cam, frames.default_T_ned_rack(),
                                                   frames.default_T_body_cam())
    assert np.allclose(T_ned_body[:3, 3], [0.0, 0.0, -2.0])
    assert np.allclose(T_ned_body[:3, :3], np.eye(3), atol=1e-12)
    back = frames.T_rack_cam_from_T_ned_body(T_ned_body, frames.default_T_ned_rack(), frames.default_T_body_cam())
    assert np.allclose(back, T_rack_cam)
