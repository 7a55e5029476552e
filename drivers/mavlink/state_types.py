"""Frozen value types of the link boundary: `VehicleState` and `SimTruth` (what the autopilot reported,
decoded by `drivers.mavlink.state.StateTracker`) and `PoseOut` (a vision pose to send), with the
read-only array helpers they are built from."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.estimation import ImuSample

__all__ = ["PoseOut", "SimTruth", "VehicleState"]


def _ro(values: Any, shape: tuple[int, ...]) -> FloatArray:
    arr = np.array(values, dtype=np.float64).reshape(shape)
    arr.setflags(write=False)
    return arr


def _covariance(values: Any, n: int, name: str) -> FloatArray:
    """An (n, n) covariance; NaN marks unknown entries, infinities are refused."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a numeric ({n}, {n}) array") from exc
    if arr.shape != (n, n):
        raise InputError(f"{name}: expected shape ({n}, {n}), got {arr.shape}")
    if np.any(np.isinf(arr)):
        raise InputError(f"{name}: contains infinite values (use NaN for unknown)")
    return _ro(arr, (n, n))


@dataclass(frozen=True)
class SimTruth:
    """Simulator ground truth from SIM_STATE: pose of body in NED (4x4), NED velocity (m/s)."""

    stamp_s: float
    T_ned_body: FloatArray
    velocity_ned_m_s: FloatArray


@dataclass(frozen=True)
class PoseOut:
    """A vision pose estimate to send to the autopilot.

    ``stamp_s``: capture time of the frame on the link's clock (s). ``T_ned_body``: 4x4 pose of
    body (FRD) in the autopilot's local NED frame. ``pose_covariance``: 6x6, order x, y, z (m),
    roll, pitch, yaw (rad); NaN entries mean unknown. ``velocity_ned_m_s`` (3,) and its 3x3
    ``velocity_covariance`` are optional. ``reset_counter`` counts real discontinuities (any int;
    wrapped to uint8 on the wire). ``quality_pct`` (0..100) is used by ODOMETRY; None derives it
    from the position covariance. ``angular_rate_body_rad_s`` (3,) feeds ODOMETRY (NaN if None).
    """

    stamp_s: float
    T_ned_body: FloatArray
    pose_covariance: FloatArray
    velocity_ned_m_s: FloatArray | None = None
    velocity_covariance: FloatArray | None = None
    reset_counter: int = 0
    quality_pct: int | None = None
    angular_rate_body_rad_s: FloatArray | None = None

    def __post_init__(self) -> None:
        if not math.isfinite(float(self.stamp_s)):
            raise InputError(f"PoseOut.stamp_s must be finite, got {self.stamp_s!r}")
        object.__setattr__(self, "stamp_s", float(self.stamp_s))
        T = check_transform(self.T_ned_body, "PoseOut.T_ned_body", tol=1e-4)
        object.__setattr__(self, "T_ned_body", _ro(T, (4, 4)))
        object.__setattr__(self, "pose_covariance", _covariance(self.pose_covariance, 6, "PoseOut.pose_covariance"))
        if self.velocity_ned_m_s is not None:
            v = np.asarray(self.velocity_ned_m_s, dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise InputError(f"PoseOut.velocity_ned_m_s must be 3 finite values, got shape {v.shape}")
            object.__setattr__(self, "velocity_ned_m_s", _ro(v, (3,)))
        if self.velocity_covariance is not None:
            vc = _covariance(self.velocity_covariance, 3, "PoseOut.velocity_covariance")
            object.__setattr__(self, "velocity_covariance", vc)
        if self.angular_rate_body_rad_s is not None:
            w = np.asarray(self.angular_rate_body_rad_s, dtype=np.float64)
            if w.shape != (3,):
                raise InputError(f"PoseOut.angular_rate_body_rad_s must have shape (3,), got {w.shape}")
            object.__setattr__(self, "angular_rate_body_rad_s", _ro(w, (3,)))
        if not isinstance(self.reset_counter, (int, np.integer)) or self.reset_counter < 0:
            raise InputError(f"PoseOut.reset_counter must be an int >= 0, got {self.reset_counter!r}")
        object.__setattr__(self, "reset_counter", int(self.reset_counter))
        if self.quality_pct is not None and not 0 <= int(self.quality_pct) <= 100:
            raise InputError(f"PoseOut.quality_pct must be in [0, 100], got {self.quality_pct!r}")


@dataclass(frozen=True)
class VehicleState:
    """Snapshot of what the autopilot told us, SI units; ``*_stamp_s`` are local receive times (s).

    Vectors are read-only float64 arrays. None means "never received". ``landed_state`` is
    "on_ground" | "in_air" | "takeoff" | "landing" (EXTENDED_SYS_STATE; None while unknown or
    MAV_LANDED_STATE_UNDEFINED). ``rangefinder_m`` is the downward DISTANCE_SENSOR (PITCH_270) and
    ``rangefinder_up_m`` the upward one (PITCH_90, clearance to a ceiling), both None when the last
    reading was out of the sensor's range; their ``*_stamp_s`` is the receive time of that reading.
    """

    autopilot: str | None = None
    autopilot_system_id: int | None = None
    autopilot_component_id: int | None = None
    vehicle_type: int | None = None
    armed: bool = False
    mode: str | None = None
    custom_mode: int | None = None
    system_status: int | None = None
    landed_state: str | None = None
    last_autopilot_heartbeat_s: float | None = None
    last_gcs_heartbeat_s: float | None = None
    gcs_system_id: int | None = None
    attitude_rpy_rad: FloatArray | None = None
    angular_rate_body_rad_s: FloatArray | None = None
    R_ned_body: FloatArray | None = None
    attitude_stamp_s: float | None = None
    position_ned_m: FloatArray | None = None
    velocity_ned_m_s: FloatArray | None = None
    local_position_stamp_s: float | None = None
    battery_voltage_v: float | None = None
    battery_current_a: float | None = None
    battery_remaining_pct: float | None = None
    battery_stamp_s: float | None = None
    rangefinder_m: float | None = None
    rangefinder_stamp_s: float | None = None
    rangefinder_up_m: float | None = None
    rangefinder_up_stamp_s: float | None = None
    ekf_flags: int | None = None
    ekf_stamp_s: float | None = None
    ekf_origin_set: bool = False
    ekf_origin_lat_deg: float | None = None
    ekf_origin_lon_deg: float | None = None
    ekf_origin_alt_m: float | None = None
    last_imu: ImuSample | None = None
    sim_truth: SimTruth | None = None
    prearm_ok: bool | None = None  # SYS_STATUS PREARM_CHECK health; None when the autopilot does not report it
    home_position_stamp_s: float | None = None  # last HOME_POSITION
    arming_text: str | None = None  # the autopilot's last "PreArm:"/"Arm:"/"Preflight" STATUSTEXT
    arming_text_stamp_s: float | None = None

    @property
    def height_m(self) -> float | None:
        """Height above the EKF origin (-z NED, m), None without a local position."""
        return None if self.position_ned_m is None else float(-self.position_ned_m[2])
