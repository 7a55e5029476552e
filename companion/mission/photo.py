"""Photo sidecars: the JSON metadata written next to every mission photo (pure; the daemon does the I/O).

`photo_sidecar(...)` returns a JSON-serializable dict; `photo_basename(...)` a deterministic
file stem. The daemon grabs the full-resolution frame, writes `<stem>.png` and
`<stem>.json` (json.dumps of the sidecar) into the flight folder and announces
CAMERA_IMAGE_CAPTURED with the same index.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from companion.checks import FloatArray, as_float_array, check_transform
from companion.errors import InputError
from companion.geometry.frames import euler_zyx_from_rotation, quaternion_wxyz_from_rotation

__all__ = ["SIDECAR_VERSION", "photo_basename", "photo_sidecar"]

SIDECAR_VERSION = 1
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def _pose_dict(T: FloatArray) -> dict[str, Any]:
    rpy = euler_zyx_from_rotation(T[:3, :3])
    q = quaternion_wxyz_from_rotation(T[:3, :3])
    return {
        "position_m": [float(x) for x in T[:3, 3]],
        "quaternion_wxyz": [float(x) for x in q],
        "roll_deg": math.degrees(float(rpy[0])),
        "pitch_deg": math.degrees(float(rpy[1])),
        "yaw_deg": math.degrees(float(rpy[2])),
        "matrix": [[float(x) for x in row] for row in T],
    }


def photo_sidecar(
    *,
    index: int,
    stamp_s: float,
    camera: str,
    T_ned_body: Any,
    pose_covariance: Any | None = None,
    pose_ok: bool = True,
    mission_name: str | None = None,
    action_id: str | None = None,
    action_index: int | None = None,
    image_file: str | None = None,
    calibration_file: str | None = None,
    image_size_px: tuple[int, int] | None = None,
    T_body_cam: Any | None = None,
    utc_time: str | None = None,
) -> dict[str, Any]:
    """Metadata of one photo.

    index: photo sequence number in the flight (>= 0; also CAMERA_IMAGE_CAPTURED.image_index);
    stamp_s: capture time of the frame (s, the daemon's monotonic clock); camera: camera name;
    T_ned_body: best body pose at capture (4x4, NED); pose_covariance: 6x6 covariance of that pose
    in the order x, y, z (m^2), roll, pitch, yaw (rad^2), or None; pose_ok: whether the estimator
    trusted the pose; T_body_cam: camera mount (4x4) -- when given the camera pose in NED is
    included too; utc_time: ISO-8601 wall-clock time supplied by the caller (pure: no clock read).
    Angles are in degrees in the sidecar (it is read by people and GIS tools), positions in m.
    """
    if not isinstance(index, int) or index < 0:
        raise InputError(f"index: expected an int >= 0, got {index!r}")
    stamp = float(as_float_array(stamp_s, "stamp_s"))
    T = check_transform(T_ned_body, "T_ned_body")
    if T.shape != (4, 4):
        raise InputError(f"T_ned_body: expected shape (4, 4), got {T.shape}")
    sidecar: dict[str, Any] = {
        "version": SIDECAR_VERSION,
        "index": index,
        "stamp_s": stamp,
        "utc_time": utc_time,
        "camera": camera,
        "image_file": image_file,
        "image_size_px": None if image_size_px is None else [int(image_size_px[0]), int(image_size_px[1])],
        "calibration_file": calibration_file,
        "mission": {"name": mission_name, "action_id": action_id, "action_index": action_index},
        "pose_ok": bool(pose_ok),
        "frame": "ned",
        "body_pose_ned": _pose_dict(T),
        "pose_covariance": None,
        "pose_covariance_order": ["x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"],
        "position_sigma_m": None,
        "camera_pose_ned": None,
    }
    if pose_covariance is not None:
        P = as_float_array(pose_covariance, "pose_covariance")
        if P.shape != (6, 6):
            raise InputError(f"pose_covariance: expected shape (6, 6), got {P.shape}")
        sidecar["pose_covariance"] = [[float(x) for x in row] for row in P]
        sidecar["position_sigma_m"] = [float(math.sqrt(max(0.0, P[i, i]))) for i in range(3)]
    if T_body_cam is not None:
        T_bc = check_transform(T_body_cam, "T_body_cam")
        sidecar["camera_pose_ned"] = _pose_dict(np.asarray(T @ T_bc))
    return sidecar


def photo_basename(index: int, camera: str, mission_name: str | None = None, action_id: str | None = None) -> str:
    """Deterministic, filesystem-safe file stem, e.g. 'fig6_photo-2m_down_0003'."""
    parts = [p for p in (mission_name, action_id, camera) if p]
    stem = "_".join(_UNSAFE.sub("-", p) for p in parts) or "photo"
    return f"{stem}_{int(index):04d}"
