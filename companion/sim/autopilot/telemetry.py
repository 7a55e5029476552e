"""The fake autopilot's outgoing telemetry: HEARTBEAT, the streamed messages and the ones sent on request."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geometry import frames
from companion.sim.autopilot.config import (
    EARTH_RADIUS_M,
)
from companion.sim.autopilot.core import AutopilotCore
from companion.sim.autopilot.ekf import VISODOM_TIMEOUT_S
from companion.sim.autopilot.profiles import Behaviour


class Telemetry(AutopilotCore):
    """Builds every message the fake sends (from the true vehicle, the EKF model and the flight logic)."""

    # ----- telemetry builders ----------------------------------------------------------------

    def _time_boot_ms(self, now_s: float) -> int:
        return round((now_s - self._boot_s) * 1000.0) & 0xFFFFFFFF

    def _time_usec(self, now_s: float) -> int:
        return round((now_s - self._boot_s) * 1e6)

    def _heartbeat(self) -> Any:
        flight = self._flight
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if flight.mode.behaviour in (
            Behaviour.GUIDED,
            Behaviour.OFFBOARD,
            Behaviour.TAKEOFF,
            Behaviour.RTL,
            Behaviour.LAND,
        ):
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if flight.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self._battery_remaining_pct() <= self.config.battery.critical_remaining_pct:
            status = mavlink.MAV_STATE_CRITICAL
        elif flight.armed:
            status = mavlink.MAV_STATE_ACTIVE
        else:
            status = mavlink.MAV_STATE_STANDBY
        return self._mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, self.profile.autopilot, base, flight.mode.custom_mode, status, 3
        )

    def _send_gcs_heartbeat(self) -> None:
        msg = self._gcs_mav.heartbeat_encode(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
        )
        self._send(msg, self._gcs_mav)

    def _llh(
        self, position_ned_m: tuple[float, float, float], origin: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        lat0, lon0, alt0 = origin
        lat = lat0 + math.degrees(position_ned_m[0] / EARTH_RADIUS_M)
        lon = lon0 + math.degrees(position_ned_m[1] / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return lat, lon, alt0 - position_ned_m[2]

    def _ekf_position(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        sigma = self.config.ekf_position_noise_m
        p = self._vehicle.position_ned_m
        n = self._noise_rng.normal(0.0, sigma, 3) if sigma > 0 else np.zeros(3)
        return (p[0] + n[0], p[1] + n[1], p[2] + n[2]), self._vehicle.velocity_ned_m_s

    def _send_stream(self, name: str, now_s: float) -> None:
        msg = self._build(name, now_s)
        if msg is not None:
            self._send(msg)
        if name == "DISTANCE_SENSOR":
            up = self._distance_up(now_s)
            if up is not None:
                self._send(up)

    def _build(self, name: str, now_s: float) -> Any:
        v = self._vehicle
        mav = self._mav
        t_ms = self._time_boot_ms(now_s)
        cfg = self.config
        healthy = self._flight.ekf_healthy(now_s)
        if name == "HEARTBEAT":
            return self._heartbeat()
        if name == "ATTITUDE":
            s = cfg.ekf_attitude_noise_rad
            n = self._noise_rng.normal(0.0, s, 3) if s > 0 else np.zeros(3)
            r = v.rates_body_rad_s
            yaw = math.atan2(math.sin(v.yaw_rad + n[2]), math.cos(v.yaw_rad + n[2]))
            return mav.attitude_encode(t_ms, v.roll_rad + n[0], v.pitch_rad + n[1], yaw, r[0], r[1], r[2])
        if name == "ATTITUDE_QUATERNION":
            q = frames.quaternion_wxyz_from_rotation(v.R_ned_body())
            r = v.rates_body_rad_s
            return mav.attitude_quaternion_encode(t_ms, *(float(x) for x in q), r[0], r[1], r[2], [0.0] * 4)
        if name == "LOCAL_POSITION_NED":
            if self.config.require_vision and self._flight.last_vision_s is None:
                return None  # no position source yet: ArduPilot/PX4 do not publish a local position
            p, vel = self._ekf_position()
            return mav.local_position_ned_encode(t_ms, p[0], p[1], p[2], vel[0], vel[1], vel[2])
        if name == "GLOBAL_POSITION_INT":
            if self._origin is None:
                return None
            p, vel = self._ekf_position()
            lat, lon, alt = self._llh(p, self._origin)
            hdg = int(math.degrees(v.yaw_rad) % 360.0 * 100.0)
            return mav.global_position_int_encode(
                t_ms,
                int(lat * 1e7),
                int(lon * 1e7),
                int(alt * 1000),
                int(-p[2] * 1000),
                int(vel[0] * 100),
                int(vel[1] * 100),
                int(vel[2] * 100),
                hdg,
            )
        if name == "SYS_STATUS":
            sensors = (
                mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
                | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
                | mavlink.MAV_SYS_STATUS_SENSOR_LASER_POSITION
                | mavlink.MAV_SYS_STATUS_AHRS
                | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
                | mavlink.MAV_SYS_STATUS_PREARM_CHECK
                | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            )
            if cfg.require_vision:
                sensors |= mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION
            health = sensors
            age = self._flight.ekf.vision_age_s(now_s)
            if cfg.require_vision and (age is None or age > VISODOM_TIMEOUT_S or not healthy):
                health &= ~mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION
            if self._flight.prearm_failures(now_s, v):
                health &= ~mavlink.MAV_SYS_STATUS_PREARM_CHECK
            if self._battery_remaining_pct() <= cfg.battery.critical_remaining_pct:
                health &= ~mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
            return mav.sys_status_encode(
                sensors,
                sensors,
                health,
                200,
                int(self._battery_voltage() * 1000),
                int(self._battery.current_a * 100),
                int(self._battery_remaining_pct()),
                0,
                self.stats["parse_errors"] & 0xFFFF,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            )
        if name == "BATTERY_STATUS":
            voltage = self._battery_voltage()
            cells = cfg.battery.cells
            cell_mv = int(voltage / cells * 1000)
            # cells 1..10 in `voltages` (UINT16_MAX = no cell), 11..14 in `voltages_ext` (0 = no cell)
            voltages = [cell_mv] * min(cells, 10) + [65535] * max(0, 10 - cells)
            voltages_ext = [cell_mv] * max(0, cells - 10) + [0] * (4 - max(0, cells - 10))
            remaining = self._battery_remaining_pct()
            if remaining <= cfg.battery.critical_remaining_pct:
                charge_state = mavlink.MAV_BATTERY_CHARGE_STATE_CRITICAL
            elif remaining <= cfg.battery.low_remaining_pct:
                charge_state = mavlink.MAV_BATTERY_CHARGE_STATE_LOW
            else:
                charge_state = mavlink.MAV_BATTERY_CHARGE_STATE_OK
            current = self._battery.current_a
            time_remaining = (
                int(3.6 * (cfg.battery.capacity_mah - self._battery.consumed_mah) / current) if current > 0 else 0
            )
            return mav.battery_status_encode(
                0,
                mavlink.MAV_BATTERY_FUNCTION_ALL,
                mavlink.MAV_BATTERY_TYPE_LIPO,
                2500,
                voltages,
                int(current * 100),
                int(self._battery.consumed_mah),
                int(self._battery.consumed_energy_j / 100.0),
                int(remaining),
                max(0, time_remaining),
                charge_state,
                voltages_ext,
                0,
                0,
            )
        if name == "EXTENDED_SYS_STATE":
            return mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, self._flight.landed_state(v, now_s))
        if name == "EKF_STATUS_REPORT":
            ekf = self._flight.ekf
            flags = ekf.flags(now_s, self._origin is not None)
            vel_var, pos_var = ekf.variances(now_s)
            return mav.ekf_status_report_encode(flags, vel_var, pos_var, 0.05, 0.05, 0.0, 0.0)
        if name == "DISTANCE_SENSOR":
            return self._distance_down(t_ms)
        if name == "HIGHRES_IMU":
            return self._highres_imu(now_s)
        if name == "SIM_STATE":
            return self._sim_state()
        if name == "GPS_GLOBAL_ORIGIN":
            if self._origin is None:
                return None
            lat, lon, alt = self._origin
            return mav.gps_global_origin_encode(
                round(lat * 1e7), round(lon * 1e7), round(alt * 1000), self._time_usec(now_s)
            )
        if name == "HOME_POSITION":
            if self._origin is None or (self.profile.name == "ardupilot" and not self._flight.home_set):
                return None
            home = (self._flight.home_ne_m[0], self._flight.home_ne_m[1], 0.0)
            lat, lon, alt = self._llh(home, self._origin)
            return mav.home_position_encode(
                int(lat * 1e7),
                int(lon * 1e7),
                int(alt * 1000),
                home[0],
                home[1],
                home[2],
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
                self._time_usec(now_s),
            )
        if name == "AUTOPILOT_VERSION":
            caps = (
                mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
            )
            version = (
                (4 << 24) | (5 << 16) | (0 << 8) | 255
                if self.profile.name == "ardupilot"
                else (1 << 24) | (15 << 16) | 255
            )
            return mav.autopilot_version_encode(
                caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x5EED0000 + cfg.system_id, [0] * 18
            )
        return None

    def _distance_down(self, t_ms: int) -> Any:
        v = self._vehicle
        cfg = self.config
        tilt_cos = max(math.cos(v.roll_rad) * math.cos(v.pitch_rad), 0.2)
        slant = max(v.height_m, 0.0) / tilt_cos + float(self._noise_rng.normal(0.0, cfg.rangefinder_noise_m))
        min_m, max_m = 0.2, cfg.rangefinder_max_m
        distance = min(max(slant, min_m), max_m + 0.01)
        return self._mav.distance_sensor_encode(
            t_ms,
            int(min_m * 100),
            int(max_m * 100),
            round(distance * 100),
            mavlink.MAV_DISTANCE_SENSOR_LASER,
            0,
            mavlink.MAV_SENSOR_ROTATION_PITCH_270,
            1,
            0.0,
            0.0,
            [0.0] * 4,
            100,
        )

    def _distance_up(self, now_s: float) -> Any:
        ceiling = self._ceiling_m(now_s)
        if ceiling is None:
            return None
        clearance = max(ceiling - self._vehicle.height_m, 0.2)
        return self._mav.distance_sensor_encode(
            self._time_boot_ms(now_s),
            20,
            int(self.config.rangefinder_max_m * 100),
            round(clearance * 100),
            mavlink.MAV_DISTANCE_SENSOR_LASER,
            1,
            mavlink.MAV_SENSOR_ROTATION_PITCH_90,
            1,
            0.0,
            0.0,
            [0.0] * 4,
            100,
        )

    def _highres_imu(self, now_s: float) -> Any:
        n = max(self._imu_n, 1)
        if self._imu_n == 0:
            f = self._vehicle.specific_force_body_m_s2
            w = self._vehicle.rates_body_rad_s
        else:
            f = (self._imu_f_sum[0] / n, self._imu_f_sum[1] / n, self._imu_f_sum[2] / n)
            w = (self._imu_w_sum[0] / n, self._imu_w_sum[1] / n, self._imu_w_sum[2] / n)
        self._imu_f_sum = [0.0, 0.0, 0.0]
        self._imu_w_sum = [0.0, 0.0, 0.0]
        self._imu_n = 0
        s = self.config.imu_noise
        na = self._noise_rng.normal(0.0, s.accel_noise_m_s2, 3) if s.accel_noise_m_s2 > 0 else np.zeros(3)
        ng = self._noise_rng.normal(0.0, s.gyro_noise_rad_s, 3) if s.gyro_noise_rad_s > 0 else np.zeros(3)
        acc = [f[i] + self._accel_bias[i] + na[i] for i in range(3)]
        gyro = [w[i] + self._gyro_bias[i] + ng[i] for i in range(3)]
        pressure_alt = self.config.reference_lla[2] + self._vehicle.height_m
        pressure_hpa = 1013.25 * (1.0 - 2.25577e-5 * pressure_alt) ** 5.25588
        return self._mav.highres_imu_encode(
            self._time_usec(now_s),
            acc[0],
            acc[1],
            acc[2],
            gyro[0],
            gyro[1],
            gyro[2],
            0.21,
            0.0,
            0.42,
            pressure_hpa,
            0.0,
            pressure_alt,
            25.0,
            0b1_1111_1111_1111,
            0,
        )

    def _sim_state(self) -> Any:
        v = self._vehicle
        R = v.R_ned_body()
        q = frames.quaternion_wxyz_from_rotation(R)
        origin = self._origin if self._origin is not None else self.config.reference_lla
        lat, lon, alt = self._llh(v.position_ned_m, origin)
        f, w = v.specific_force_body_m_s2, v.rates_body_rad_s
        vel = v.velocity_ned_m_s
        return self._mav.sim_state_encode(
            float(q[0]),
            float(q[1]),
            float(q[2]),
            float(q[3]),
            v.roll_rad,
            v.pitch_rad,
            v.yaw_rad,
            f[0],
            f[1],
            f[2],
            w[0],
            w[1],
            w[2],
            lat,
            lon,
            alt,
            0.0,
            0.0,
            vel[0],
            vel[1],
            vel[2],
            round(lat * 1e7),
            round(lon * 1e7),
        )
