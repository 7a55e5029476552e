"""Photo sidecar: JSON-serializable, pose and covariance, camera pose, validation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from companion.errors import InputError
from companion.geometry import se3
from companion.geometry.frames import default_T_body_cam, rotation_from_euler_zyx
from companion.mission.photo import photo_basename, photo_sidecar


def test_sidecar_round_trips_through_json() -> None:
    T = se3.make(rotation_from_euler_zyx(0.02, -0.01, math.radians(30.0)), np.array([2.0, 0.5, -1.2]))
    P = np.diag([0.01, 0.04, 0.0025, 1e-4, 1e-4, 4e-4])
    s = photo_sidecar(index=3, stamp_s=12.5, camera="down", T_ned_body=T, pose_covariance=P,
                      mission_name="fig6", action_id="photo-2m", action_index=6, image_file="x.png",
                      calibration_file="cam.yaml", image_size_px=(720, 480), T_body_cam=default_T_body_cam(),
                      utc_time="2026-11-22T19:00:00Z")
    back = json.loads(json.dumps(s))
    assert back == s
    assert back["body_pose_ned"]["position_m"] == [2.0, 0.5, -1.2]
    assert back["body_pose_ned"]["yaw_deg"] == pytest.approx(30.0)
    assert back["position_sigma_m"] == pytest.approx([0.1, 0.2, 0.05])
    assert back["mission"] == {"name": "fig6", "action_id": "photo-2m", "action_index": 6}
    assert back["calibration_file"] == "cam.yaml" and back["stamp_s"] == 12.5 and back["index"] == 3
    T_ned_cam = np.array(back["camera_pose_ned"]["matrix"])
    assert np.allclose(T_ned_cam, T @ default_T_body_cam())
    q = np.array(back["body_pose_ned"]["quaternion_wxyz"])
    assert np.linalg.norm(q) == pytest.approx(1.0)


def test_sidecar_without_optional_parts_and_bad_inputs() -> None:
    s = photo_sidecar(index=0, stamp_s=1.0, camera="down", T_ned_body=np.eye(4))
    assert s["pose_covariance"] is None and s["camera_pose_ned"] is None and s["utc_time"] is None
    with pytest.raises(InputError, match="pose_covariance"):
        photo_sidecar(index=0, stamp_s=1.0, camera="c", T_ned_body=np.eye(4), pose_covariance=np.eye(3))
    with pytest.raises(InputError, match="T_ned_body"):
        photo_sidecar(index=0, stamp_s=1.0, camera="c", T_ned_body=2.0 * np.eye(4))
    with pytest.raises(InputError, match="index"):
        photo_sidecar(index=-1, stamp_s=1.0, camera="c", T_ned_body=np.eye(4))


def test_basename_is_safe_and_deterministic() -> None:
    assert photo_basename(3, "down", "fig6", "photo-2m") == "fig6_photo-2m_down_0003"
    assert photo_basename(12, "cam/../x y") == "cam-..-x-y_0012"
    assert photo_basename(0, "") == "photo_0000"
