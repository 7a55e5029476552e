"""The navigation filter's timeline: (re)initialization, IMU prediction, the history buffer and replay.

IMU samples (body FRD) drive the prediction; a snapshot after each one lets a late measurement roll
the filter back to its stamp (s) and replay samples and measurements in stamp order.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from typing import Any

import numpy as np

from companion.checks import check_last_two_dims, check_transform
from companion.estimation import model
from companion.estimation.filter_sources import FilterSources
from companion.estimation.filter_state import _KINDS, _Measurement, _Snapshot, _SourceState
from companion.estimation.types import ImuSample
from companion.geometry import frames, se3


class FilterTimeline(FilterSources):
    """Initialization, IMU propagation, the sample / snapshot / measurement buffers and rollback-replay."""

    # ------------------------------------------------------------------ setup

    def initialize(
        self,
        stamp_s: float,
        T_ned_body: Any,
        velocity_ned_m_s: Any = None,
        *,
        gyro_bias_rad_s: Any = None,
        accel_bias_m_s2: Any = None,
        covariance: Any = None,
    ) -> None:
        """(Re)start the filter at `stamp_s` with pose T_ned_body (4x4) and optional velocity/biases.

        `covariance` is the (15, 15) error-state covariance (dp, dv, dtheta, dbg,
        dba; see docs/estimation.md); None uses the configured initial standard
        deviations. Clears the buffers and the source selection; counters and
        `reset_counter` are kept. IMU samples older than `stamp_s` are then ignored.
        """
        T = check_transform(T_ned_body, "T_ned_body")
        cfg = self.config
        v = np.zeros(3) if velocity_ned_m_s is None else np.asarray(velocity_ned_m_s, dtype=np.float64).reshape(3)
        bg = np.zeros(3) if gyro_bias_rad_s is None else np.asarray(gyro_bias_rad_s, dtype=np.float64).reshape(3)
        ba = np.zeros(3) if accel_bias_m_s2 is None else np.asarray(accel_bias_m_s2, dtype=np.float64).reshape(3)
        if covariance is None:
            imu = cfg.imu
            std = np.concatenate(
                [
                    np.full(3, cfg.initial_position_std_m),
                    np.full(3, cfg.initial_velocity_std_m_s),
                    [cfg.initial_tilt_std_rad, cfg.initial_tilt_std_rad, cfg.initial_yaw_std_rad],
                    np.full(3, imu.gyro_bias_initial_std_rad_s),
                    np.full(3, imu.accel_bias_initial_std_m_s2),
                ]
            )
            P15 = np.diag(std**2)
        else:
            P15 = check_last_two_dims(covariance, 15, 15, "covariance")
            P15 = 0.5 * (P15 + P15.T)
        self._x = model.new_state(T[:3, 3], v, T[:3, :3], bg, ba)
        P = np.zeros((model.ERROR_SIZE, model.ERROR_SIZE))
        P[:15, :15] = P15
        self._P = P
        self._reset_clone_covariance()
        self._t = float(stamp_s)
        self._gyro = (0.0, 0.0, 0.0)
        self._accel = (0.0, 0.0, 0.0)
        self._initialized = True
        self._imu.clear()
        self._snaps.clear()
        self._snap_t.clear()
        self._meas.clear()
        self._meas_key.clear()
        self._src = _SourceState()
        self._output = None
        self._last_stamp = dict.fromkeys(_KINDS, -math.inf)

    def _auto_initialize(self, sample: ImuSample) -> None:
        """Level from the accelerometer (vehicle assumed at rest), yaw from the config, origin position."""
        f = sample.accel_m_s2
        roll = math.atan2(-f[1], -f[2])
        pitch = math.atan2(f[0], math.hypot(f[1], f[2]))
        R = frames.rotation_from_euler_zyx(roll, pitch, self.config.initial_yaw_rad)
        self.initialize(sample.stamp_s, se3.make(R, np.zeros(3)))

    # ------------------------------------------------------------------ IMU

    def add_imu(self, sample: ImuSample) -> None:
        """Propagate with one IMU sample (body FRD gyro rad/s, specific force m/s^2)."""
        if not self._initialized:
            self._auto_initialize(sample)
        t = sample.stamp_s
        if not self._snaps:
            if t < self._t:
                self._count("imu_before_init")
                return
            # First sample after initialization: hold its reading back to the initial stamp.
            self._gyro = tuple(sample.gyro_rad_s.tolist())
            self._accel = tuple(sample.accel_m_s2.tolist())
            self._imu_count += 1
            self._step_imu(sample)
            return
        last_t = self._snap_t[-1]
        if t <= last_t:
            self._count("imu_out_of_order")
            return
        self._imu_count += 1
        if t - last_t > self.config.max_imu_dt_s:
            self._count("imu_gap")
        if self._t > last_t:
            # Measurements were applied past the last sample with a held reading:
            # replay them with the reading interpolated towards this sample.
            self._imu.append(sample)
            self._replay(len(self._snaps) - 1)
        else:
            self._step_imu(sample)
        self._prune()

    def _step_imu(self, sample: ImuSample) -> None:
        self._propagate_to(sample.stamp_s, tuple(sample.gyro_rad_s.tolist()), tuple(sample.accel_m_s2.tolist()))
        self._imu.append(sample)
        self._snaps.append(_Snapshot(self._t, self._gyro, self._accel, self._x.copy(), self._P, self._src,
                                     self._output))
        self._snap_t.append(self._t)

    def _propagate_to(self, t: float, gyro_end: tuple[float, ...], accel_end: tuple[float, ...]) -> None:
        dt = t - self._t
        if dt > 0.0:
            g0, a0 = self._gyro, self._accel
            gyro_mid = (0.5 * (g0[0] + gyro_end[0]), 0.5 * (g0[1] + gyro_end[1]), 0.5 * (g0[2] + gyro_end[2]))
            accel_mid = (0.5 * (a0[0] + accel_end[0]), 0.5 * (a0[1] + accel_end[1]), 0.5 * (a0[2] + accel_end[2]))
            F = self._F
            model.propagate_in_place(self._x, gyro_mid, accel_mid, dt, self.config.gravity_m_s2, F)
            # The clone's block of F is the identity: P_cc stays, P_xc <- F P_xc, all in one product.
            P = F @ self._P @ F.T
            P.reshape(-1)[:: model.ERROR_SIZE + 1] += self._qdiag * dt
            self._P = P
            self._t = t
        self._gyro = gyro_end
        self._accel = accel_end

    def _prune(self) -> None:
        self._prune_countdown -= 1
        if self._prune_countdown > 0:
            return
        self._prune_countdown = 16
        cut = self._snap_t[-1] - self.config.buffer_s
        n = bisect_right(self._snap_t, cut) - 1
        if n > 0:
            del self._snaps[:n]
            del self._snap_t[:n]
            del self._imu[:n]
            first = self._snap_t[0]
            m = bisect_left(self._meas_key, (first, -1))
            if m > 0:
                del self._meas[:m]
                del self._meas_key[:m]

    def _replay(self, k: int) -> None:
        """Restore snapshot k and re-run every later IMU sample and buffered measurement in stamp order."""
        snap = self._snaps[k]
        self._x[:] = snap.x
        self._P = snap.P
        self._t = snap.stamp_s
        self._gyro = snap.gyro
        self._accel = snap.accel
        self._src = snap.src
        self._output = snap.output
        samples = self._imu[k + 1 :]
        del self._imu[k + 1 :]
        del self._snaps[k + 1 :]
        del self._snap_t[k + 1 :]
        j = bisect_left(self._meas_key, (snap.stamp_s, -1))
        meas = self._meas
        for sample in samples:
            while j < len(meas) and meas[j].stamp_s < sample.stamp_s:
                self._process(meas[j], sample)
                j += 1
            self._step_imu(sample)
        while j < len(meas):
            self._process(meas[j], None)
            j += 1

    # ------------------------------------------------------------------ measurements: processing

    def _add(self, kind: str, stamp_s: float, ok: bool, data: tuple[Any, ...]) -> None:
        if not math.isfinite(stamp_s):
            self._count("invalid")
            return
        if not self._snaps:
            self._count("not_initialized")
            return
        if stamp_s <= self._last_stamp[kind]:
            self._count("out_of_order")
            return
        if stamp_s < self._snap_t[0]:
            self._count("too_old")
            return
        if stamp_s > self._snap_t[-1] + self.config.max_extrapolation_s:
            self._count("too_new")
            return
        self._last_stamp[kind] = stamp_s
        self._seq += 1
        m = _Measurement(stamp_s, self._seq, kind, ok, data)
        key = (stamp_s, self._seq)
        i = bisect_right(self._meas_key, key)
        self._meas_key.insert(i, key)
        self._meas.insert(i, m)
        if stamp_s >= self._t:
            self._process(m, None)
        else:
            self._replay(bisect_right(self._snap_t, stamp_s) - 1)

    def _process(self, m: _Measurement, next_sample: ImuSample | None) -> None:
        t = m.stamp_s
        if t > self._t:
            if next_sample is None:
                self._propagate_to(t, self._gyro, self._accel)
            else:
                alpha = (t - self._t) / (next_sample.stamp_s - self._t)
                g0, a0 = self._gyro, self._accel
                g1, a1 = next_sample.gyro_rad_s, next_sample.accel_m_s2
                gyro = tuple(g0[i] + alpha * (float(g1[i]) - g0[i]) for i in range(3))
                accel = tuple(a0[i] + alpha * (float(a1[i]) - a0[i]) for i in range(3))
                self._propagate_to(t, gyro, accel)
        if m.kind == "rack":
            outcome = self._apply_rack(m)
        elif m.kind == "ground":
            outcome = self._apply_ground(m)
        else:
            outcome = self._apply_range(m)
        if not m.counted:
            m.counted = True
            self._count(f"{outcome}_{m.kind}")
