"""Typed, SI-unit view of the autopilot, decoded at the link boundary.

Every MAVLink unit and convention is converted here and nowhere else: millivolts, centimetres,
milli-g, degE7, quaternion order (MAVLink is w, x, y, z), Euler angles (ZYX, R_ned_body =
Rz(yaw) Ry(pitch) Rx(roll)), autopilot microseconds (mapped to our monotonic clock through
TIMESYNC once it converged). `StateTracker` is a synchronous state machine fed with decoded
messages and the local receive time; `VehicleState` is its frozen snapshot.

IMU messages become `companion.estimation.ImuSample` (stamp on our clock, body FRD gyro and
specific force); non-finite samples are dropped and counted (``StateTracker.rejected_imu``).

The value types (`VehicleState`, `SimTruth`, `PoseOut`) are in `state_types` and the flat-earth NED
conversions in `geodetic`; this module re-exports them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from companion.estimation import ImuSample
from companion.geometry import frames
from drivers.mavlink.geodetic import geodetic_from_ned, ned_from_geodetic
from drivers.mavlink.profiles import AutopilotProfile, profile_for_autopilot
from drivers.mavlink.state_types import PoseOut, SimTruth, VehicleState, _ro
from drivers.mavlink.timesync import TimeSync

__all__ = [
    "ImuSample",
    "PoseOut",
    "SimTruth",
    "StateTracker",
    "VehicleState",
    "geodetic_from_ned",
    "ned_from_geodetic",
]

MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_TYPE_GCS = 6
MAV_AUTOPILOT_INVALID = 8
# Vehicle types that never are the flight controller we talk to.
_NON_AUTOPILOT_TYPES = frozenset({6, 18, 26, 27, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39, 40, 41, 42, 43})
MAV_SENSOR_ROTATION_PITCH_270 = 25  # downward-facing rangefinder
MAV_SENSOR_ROTATION_PITCH_90 = 24  # upward-facing rangefinder (distance to a ceiling)
G_M_S2 = 9.80665
UINT16_MAX = 65535


class StateTracker:
    """Folds decoded MAVLink messages into a `VehicleState` (synchronous, no I/O, no clock).

    ``system_id``: accept only this autopilot system id (None = lock onto the first autopilot
    heartbeat). ``origin_deg``: (lat, lon, alt_m) used to turn SIM_STATE into NED until the
    autopilot confirms its EKF origin. ``timesync`` maps autopilot microseconds to local time.
    """

    def __init__(
        self,
        *,
        system_id: int | None = None,
        origin_deg: tuple[float, float, float] | None = None,
        timesync: TimeSync | None = None,
        forced_profile: AutopilotProfile | None = None,
    ) -> None:
        self._fixed_sysid = system_id
        self._origin = origin_deg
        self._timesync = timesync or TimeSync()
        self._forced_profile = forced_profile
        self.profile: AutopilotProfile | None = forced_profile
        self._f: dict[str, Any] = {}
        self._snapshot: VehicleState | None = None
        self.ignored_messages = 0
        self.rejected_imu = 0

    # -- identity -------------------------------------------------------------------------
    @property
    def autopilot_address(self) -> tuple[int, int] | None:
        """(system id, component id) of the autopilot once its heartbeat was seen."""
        sysid = self._f.get("autopilot_system_id")
        compid = self._f.get("autopilot_component_id")
        return None if sysid is None or compid is None else (int(sysid), int(compid))

    def _set(self, **values: Any) -> None:
        self._f.update(values)
        self._snapshot = None

    def snapshot(self) -> VehicleState:
        """The current frozen state (cached until the next change)."""
        if self._snapshot is None:
            self._snapshot = VehicleState(**self._f)
        return self._snapshot

    def _is_autopilot_heartbeat(self, msg: Any) -> bool:
        if msg.type in _NON_AUTOPILOT_TYPES or msg.autopilot == MAV_AUTOPILOT_INVALID:
            return False
        sysid = msg.get_srcSystem()
        if self._fixed_sysid is not None and sysid != self._fixed_sysid:
            return False
        known = self.autopilot_address
        return known is None or known == (sysid, msg.get_srcComponent())

    def _from_autopilot(self, msg: Any) -> bool:
        return self.autopilot_address == (msg.get_srcSystem(), msg.get_srcComponent())

    # -- decoding -------------------------------------------------------------------------
    def apply(self, msg: Any, now_s: float) -> ImuSample | None:
        """Fold one decoded message received at local time ``now_s``; returns an IMU sample if it was one."""
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self._heartbeat(msg, now_s)
            return None
        if not self._from_autopilot(msg):
            self.ignored_messages += 1
            return None
        handler = _HANDLERS.get(kind)
        if handler is None:
            return None
        result = handler(self, msg, now_s)
        return result if isinstance(result, ImuSample) else None

    def _heartbeat(self, msg: Any, now_s: float) -> None:
        if msg.type == MAV_TYPE_GCS:
            self._set(last_gcs_heartbeat_s=now_s, gcs_system_id=msg.get_srcSystem())
            return
        if not self._is_autopilot_heartbeat(msg):
            self.ignored_messages += 1
            return
        profile = self._forced_profile or profile_for_autopilot(msg.autopilot) or self.profile
        self.profile = profile
        self._set(
            autopilot=None if profile is None else profile.name,
            autopilot_system_id=msg.get_srcSystem(),
            autopilot_component_id=msg.get_srcComponent(),
            vehicle_type=int(msg.type),
            armed=bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED),
            custom_mode=int(msg.custom_mode),
            mode=None if profile is None else profile.mode_name(int(msg.custom_mode)),
            system_status=int(msg.system_status),
            last_autopilot_heartbeat_s=now_s,
        )

    def _attitude(self, msg: Any, now_s: float) -> None:
        rpy = (msg.roll, msg.pitch, msg.yaw)
        self._set(
            attitude_rpy_rad=_ro(rpy, (3,)),
            angular_rate_body_rad_s=_ro((msg.rollspeed, msg.pitchspeed, msg.yawspeed), (3,)),
            R_ned_body=_ro(frames.rotation_from_euler_zyx(*rpy), (3, 3)),
            attitude_stamp_s=now_s,
        )

    def _attitude_quaternion(self, msg: Any, now_s: float) -> None:
        q_wxyz = np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=np.float64)
        norm = float(np.linalg.norm(q_wxyz))
        if not math.isfinite(norm) or norm < 1e-6:
            return
        R = frames.rotation_from_quaternion_wxyz(q_wxyz / norm)
        self._set(
            attitude_rpy_rad=_ro(frames.euler_zyx_from_rotation(R), (3,)),
            angular_rate_body_rad_s=_ro((msg.rollspeed, msg.pitchspeed, msg.yawspeed), (3,)),
            R_ned_body=_ro(R, (3, 3)),
            attitude_stamp_s=now_s,
        )

    def _local_position(self, msg: Any, now_s: float) -> None:
        self._set(
            position_ned_m=_ro((msg.x, msg.y, msg.z), (3,)),
            velocity_ned_m_s=_ro((msg.vx, msg.vy, msg.vz), (3,)),
            local_position_stamp_s=now_s,
        )

    def _sys_status(self, msg: Any, now_s: float) -> None:
        values: dict[str, Any] = {"battery_stamp_s": now_s}
        if msg.voltage_battery != UINT16_MAX:
            values["battery_voltage_v"] = msg.voltage_battery * 1e-3
        if msg.current_battery >= 0:
            values["battery_current_a"] = msg.current_battery * 1e-2
        if msg.battery_remaining >= 0:
            values["battery_remaining_pct"] = float(msg.battery_remaining)
        if int(msg.onboard_control_sensors_present) & MAV_SYS_STATUS_PREARM_CHECK:
            values["prearm_ok"] = bool(int(msg.onboard_control_sensors_health) & MAV_SYS_STATUS_PREARM_CHECK)
        self._set(**values)

    def _home_position(self, msg: Any, now_s: float) -> None:
        self._set(home_position_stamp_s=now_s)

    def _statustext(self, msg: Any, now_s: float) -> None:
        text = str(msg.text).rstrip("\x00").strip()
        if text.startswith(_ARMING_TEXT_PREFIXES):
            self._set(arming_text=text, arming_text_stamp_s=now_s)

    def _battery_status(self, msg: Any, now_s: float) -> None:
        if msg.id != 0:
            return
        values: dict[str, Any] = {"battery_stamp_s": now_s}
        cells = [v for v in msg.voltages if v != UINT16_MAX]
        cells += [v for v in (getattr(msg, "voltages_ext", None) or []) if v not in (0, UINT16_MAX)]
        if cells:
            values["battery_voltage_v"] = sum(cells) * 1e-3
        if msg.current_battery >= 0:
            values["battery_current_a"] = msg.current_battery * 1e-2
        if msg.battery_remaining >= 0:
            values["battery_remaining_pct"] = float(msg.battery_remaining)
        self._set(**values)

    def _distance_sensor(self, msg: Any, now_s: float) -> None:
        orientation = int(msg.orientation)
        if orientation not in (MAV_SENSOR_ROTATION_PITCH_270, MAV_SENSOR_ROTATION_PITCH_90):
            return
        distance_cm = int(msg.current_distance)
        valid = msg.min_distance <= distance_cm <= msg.max_distance and distance_cm != UINT16_MAX
        distance_m = distance_cm * 1e-2 if valid else None
        if orientation == MAV_SENSOR_ROTATION_PITCH_270:
            self._set(rangefinder_m=distance_m, rangefinder_stamp_s=now_s)
        else:
            self._set(rangefinder_up_m=distance_m, rangefinder_up_stamp_s=now_s)

    def _extended_sys_state(self, msg: Any, now_s: float) -> None:
        self._set(landed_state=_LANDED_STATES.get(int(msg.landed_state)))

    def _ekf_status(self, msg: Any, now_s: float) -> None:
        self._set(ekf_flags=int(msg.flags), ekf_stamp_s=now_s)

    def _gps_global_origin(self, msg: Any, now_s: float) -> None:
        self._set(
            ekf_origin_set=True,
            ekf_origin_lat_deg=msg.latitude * 1e-7,
            ekf_origin_lon_deg=msg.longitude * 1e-7,
            ekf_origin_alt_m=msg.altitude * 1e-3,
        )

    def _imu_stamp(self, time_usec: int, now_s: float) -> float:
        local = self._timesync.to_local_s(time_usec * 1e-6)
        return now_s if local is None else local

    def _imu(
        self, stamp_s: float, gyro: tuple[float, float, float], accel: tuple[float, float, float]
    ) -> ImuSample | None:
        values = (*gyro, *accel)
        if not all(math.isfinite(v) for v in values):
            self.rejected_imu += 1
            return None
        sample = ImuSample(stamp_s=stamp_s, gyro_rad_s=_ro(gyro, (3,)), accel_m_s2=_ro(accel, (3,)))
        self._set(last_imu=sample)
        return sample

    def _highres_imu(self, msg: Any, now_s: float) -> ImuSample | None:
        return self._imu(
            self._imu_stamp(int(msg.time_usec), now_s),
            (msg.xgyro, msg.ygyro, msg.zgyro),
            (msg.xacc, msg.yacc, msg.zacc),
        )

    def _scaled_imu(self, msg: Any, now_s: float) -> ImuSample | None:
        return self._imu(
            self._imu_stamp(int(msg.time_boot_ms) * 1000, now_s),
            (msg.xgyro * 1e-3, msg.ygyro * 1e-3, msg.zgyro * 1e-3),
            (msg.xacc * G_M_S2e3, msg.yacc * G_M_S2e3, msg.zacc * G_M_S2e3),
        )

    def _sim_state(self, msg: Any, now_s: float) -> None:
        origin = self._origin_deg()
        if origin is None:
            return
        lat0, lon0, alt0 = origin
        lat = msg.lat_int * 1e-7 if msg.lat_int != 0 else float(msg.lat)
        lon = msg.lon_int * 1e-7 if msg.lon_int != 0 else float(msg.lon)
        p_ned = ned_from_geodetic(lat, lon, float(msg.alt), lat0, lon0, alt0)
        q_wxyz = np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=np.float64)
        norm = float(np.linalg.norm(q_wxyz))
        if not math.isfinite(norm) or norm < 1e-6:
            R = frames.rotation_from_euler_zyx(msg.roll, msg.pitch, msg.yaw)
        else:
            R = frames.rotation_from_quaternion_wxyz(q_wxyz / norm)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = p_ned
        truth = SimTruth(stamp_s=now_s, T_ned_body=_ro(T, (4, 4)), velocity_ned_m_s=_ro((msg.vn, msg.ve, msg.vd), (3,)))
        self._set(sim_truth=truth)

    def _origin_deg(self) -> tuple[float, float, float] | None:
        if self._f.get("ekf_origin_set"):
            return (self._f["ekf_origin_lat_deg"], self._f["ekf_origin_lon_deg"], self._f["ekf_origin_alt_m"])
        return self._origin


G_M_S2e3 = G_M_S2 * 1e-3  # milli-g to m/s^2
MAV_SYS_STATUS_PREARM_CHECK = 0x10000000
# ArduPilot: "PreArm: ..." (periodic) and "Arm: ..." (on an ARM command); PX4: "Preflight Fail: ..."
_ARMING_TEXT_PREFIXES = ("PreArm:", "Arm:", "Preflight")
_LANDED_STATES = {1: "on_ground", 2: "in_air", 3: "takeoff", 4: "landing"}  # MAV_LANDED_STATE


_HANDLERS: dict[str, Any] = {
    "ATTITUDE": StateTracker._attitude,
    "ATTITUDE_QUATERNION": StateTracker._attitude_quaternion,
    "LOCAL_POSITION_NED": StateTracker._local_position,
    "SYS_STATUS": StateTracker._sys_status,
    "BATTERY_STATUS": StateTracker._battery_status,
    "DISTANCE_SENSOR": StateTracker._distance_sensor,
    "EKF_STATUS_REPORT": StateTracker._ekf_status,
    "EXTENDED_SYS_STATE": StateTracker._extended_sys_state,
    "GPS_GLOBAL_ORIGIN": StateTracker._gps_global_origin,
    "HIGHRES_IMU": StateTracker._highres_imu,
    "SCALED_IMU": StateTracker._scaled_imu,
    "SIM_STATE": StateTracker._sim_state,
    "HOME_POSITION": StateTracker._home_position,
    "STATUSTEXT": StateTracker._statustext,
}
