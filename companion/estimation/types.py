"""Inputs, configuration and outputs of the navigation filter (frozen dataclasses and Protocols)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from companion.checks import FloatArray
from companion.errors import ConfigError, InputError


@dataclass(frozen=True)
class ImuSample:
    """One IMU reading (HIGHRES_IMU / SCALED_IMU converted by the link).

    stamp_s: sample time on the companion's monotonic time base (s), i.e. the
        autopilot's time_usec already shifted by the TIMESYNC offset.
    gyro_rad_s: (3,) angular rate, body FRD, rad/s.
    accel_m_s2: (3,) specific force, body FRD, m/s^2 (about (0, 0, -9.81) at rest, level).
    """

    stamp_s: float
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray

    def __post_init__(self) -> None:
        g = np.asarray(self.gyro_rad_s, dtype=np.float64).reshape(-1)
        a = np.asarray(self.accel_m_s2, dtype=np.float64).reshape(-1)
        if g.shape != (3,) or a.shape != (3,):
            raise InputError(f"ImuSample: gyro and accel must have 3 elements, got {g.shape} and {a.shape}")
        if not (math.isfinite(self.stamp_s) and np.isfinite(g).all() and np.isfinite(a).all()):
            raise InputError("ImuSample: stamp, gyro and accel must be finite")
        object.__setattr__(self, "stamp_s", float(self.stamp_s))
        object.__setattr__(self, "gyro_rad_s", g)
        object.__setattr__(self, "accel_m_s2", a)


@dataclass(frozen=True)
class ImuNoiseModel:
    """Continuous-time IMU noise (white noise densities and bias random walks).

    Defaults are for a consumer MEMS IMU (ICM-20689 / BMI088 class) on a
    multirotor: datasheet densities inflated about ten-fold for vibration, the
    same order as PX4 EKF2 / ArduPilot EKF3 defaults.
    """

    gyro_noise_density_rad_s_sqrt_hz: float = 2.0e-3
    accel_noise_density_m_s2_sqrt_hz: float = 2.0e-2
    gyro_bias_random_walk_rad_s2_sqrt_hz: float = 1.0e-4
    accel_bias_random_walk_m_s3_sqrt_hz: float = 1.0e-3
    gyro_bias_initial_std_rad_s: float = 0.01
    accel_bias_initial_std_m_s2: float = 0.1

    def __post_init__(self) -> None:
        for name in (
            "gyro_noise_density_rad_s_sqrt_hz",
            "accel_noise_density_m_s2_sqrt_hz",
            "gyro_bias_random_walk_rad_s2_sqrt_hz",
            "accel_bias_random_walk_m_s3_sqrt_hz",
            "gyro_bias_initial_std_rad_s",
            "accel_bias_initial_std_m_s2",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ConfigError(f"ImuNoiseModel.{name}: must be finite and >= 0, got {value}")


@dataclass(frozen=True)
class NavFilterConfig:
    """Configuration of `NavigationFilter` (SI units)."""

    imu: ImuNoiseModel = field(default_factory=ImuNoiseModel)
    gravity_m_s2: float = 9.80665
    # Initial uncertainty when the filter initializes itself from the first IMU sample.
    initial_position_std_m: float = 0.05
    initial_velocity_std_m_s: float = 0.1
    initial_tilt_std_rad: float = 0.03
    initial_yaw_std_rad: float = 0.1
    initial_yaw_rad: float = 0.0
    # Mahalanobis gate: a measurement is rejected when r^T S^-1 r > chi2.ppf(gate_probability, dof).
    gate_probability: float = 0.999
    # Source selection hysteresis.
    rack_frames_to_switch_in: int = 5
    rack_failures_to_switch_out: int = 5
    ground_failures_to_switch_out: int = 10
    source_timeout_s: float = 0.5
    # A switch to the rack whose correction passes the gate but still moves the position by more than
    # switch_reset_position_m (m) or the attitude by more than switch_reset_angle_rad (rad) is reported
    # as a reset (reset_counter incremented): the autopilot sees a step either way. Defaults: 3 sigma of
    # the daemon's rack pose floor (1 cm, 0.5 deg), i.e. beyond what one rack frame's noise explains.
    switch_reset_position_m: float = 0.03
    switch_reset_angle_rad: float = 0.026
    # A rack pose whose roll/pitch fails the gate against the filter's is not healthy ("unsettled")
    # while the rack is not the source; after this many such frames in a row it is taken anyway (the
    # filter's own tilt may be the wrong one).
    rack_unsettled_frames_max: int = 30
    # Time alignment.
    buffer_s: float = 1.0
    max_extrapolation_s: float = 0.2
    max_imu_dt_s: float = 0.1
    # Output.
    max_position_std_m: float = 0.5
    # Rangefinder.
    use_range: bool = True
    range_std_m: float = 0.05
    range_min_m: float = 0.1
    range_max_m: float = 30.0
    ground_z_ned_m: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 < self.gate_probability < 1.0:
            raise ConfigError(f"NavFilterConfig.gate_probability: must be in (0, 1), got {self.gate_probability}")
        for name in ("rack_frames_to_switch_in", "rack_failures_to_switch_out", "ground_failures_to_switch_out",
                     "rack_unsettled_frames_max"):
            if getattr(self, name) < 1:
                raise ConfigError(f"NavFilterConfig.{name}: must be >= 1")
        for name in (
            "gravity_m_s2",
            "initial_position_std_m",
            "initial_velocity_std_m_s",
            "initial_tilt_std_rad",
            "initial_yaw_std_rad",
            "source_timeout_s",
            "buffer_s",
            "max_imu_dt_s",
            "max_position_std_m",
            "range_std_m",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"NavFilterConfig.{name}: must be finite and > 0, got {value}")
        for name in ("switch_reset_position_m", "switch_reset_angle_rad", "max_extrapolation_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ConfigError(f"NavFilterConfig.{name}: must be finite and >= 0, got {value}")
        if not 0.0 <= self.range_min_m < self.range_max_m:
            raise ConfigError("NavFilterConfig.range_min_m/range_max_m: need 0 <= min < max")


@dataclass(frozen=True)
class NavEstimate:
    """The fused estimate handed to the pose sender.

    stamp_s: time (s, companion time base) the estimate refers to.
    ok: False before initialization, without an active visual source, or when
        the largest position standard deviation exceeds `max_position_std_m`.
    T_ned_body: (4, 4) pose of the body FRD frame in NED.
    position_ned_m, velocity_ned_m_s: (3,) NED.
    pose_covariance: (6, 6) order (x, y, z, roll, pitch, yaw), m and rad (ZYX Euler).
    velocity_covariance: (3, 3) NED, (m/s)^2.
    reset_counter: number of estimate discontinuities (source-switch resets) so far.
    source: "rack", "ground" or "none" (the active visual source).
    gyro_bias_rad_s, accel_bias_m_s2: (3,) body FRD bias estimates.
    """

    stamp_s: float
    ok: bool
    T_ned_body: FloatArray
    position_ned_m: FloatArray
    velocity_ned_m_s: FloatArray
    pose_covariance: FloatArray
    velocity_covariance: FloatArray
    reset_counter: int
    source: str
    gyro_bias_rad_s: FloatArray
    accel_bias_m_s2: FloatArray


@dataclass(frozen=True)
class NavFilterStats:
    """Counters since construction. `counts` keys: `<outcome>_<kind>` or a rejection reason.

    Outcomes per kind (rack, ground, range): applied, gated (Mahalanobis outlier),
    failed (estimate not ok), standby (healthy but not the active source),
    reset (applied as a re-localization). Rejection reasons (never applied):
    too_old, too_new, out_of_order, not_initialized, invalid, out_of_range,
    imu_out_of_order, imu_before_init, imu_gap.
    """

    imu_samples: int
    counts: Mapping[str, int]
    reset_counter: int
    source: str

    def count(self, key: str) -> int:
        """The counter `key` (0 when it never happened)."""
        return int(self.counts.get(key, 0))


class RackEstimateLike(Protocol):
    """What the filter reads from `companion.vision.rack.RackEstimate`.

    T_rack_cam: (4, 4) camera pose in the rack frame; covariance: (6, 6) of a right
    perturbation in the camera frame, twist order (v, w): T_true = T_rack_cam exp(d).
    """

    @property
    def ok(self) -> bool: ...

    @property
    def T_rack_cam(self) -> ArrayLike: ...

    @property
    def covariance(self) -> ArrayLike: ...


class GroundEstimateLike(Protocol):
    """What the filter reads from `companion.vision.ground.GroundEstimate`.

    dx_m, dy_m: NED position increment since the odometer's previous frame (m);
    dyaw_rad: heading increment (rad); covariance: (3, 3) of (dx, dy, dyaw).
    """

    @property
    def ok(self) -> bool: ...

    @property
    def dx_m(self) -> float: ...

    @property
    def dy_m(self) -> float: ...

    @property
    def dyaw_rad(self) -> float: ...

    @property
    def covariance(self) -> ArrayLike: ...
