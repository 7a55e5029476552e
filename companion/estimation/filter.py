"""Delayed-state (stochastic cloning) error-state EKF fusing the IMU with the visual estimates.

Tardif et al., section III-B: the IMU predicts at its own rate, visual
measurements correct at camera rate; relative poses from the ground odometer
are applied between a cloned copy of the pose (taken at the previous ground
frame) and the current pose; a failed frame makes no correction and re-clones.
Absolute poses from the rack tracker and rangefinder heights are ordinary
EKF updates. See docs/estimation.md for the models, defaults and the source
selection rules.

Time alignment: the filter keeps ~`buffer_s` of IMU samples, a snapshot of the
filter after each one, and the measurements applied in that window. A
measurement older than the current filter time rolls the filter back to the
last snapshot before its stamp and replays samples and measurements in stamp
order. A measurement newer than the last IMU sample is applied by holding the
last IMU reading; the next IMU sample replays it with the interpolated reading.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.stats import chi2

from companion.checks import FloatArray, check_last_two_dims, check_transform
from companion.errors import InputError
from companion.estimation import model
from companion.estimation.types import (
    GroundEstimateLike,
    ImuSample,
    NavEstimate,
    NavFilterConfig,
    NavFilterStats,
    RackEstimateLike,
)
from companion.geometry import frames, se3

_POSE_IX = np.ix_(model.POSE_IDX, model.POSE_IDX)
_KINDS = ("rack", "ground", "range")
_CLONE_STAMP_TOL_S = 1e-3


@dataclass(frozen=True)
class _SourceState:
    """Source-selection state; immutable so snapshots share it by reference."""

    source: str = "none"
    rack_good: int = 0
    rack_bad: int = 0
    rack_unsettled: int = 0
    ground_bad: int = 0
    last_rack_ok_s: float = -math.inf
    last_ground_ok_s: float = -math.inf
    clone_valid: bool = False
    clone_stamp_s: float = -math.inf


@dataclass(frozen=True)
class _Output:
    """The posterior right after the latest applied visual correction."""

    stamp_s: float
    x: FloatArray
    P_pose: FloatArray
    P_vel: FloatArray
    source: str


@dataclass
class _Measurement:
    """A buffered measurement (mutable only for its bookkeeping flags)."""

    stamp_s: float
    seq: int
    kind: str
    ok: bool
    data: tuple[Any, ...]
    counted: bool = False
    reset_counted: bool = False


@dataclass(frozen=True)
class _Snapshot:
    stamp_s: float
    gyro: tuple[float, ...]
    accel: tuple[float, ...]
    x: FloatArray
    P: FloatArray
    src: _SourceState
    output: _Output | None


class NavigationFilter:
    """IMU-driven error-state EKF with a cloned pose, source selection and measurement rollback.

    Frames: NED world, body FRD. All stamps (s) on one time base (the daemon
    converts autopilot IMU stamps with the TIMESYNC offset). Not thread-safe:
    call it from one thread or task.
    """

    def __init__(
        self,
        config: NavFilterConfig | None = None,
        *,
        T_ned_rack: Any = None,
        T_body_cam: Any = None,
    ) -> None:
        self.config = config if config is not None else NavFilterConfig()
        cfg = self.config
        self._T_ned_rack = frames.default_T_ned_rack() if T_ned_rack is None else check_transform(
            T_ned_rack, "T_ned_rack"
        )
        self._T_body_cam = frames.default_T_body_cam() if T_body_cam is None else check_transform(
            T_body_cam, "T_body_cam"
        )
        self._T_cam_body = se3.inverse(self._T_body_cam)
        self._Ad_body_cam = se3.adjoint(self._T_body_cam)
        self._gate = {dof: float(chi2.ppf(cfg.gate_probability, dof)) for dof in (1, 2, 3, 6)}
        imu = cfg.imu
        # Continuous process noise on the diagonal of the 21 error states (per second).
        self._qdiag = np.concatenate(
            [
                np.zeros(3),
                np.full(3, imu.accel_noise_density_m_s2_sqrt_hz**2),
                np.full(3, imu.gyro_noise_density_rad_s_sqrt_hz**2),
                np.full(3, imu.gyro_bias_random_walk_rad_s2_sqrt_hz**2),
                np.full(3, imu.accel_bias_random_walk_m_s3_sqrt_hz**2),
                np.zeros(6),
            ]
        )
        self._x = np.zeros(model.STATE_SIZE)
        # The covariance is never modified in place (every writer rebinds it), so
        # snapshots share it by reference.
        self._P = np.zeros((model.ERROR_SIZE, model.ERROR_SIZE))
        self._F = model.new_transition()
        self._gyro: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._accel: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._t = -math.inf
        self._initialized = False
        self._imu: list[ImuSample] = []
        self._snaps: list[_Snapshot] = []
        self._snap_t: list[float] = []
        self._meas: list[_Measurement] = []
        self._meas_key: list[tuple[float, int]] = []
        self._seq = 0
        self._src = _SourceState()
        self._output: _Output | None = None
        self._counts: dict[str, int] = {}
        self._reset_counter = 0
        self._imu_count = 0
        self._last_stamp: dict[str, float] = dict.fromkeys(_KINDS, -math.inf)
        self._prune_countdown = 0

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

    # ------------------------------------------------------------------ measurements: entry points

    def add_rack(self, est: RackEstimateLike, stamp_s: float, *, reset: bool = False) -> None:
        """Absolute pose from the rack tracker, captured at `stamp_s`.

        T_ned_body = T_ned_rack @ T_rack_cam @ inverse(T_body_cam); the camera-frame
        right-perturbation covariance maps to the body frame with Ad(T_body_cam).
        `reset`: the tracker was just moved to a pose found independently of the estimate (rack
        acquisition, the rack's end): taken like a switch to the rack, a reset when it disagrees.
        """
        if not bool(est.ok):
            self.add_absolute_pose(stamp_s, np.eye(4), np.eye(6), source="rack", ok=False)
            return
        T_rack_cam = _matrix(est.T_rack_cam, 4, "est.T_rack_cam")
        cov_cam = _matrix(est.covariance, 6, "est.covariance")
        T_ned_body = self._T_ned_rack @ T_rack_cam @ self._T_cam_body
        cov_body = self._Ad_body_cam @ cov_cam @ self._Ad_body_cam.T
        self.add_absolute_pose(stamp_s, T_ned_body, cov_body, source="rack", ok=True, reset=reset)

    def add_ground(self, est: GroundEstimateLike, stamp_s: float, *, restart: bool = False) -> None:
        """Planar increment (NED dx, dy, dyaw since the odometer's previous frame) captured at `stamp_s`.

        Feed every odometer output, ok or not, in order: the increment is applied
        between the clone (taken at the previous ground frame) and now.
        `restart=True` marks the odometer's first frame after its own reset (the
        increment is ignored and only the clone is taken). When the estimate
        carries `dt_s` (the time spanned by the increment, as
        `companion.vision.ground.GroundEstimate` does), dt_s == 0 means a first
        frame and stamp_s - dt_s must match the clone's stamp (the odometer may
        keep an older reference frame after a failure): see `add_relative_pose`.
        """
        ok = bool(est.ok)
        cov = _matrix(est.covariance, 3, "est.covariance") if ok else np.eye(3)
        dt_s = getattr(est, "dt_s", None)
        reference = None
        if ok and dt_s is not None:
            dt = float(dt_s)
            if dt <= 0.0:
                restart = True
            else:
                reference = float(stamp_s) - dt
        self.add_relative_pose(
            stamp_s, float(est.dx_m), float(est.dy_m), float(est.dyaw_rad), cov, source="ground", ok=ok,
            restart=restart, reference_stamp_s=reference,
        )

    def add_absolute_pose(
        self, stamp_s: float, T_ned_body: Any, covariance_6x6: Any, source: str = "rack", *, ok: bool = True,
        reset: bool = False,
    ) -> None:
        """Absolute body pose T_ned_body (4x4) at `stamp_s`.

        `covariance_6x6`: right perturbation of T_ned_body in the body frame, twist
        order (v, w): T_true = T_ned_body @ exp(d), d ~ N(0, cov). `ok=False`
        reports a failed frame (counts towards switching away from the source).
        `reset=True`: taken like a switch to the source (a reset when it disagrees, see `add_rack`).
        """
        if source != "rack":
            raise InputError(f"source: absolute poses come from 'rack', got {source!r}")
        T = _matrix(T_ned_body, 4, "T_ned_body")
        C = _matrix(covariance_6x6, 6, "covariance_6x6")
        if ok:
            R = T[:3, :3]
            if (
                not (np.isfinite(T).all() and np.isfinite(C).all())
                or np.abs(R.T @ R - np.eye(3)).max() > 1e-6
                or np.linalg.det(R) <= 0.0
                or not _is_pd(C)
            ):
                self._count("invalid")
                return
            data: tuple[Any, ...] = (R.copy(), T[:3, 3].copy(), 0.5 * (C + C.T), bool(reset))
        else:
            data = ()
        self._add("rack", float(stamp_s), ok, data)

    def add_relative_pose(
        self,
        stamp_s: float,
        dx_m: float,
        dy_m: float,
        dyaw_rad: float,
        covariance_3x3: Any,
        source: str = "ground",
        ok: bool = True,
        *,
        restart: bool = False,
        reference_stamp_s: float | None = None,
    ) -> None:
        """Planar increment (NED metres, rad) since the previous ground update; covariance (3, 3) of it.

        Applied as a relative-pose measurement between the clone (the pose at the
        previous ground update, ok or not) and the pose at `stamp_s`; afterwards
        the clone is reset to the pose at `stamp_s`. `ok=False`: no correction,
        clone reset. `restart=True`: no correction (the odometer restarted), clone
        reset. `reference_stamp_s` (optional): capture time of the frame the
        increment starts from; when it differs from the clone's stamp by more than
        1 ms the increment is not applied (counted as `unanchored_ground`).
        """
        if source != "ground":
            raise InputError(f"source: relative poses come from 'ground', got {source!r}")
        C = _matrix(covariance_3x3, 3, "covariance_3x3")
        if ok:
            finite = math.isfinite(dx_m) and math.isfinite(dy_m) and math.isfinite(dyaw_rad) and np.isfinite(C).all()
            if not finite or not _is_pd(C):
                self._count("invalid")
                return
            ref = math.nan if reference_stamp_s is None else float(reference_stamp_s)
            data: tuple[Any, ...] = (float(dx_m), float(dy_m), float(dyaw_rad), 0.5 * (C + C.T), bool(restart), ref)
        else:
            data = ()
        self._add("ground", float(stamp_s), ok, data)

    def add_range(self, height_m: float, stamp_s: float) -> None:
        """Downward rangefinder reading (m along body +z, i.e. slant range) at `stamp_s`.

        Modelled as (ground_z_ned_m - z_ned) / cos(tilt) over flat ground.
        """
        h = float(height_m)
        if not math.isfinite(h):
            self._count("invalid")
            return
        cfg = self.config
        if not cfg.range_min_m <= h <= cfg.range_max_m:
            self._count("out_of_range")
            return
        if not cfg.use_range:
            self._count("ignored_range")
            return
        self._add("range", float(stamp_s), True, (h,))

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

    # ------------------------------------------------------------------ measurements: processing

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

    def _apply_rack(self, m: _Measurement) -> str:
        cfg = self.config
        st = self._src
        t = m.stamp_s
        if not m.ok:
            st = replace(st, rack_good=0, rack_bad=st.rack_bad + 1, rack_unsettled=0)
            if st.source == "rack" and st.rack_bad >= cfg.rack_failures_to_switch_out:
                st = self._switch_away_from_rack(st, t)
            self._src = st
            return "failed"
        R_m, p_m, cov, forced = m.data
        r, H = model.absolute_pose_residual(self._x, R_m, p_m)
        good = st.rack_good + 1
        # Back after a silence longer than the timeout, or a pose found independently of the estimate:
        # re-acquire like a switch (a reset if it disagrees).
        reacquire = (st.source == "rack" and t - st.last_rack_ok_s > cfg.source_timeout_s) or forced
        if (st.source != "rack" or reacquire) and st.rack_unsettled < cfg.rack_unsettled_frames_max:
            if not self._tilt_agrees(r, H, cov):
                # Roll and pitch are held by gravity through any vision outage; a tracker that disagrees
                # with them is still settling (e.g. re-locking at the rack's end): not healthy yet, no reset.
                self._src = replace(st, rack_good=0, rack_bad=0, rack_unsettled=st.rack_unsettled + 1)
                return "unsettled"
            st = replace(st, rack_unsettled=0)
        if st.source == "rack" and not reacquire:
            status = self._kalman(r, H, cov, self._gate[6])
            if status == "applied":
                self._src = replace(st, rack_good=good, rack_bad=0, last_rack_ok_s=t)
                self._record_output(t)
                return status
            st = replace(st, rack_good=0, rack_bad=st.rack_bad + 1)
            if st.rack_bad >= cfg.rack_failures_to_switch_out:
                st = self._switch_away_from_rack(st, t)
            self._src = st
            return status
        if good < cfg.rack_frames_to_switch_in and not reacquire:
            self._src = replace(st, rack_good=good, rack_bad=0)
            return "standby"
        # Switch to the rack: a smooth correction when it agrees with the estimate, a reset otherwise.
        p_before = self._x[model.P_SL].copy()
        R_before = model.rotation(self._x).copy()
        status = self._kalman(r, H, cov, self._gate[6])
        if status != "applied":
            self._reset_pose(R_m, p_m, cov)
            status = "reset"
        elif self._moved(p_before, R_before):
            # Consistent with the (loose) prior, but the estimate jumps: a discontinuity for the autopilot.
            status = "reset"
        if status == "reset" and not m.reset_counted:
            m.reset_counted = True
            self._reset_counter += 1
        self._src = replace(st, source="rack", rack_good=good, rack_bad=0, rack_unsettled=0, last_rack_ok_s=t)
        self._record_output(t)
        return status

    def _tilt_agrees(self, r: FloatArray, H: FloatArray, cov_body: FloatArray) -> bool:
        """Whether the roll/pitch part of an absolute pose residual passes the (2-dof) gate.

        The attitude residual (body frame) is split into the rotation about gravity (yaw, which the
        IMU does not hold) and the two tilt components perpendicular to it.
        """
        u = model.rotation(self._x).T @ np.array([0.0, 0.0, 1.0])  # NED down in the body frame
        a = np.array([1.0, 0.0, 0.0]) if abs(float(u[0])) < 0.9 else np.array([0.0, 1.0, 0.0])
        b1 = np.cross(u, a)
        b1 /= np.linalg.norm(b1)
        B = np.stack([b1, np.cross(u, b1)])
        H_th = H[3:6]
        S = B @ (H_th @ self._P @ H_th.T + cov_body[3:, 3:]) @ B.T
        r_t = B @ r[3:]
        try:
            d2 = float(r_t @ np.linalg.solve(S, r_t))
        except np.linalg.LinAlgError:
            return False
        return math.isfinite(d2) and d2 <= self._gate[2]

    def _moved(self, p_before: FloatArray, R_before: FloatArray) -> bool:
        """Whether the pose moved by more than the configured switch-reset step since (p_before, R_before)."""
        cfg = self.config
        dp = float(np.linalg.norm(self._x[model.P_SL] - p_before))
        c = 0.5 * (float(np.trace(R_before.T @ model.rotation(self._x))) - 1.0)
        dtheta = math.acos(min(1.0, max(-1.0, c)))
        return dp > cfg.switch_reset_position_m or dtheta > cfg.switch_reset_angle_rad

    def _switch_away_from_rack(self, st: _SourceState, t: float) -> _SourceState:
        ground_ok = st.ground_bad == 0 and t - st.last_ground_ok_s <= self.config.source_timeout_s
        return replace(st, source="ground" if ground_ok else "none", rack_good=0, rack_bad=0)

    def _apply_ground(self, m: _Measurement) -> str:
        cfg = self.config
        st = self._src
        t = m.stamp_s
        if not m.ok:
            st = replace(st, ground_bad=st.ground_bad + 1, clone_valid=True, clone_stamp_s=t)
            if st.source == "ground" and st.ground_bad >= cfg.ground_failures_to_switch_out:
                st = replace(st, source="none")
            self._src = st
            self._reset_clone()
            return "failed"
        dx_m, dy_m, dyaw_rad, cov, restart, ref = m.data
        st = replace(st, ground_bad=0, last_ground_ok_s=t)
        if st.source == "rack" and t - st.last_rack_ok_s > cfg.source_timeout_s:
            st = replace(st, source="ground", rack_good=0, rack_bad=0)
        elif st.source == "none":
            st = replace(st, source="ground")
        outcome = "standby"
        if st.source == "ground":
            if not st.clone_valid or restart:
                outcome = "anchor"
            elif not (math.isnan(ref) or abs(ref - st.clone_stamp_s) <= _CLONE_STAMP_TOL_S):
                outcome = "unanchored"
            else:
                r, H = model.relative_pose_residual(self._x, dx_m, dy_m, dyaw_rad)
                outcome = self._kalman(r, H, cov, self._gate[3])
                if outcome == "applied":
                    self._src = st
                    self._record_output(t)
        self._src = replace(st, clone_valid=True, clone_stamp_s=t)
        self._reset_clone()
        return outcome

    def _apply_range(self, m: _Measurement) -> str:
        r, H = model.range_residual(self._x, m.data[0], self.config.ground_z_ned_m)
        return self._kalman(r, H, np.array([[self.config.range_std_m**2]]), self._gate[1])

    def _kalman(self, r: FloatArray, H: FloatArray, R_noise: FloatArray, gate: float) -> str:
        P = self._P
        PHt = P @ H.T
        S = H @ PHt + R_noise
        try:
            S_inv = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return "invalid"
        d2 = float(r @ S_inv @ r)
        if not math.isfinite(d2) or d2 < 0.0:
            return "invalid"
        if d2 > gate:
            return "gated"
        K = PHt @ S_inv
        # P - K S K^T (= the Joseph form for the optimal gain), symmetrized.
        P_new = P - K @ PHt.T
        self._P = 0.5 * (P_new + P_new.T)
        model.inject_in_place(self._x, K @ r)
        return "applied"

    def _reset_pose(self, R_m: FloatArray, p_m: FloatArray, cov_body: FloatArray) -> None:
        """Move the pose to a disagreeing measurement (a discontinuity).

        First updates (attitude, then position) with the pose prior inflated along
        the disagreement (`_disagreement_inflation`): the pose jumps to the
        measurement along the axes it measures precisely and keeps its prior
        along axes it barely measures (e.g. along the pipes). If the result still disagrees with the measurement
        beyond its own covariance (large rotations: the update is too nonlinear),
        the pose is set to the measurement and its covariance block replaced.
        """
        # Attitude first (so the position residual is then expressed in the right body frame), then position.
        r, H = model.absolute_pose_residual(self._x, R_m, p_m)
        P = self._P.copy()
        P[6:9, 6:9] += self._disagreement_inflation(r[3:], cov_body[3:, 3:])
        self._P = P
        status = self._kalman(r[3:], H[3:], cov_body[3:, 3:], math.inf)
        if status == "applied":
            r, H = model.absolute_pose_residual(self._x, R_m, p_m)
            R = model.rotation(self._x)
            P = self._P.copy()
            P[0:3, 0:3] += self._disagreement_inflation(R @ r[:3], R @ cov_body[:3, :3] @ R.T)
            self._P = P
            status = self._kalman(r[:3], H[:3], cov_body[:3, :3], math.inf)
        if status == "applied":
            r_after, _ = model.absolute_pose_residual(self._x, R_m, p_m)
            try:
                d2 = float(r_after @ np.linalg.solve(cov_body, r_after))
            except np.linalg.LinAlgError:
                d2 = math.inf
            if d2 <= self._gate[6]:
                self._reset_clone()
                return
        self._x[model.P_SL] = p_m
        self._x[model.R_SL] = R_m.ravel()
        P = self._P.copy()
        P[model.POSE_IDX, :] = 0.0
        P[:, model.POSE_IDX] = 0.0
        P[_POSE_IX] = model.body_to_error_pose_covariance(R_m, cov_body)
        self._P = P
        self._reset_clone()

    def _disagreement_inflation(self, e: FloatArray, C: FloatArray) -> FloatArray:
        """Rank-1 prior inflation e_s e_s^T for a reset (3x3).

        e_s is the disagreement `e` projected on the eigenvectors of the
        measurement covariance C that measure precisely compared with |e|
        (gate * eigenvalue < |e|^2): the pose may jump along e_s, not along axes
        the measurement barely constrains.
        """
        w, U = np.linalg.eigh(C)
        precise = self._gate[1] * np.maximum(w, 0.0) < float(e @ e)
        U_s = U[:, precise]
        e_s = U_s @ (U_s.T @ e)
        Q: FloatArray = np.outer(e_s, e_s)
        return Q

    def _reset_clone(self) -> None:
        self._x[model.PC_SL] = self._x[model.P_SL]
        self._x[model.RC_SL] = self._x[model.R_SL]
        self._reset_clone_covariance()

    def _reset_clone_covariance(self) -> None:
        P = self._P.copy()
        P[15:21, :] = P[model.POSE_IDX, :]
        P[:, 15:21] = P[:, model.POSE_IDX]
        self._P = P

    def _record_output(self, t: float) -> None:
        P = self._P
        self._output = _Output(t, self._x.copy(), P[_POSE_IX].copy(), P[3:6, 3:6].copy(), self._src.source)

    def _count(self, key: str) -> None:
        self._counts[key] = self._counts.get(key, 0) + 1

    # ------------------------------------------------------------------ outputs

    def estimate(self) -> NavEstimate:
        """The posterior at the latest applied visual correction (stamp = that frame's capture time).

        Before any visual correction: the current IMU-propagated state with ok False.
        `ok` is also False while the active source is "none" (every visual source
        failed since) or when the position standard deviation exceeds the bound.
        """
        out = self._output
        if out is None:
            est = self.estimate_latest()
            return replace(est, ok=False)
        est = self._make_estimate(out.stamp_s, out.x, out.P_pose, out.P_vel, out.source)
        if self._src.source == "none":
            # Every visual source has failed since: the last correction is not to be trusted as current.
            est = replace(est, ok=False)
        return est

    def estimate_latest(self) -> NavEstimate:
        """The current state, propagated to the latest IMU sample or measurement (whichever is later)."""
        if not self._initialized:
            z3 = np.zeros(3)
            return NavEstimate(
                stamp_s=math.nan, ok=False, T_ned_body=np.eye(4), position_ned_m=z3, velocity_ned_m_s=z3.copy(),
                pose_covariance=np.eye(6) * 1e6, velocity_covariance=np.eye(3) * 1e6,
                reset_counter=self._reset_counter, source="none", gyro_bias_rad_s=z3.copy(),
                accel_bias_m_s2=z3.copy(),
            )
        P = self._P
        return self._make_estimate(self._t, self._x.copy(), P[_POSE_IX].copy(), P[3:6, 3:6].copy(), self._src.source)

    def _make_estimate(
        self, t: float, x: FloatArray, P_pose: FloatArray, P_vel: FloatArray, source: str
    ) -> NavEstimate:
        R = model.rotation(x).copy()
        p = x[model.P_SL].copy()
        pos_std = math.sqrt(max(float(np.max(np.diag(P_pose)[:3])), 0.0))
        ok = source != "none" and pos_std <= self.config.max_position_std_m
        return NavEstimate(
            stamp_s=t,
            ok=ok,
            T_ned_body=se3.make(R, p),
            position_ned_m=p,
            velocity_ned_m_s=x[model.V_SL].copy(),
            pose_covariance=model.pose_covariance_xyz_rpy(R, P_pose),
            velocity_covariance=P_vel,
            reset_counter=self._reset_counter,
            source=source,
            gyro_bias_rad_s=x[model.BG_SL].copy(),
            accel_bias_m_s2=x[model.BA_SL].copy(),
        )

    def error_state_covariance(self) -> FloatArray:
        """A copy of the current (21, 21) error-state covariance (layout in `companion.estimation.model`)."""
        return self._P.copy()

    def nominal_state(self) -> FloatArray:
        """A copy of the current (33,) nominal state vector (layout in `companion.estimation.model`)."""
        return self._x.copy()

    @property
    def stamp_s(self) -> float:
        """Time (s) of the current state."""
        return self._t

    @property
    def reset_counter(self) -> int:
        """Number of pose discontinuities so far (the link wraps it to MAVLink's uint8)."""
        return self._reset_counter

    @property
    def source(self) -> str:
        """The active visual source: "rack", "ground" or "none"."""
        return self._src.source

    @property
    def stats(self) -> NavFilterStats:
        """Counters of IMU samples, measurement outcomes and rejections."""
        return NavFilterStats(
            imu_samples=self._imu_count, counts=dict(self._counts), reset_counter=self._reset_counter,
            source=self._src.source,
        )


def _matrix(a: Any, n: int, name: str) -> FloatArray:
    """`a` as a float64 (n, n) array; raises InputError on a wrong shape, lets NaN through (counted later)."""
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a numeric ({n}, {n}) array") from exc
    if arr.shape != (n, n):
        raise InputError(f"{name}: expected shape ({n}, {n}), got {arr.shape}")
    return arr


def _is_pd(C: FloatArray) -> bool:
    try:
        np.linalg.cholesky(0.5 * (C + C.T))
    except np.linalg.LinAlgError:
        return False
    return True
