"""Seeded truth trajectories, IMU samples and noisy visual measurements for tests and benchmarks.

Truth is analytic (sums of sines per axis and per Euler angle), so every
quantity is evaluated in closed form and vectorized over any set of stamps:
position, velocity, attitude R_ned_body, body angular rate and specific force.
Noise follows `ImuNoiseModel` exactly as the filter assumes it (white noise
of density sigma sampled as sigma / sqrt(dt), biases as random walks).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray
from companion.estimation.types import ImuNoiseModel, ImuSample
from companion.geometry import frames, se3, so3


@dataclass(frozen=True)
class TruthSamples:
    """Truth at `stamp_s` (N,): NED position/velocity/acceleration (N, 3), R_ned_body (N, 3, 3),
    body FRD angular rate (N, 3) rad/s and specific force (N, 3) m/s^2."""

    stamp_s: FloatArray
    position_ned_m: FloatArray
    velocity_ned_m_s: FloatArray
    acceleration_ned_m_s2: FloatArray
    R_ned_body: FloatArray
    gyro_rad_s: FloatArray
    specific_force_m_s2: FloatArray

    @property
    def T_ned_body(self) -> FloatArray:
        """(N, 4, 4) body poses in NED."""
        return se3.make(self.R_ned_body, self.position_ned_m)

    @property
    def yaw_rad(self) -> FloatArray:
        """(N,) heading (ZYX yaw) in rad."""
        return frames.yaw_from_rotation(self.R_ned_body)


@dataclass(frozen=True)
class SineTrajectory:
    """p_i(t) = center_i + sum_k A_ik sin(2 pi f_ik t + phi_ik); the same for (roll, pitch, yaw).

    Arrays: `position_*` (3, K), `euler_*` (3, K) (rad); `center_ned_m` (3,),
    `euler_offset_rad` (3,).
    """

    center_ned_m: FloatArray
    position_amplitude_m: FloatArray
    position_frequency_hz: FloatArray
    position_phase_rad: FloatArray
    euler_offset_rad: FloatArray
    euler_amplitude_rad: FloatArray
    euler_frequency_hz: FloatArray
    euler_phase_rad: FloatArray

    @staticmethod
    def static(center_ned_m: tuple[float, float, float] = (0.0, 0.0, -2.0),
               euler_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> SineTrajectory:
        """A vehicle at rest at `center_ned_m` with attitude (roll, pitch, yaw) `euler_rad`."""
        z = np.zeros((3, 1))
        return SineTrajectory(np.asarray(center_ned_m, float), z, z, z, np.asarray(euler_rad, float), z, z, z)

    @staticmethod
    def random(
        rng: np.random.Generator,
        *,
        center_ned_m: tuple[float, float, float] = (0.0, 0.0, -2.0),
        position_amplitude_m: float = 0.5,
        attitude_amplitude_rad: float = 0.1,
        yaw_amplitude_rad: float = 0.5,
        max_frequency_hz: float = 0.3,
        terms: int = 2,
    ) -> SineTrajectory:
        """A smooth random flight: `terms` sines per axis with frequencies up to `max_frequency_hz`."""
        shape = (3, terms)
        att_amp = np.array([attitude_amplitude_rad, attitude_amplitude_rad, yaw_amplitude_rad])[:, None]
        return SineTrajectory(
            center_ned_m=np.asarray(center_ned_m, float),
            position_amplitude_m=rng.uniform(0.2, 1.0, shape) * position_amplitude_m / terms,
            position_frequency_hz=rng.uniform(0.05, max_frequency_hz, shape),
            position_phase_rad=rng.uniform(-np.pi, np.pi, shape),
            euler_offset_rad=np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]),
            euler_amplitude_rad=rng.uniform(0.2, 1.0, shape) * att_amp / terms,
            euler_frequency_hz=rng.uniform(0.05, max_frequency_hz, shape),
            euler_phase_rad=rng.uniform(-np.pi, np.pi, shape),
        )

    def at(self, stamp_s: FloatArray, gravity_m_s2: float = 9.80665) -> TruthSamples:
        """Truth at the stamps (N,) (s)."""
        t = np.asarray(stamp_s, dtype=np.float64).reshape(-1)
        p, v, a = _sines(t, self.position_amplitude_m, self.position_frequency_hz, self.position_phase_rad)
        p = p + self.center_ned_m
        e, de, _ = _sines(t, self.euler_amplitude_rad, self.euler_frequency_hz, self.euler_phase_rad)
        e = e + self.euler_offset_rad
        roll, pitch, yaw = e[:, 0], e[:, 1], e[:, 2]
        R = frames.rotation_from_euler_zyx(roll, pitch, yaw)
        sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
        gyro = np.stack(
            [
                de[:, 0] - sp * de[:, 2],
                cr * de[:, 1] + sr * cp * de[:, 2],
                -sr * de[:, 1] + cr * cp * de[:, 2],
            ],
            axis=-1,
        )
        f_ned = a - np.array([0.0, 0.0, gravity_m_s2])
        f_body = np.einsum("nji,nj->ni", R, f_ned)
        return TruthSamples(t, p, v, a, R, gyro, f_body)


def _sines(t: FloatArray, amp: FloatArray, freq: FloatArray, phase: FloatArray) -> tuple[FloatArray, ...]:
    w = 2.0 * np.pi * freq  # (3, K)
    arg = t[:, None, None] * w[None] + phase[None]  # (N, 3, K)
    s, c = np.sin(arg), np.cos(arg)
    value = np.sum(amp * s, axis=-1)
    rate = np.sum(amp * w * c, axis=-1)
    accel = -np.sum(amp * w * w * s, axis=-1)
    return value, rate, accel


@dataclass(frozen=True)
class ImuSeries:
    """Simulated IMU readings (N, 3) at `stamp_s` (N,) and the true biases (N, 3) behind them."""

    stamp_s: FloatArray
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray
    gyro_bias_rad_s: FloatArray
    accel_bias_m_s2: FloatArray

    def samples(self) -> list[ImuSample]:
        """The readings as `ImuSample`s."""
        return [ImuSample(float(t), g, a) for t, g, a in zip(self.stamp_s, self.gyro_rad_s, self.accel_m_s2,
                                                              strict=True)]


def simulate_imu(
    rng: np.random.Generator,
    truth: TruthSamples,
    noise: ImuNoiseModel,
    gyro_bias0_rad_s: FloatArray | None = None,
    accel_bias0_m_s2: FloatArray | None = None,
) -> ImuSeries:
    """IMU readings = truth + bias (random walk from the initial bias) + white noise."""
    t = truth.stamp_s
    n = t.shape[0]
    dt = np.diff(t, prepend=t[0] - (t[1] - t[0] if n > 1 else 0.01))
    bg0 = np.zeros(3) if gyro_bias0_rad_s is None else np.asarray(gyro_bias0_rad_s, float)
    ba0 = np.zeros(3) if accel_bias0_m_s2 is None else np.asarray(accel_bias0_m_s2, float)
    sq = np.sqrt(dt)[:, None]
    walk_g = rng.standard_normal((n, 3)) * sq * noise.gyro_bias_random_walk_rad_s2_sqrt_hz
    walk_a = rng.standard_normal((n, 3)) * sq * noise.accel_bias_random_walk_m_s3_sqrt_hz
    walk_g[0] = 0.0
    walk_a[0] = 0.0
    bg = bg0 + np.cumsum(walk_g, axis=0)
    ba = ba0 + np.cumsum(walk_a, axis=0)
    gyro = truth.gyro_rad_s + bg + rng.standard_normal((n, 3)) * noise.gyro_noise_density_rad_s_sqrt_hz / sq
    accel = truth.specific_force_m_s2 + ba + rng.standard_normal((n, 3)) * noise.accel_noise_density_m_s2_sqrt_hz / sq
    return ImuSeries(t, gyro, accel, bg, ba)


def noisy_absolute_poses(rng: np.random.Generator, truth: TruthSamples, covariance_6x6: FloatArray) -> FloatArray:
    """Measured T_ned_body (N, 4, 4) with T_true = T_meas exp(d), d ~ N(0, covariance) (body frame, (v, w))."""
    n = truth.stamp_s.shape[0]
    d = rng.multivariate_normal(np.zeros(6), covariance_6x6, size=n)
    result: FloatArray = truth.T_ned_body @ se3.exp(-d)
    return result


def noisy_relative_increments(
    rng: np.random.Generator, truth: TruthSamples, covariance_3x3: FloatArray
) -> FloatArray:
    """(N, 3) increments (dx_m, dy_m, dyaw_rad) in NED between consecutive stamps, plus noise.

    Row 0 is the odometer's first frame: a zero increment without noise.
    """
    p = truth.position_ned_m
    yaw = truth.yaw_rad
    inc = np.zeros((p.shape[0], 3))
    inc[1:, :2] = p[1:, :2] - p[:-1, :2]
    inc[1:, 2] = frames.wrap_angle(yaw[1:] - yaw[:-1])
    inc[1:] += rng.multivariate_normal(np.zeros(3), covariance_3x3, size=p.shape[0] - 1)
    return inc


def noisy_ranges(
    rng: np.random.Generator, truth: TruthSamples, std_m: float, ground_z_ned_m: float = 0.0
) -> FloatArray:
    """(N,) downward rangefinder readings (slant range along body +z) over flat ground, plus noise."""
    c = truth.R_ned_body[:, 2, 2]
    result: FloatArray = (ground_z_ned_m - truth.position_ned_m[:, 2]) / c + std_m * rng.standard_normal(c.shape)
    return result


def perturb_state(x_true_pose: FloatArray, error_pose: FloatArray) -> FloatArray:
    """T (4, 4) with T_true = T exp-perturbed: position - dp (NED), R_true = R exp(dtheta).

    `error_pose` (6,) = (dp_ned, dtheta) is the estimation error x_true [-] x_est.
    """
    R_true = x_true_pose[:3, :3]
    R = R_true @ so3.exp(-error_pose[3:])
    return se3.make(R, x_true_pose[:3, 3] - error_pose[:3])
