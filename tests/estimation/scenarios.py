"""Closed-loop scenarios for the navigation filter tests: simulated truth, IMU and delayed camera measurements."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.estimation import ImuNoiseModel, NavFilterConfig, NavigationFilter, model
from companion.estimation import simulate as sim
from companion.geometry import se3, so3

RACK_COV = np.diag([0.01**2] * 3 + [0.005**2] * 3)
GROUND_COV = np.diag([0.005**2, 0.005**2, 0.003**2])
RANGE_STD_M = 0.03


@dataclass
class ScenarioResult:
    stamp_s: np.ndarray  # (K,) checkpoint times
    error: np.ndarray  # (K, 15) x_true [-] x_est (dp, dv, dtheta, dbg, dba)
    nees: np.ndarray  # (K,)
    sigma: np.ndarray  # (K, 15) filter standard deviations
    filter: NavigationFilter
    truth_bias: tuple[np.ndarray, np.ndarray] = field(default=(np.zeros(3), np.zeros(3)))


def initial_covariance(config: NavFilterConfig) -> np.ndarray:
    imu = config.imu
    std = np.concatenate(
        [
            np.full(3, config.initial_position_std_m),
            np.full(3, config.initial_velocity_std_m_s),
            [config.initial_tilt_std_rad, config.initial_tilt_std_rad, config.initial_yaw_std_rad],
            np.full(3, imu.gyro_bias_initial_std_rad_s),
            np.full(3, imu.accel_bias_initial_std_m_s2),
        ]
    )
    return np.diag(std**2)


def run_scenario(
    seed: int,
    *,
    mode: str = "ground",
    duration_s: float = 4.0,
    imu_rate_hz: float = 100.0,
    camera_rate_hz: float = 20.0,
    range_rate_hz: float = 0.0,
    delay_s: float = 0.03,
    static: bool = False,
    dropout_s: tuple[float, float] | None = None,
    config: NavFilterConfig | None = None,
    gyro_bias0: np.ndarray | None = None,
    accel_bias0: np.ndarray | None = None,
    checkpoint_every: int = 1,
    imu_noise: ImuNoiseModel | None = None,
) -> ScenarioResult:
    """Fly one seeded scenario and return the errors at every `checkpoint_every`-th IMU sample.

    mode: "ground" (planar increments), "rack" (absolute poses) or "none".
    Camera frames are captured off the IMU grid and delivered `delay_s` late,
    so every update goes through the rollback path. During `dropout_s`
    (start, end) no camera measurement is delivered. `imu_noise` overrides the
    noise of the simulated IMU (default: the filter's own model).
    """
    rng = np.random.default_rng(seed)
    cfg = config if config is not None else NavFilterConfig(
        rack_frames_to_switch_in=1, max_position_std_m=10.0, range_std_m=RANGE_STD_M
    )
    traj = sim.SineTrajectory.static() if static else sim.SineTrajectory.random(rng)
    t_imu = np.arange(0.0, duration_s, 1.0 / imu_rate_hz)
    truth = traj.at(t_imu, cfg.gravity_m_s2)
    P0 = initial_covariance(cfg)
    std0 = np.sqrt(np.diag(P0))
    bg0 = rng.normal(size=3) * std0[9:12] if gyro_bias0 is None else gyro_bias0
    ba0 = rng.normal(size=3) * std0[12:15] if accel_bias0 is None else accel_bias0
    imu = sim.simulate_imu(rng, truth, cfg.imu if imu_noise is None else imu_noise, bg0, ba0)

    # Initial estimate: truth shifted by an error drawn from P0 (biases start at zero).
    e0 = rng.normal(size=9) * std0[:9]
    T0 = sim.perturb_state(truth.T_ned_body[0], np.concatenate([e0[:3], e0[6:9]]))
    f = NavigationFilter(cfg)
    f.initialize(0.0, T0, truth.velocity_ned_m_s[0] - e0[3:6], covariance=P0)

    events: list[tuple[float, int, str, object]] = []
    for s in imu.samples():
        events.append((s.stamp_s, 1, "imu", s))
    if mode != "none":
        t_cam = np.arange(rng.uniform(0.001, 0.009), duration_s - delay_s, 1.0 / camera_rate_hz)
        cam_truth = traj.at(t_cam, cfg.gravity_m_s2)
        if mode == "rack":
            poses = sim.noisy_absolute_poses(rng, cam_truth, RACK_COV)
            for t, T in zip(t_cam, poses, strict=True):
                events.append((t + delay_s, 0, "rack", (t, T)))
        else:
            inc = sim.noisy_relative_increments(rng, cam_truth, GROUND_COV)
            for k, (t, d) in enumerate(zip(t_cam, inc, strict=True)):
                events.append((t + delay_s, 0, "ground", (t, d, k == 0)))
    if range_rate_hz > 0.0:
        t_rng = np.arange(0.0037, duration_s - delay_s, 1.0 / range_rate_hz)
        ranges = sim.noisy_ranges(rng, traj.at(t_rng, cfg.gravity_m_s2), RANGE_STD_M)
        for t, r in zip(t_rng, ranges, strict=True):
            events.append((t + 0.5 * delay_s, 0, "range", (t, r)))
    events.sort(key=lambda e: (e[0], e[1]))

    errors, nees, sigma, stamps = [], [], [], []
    k = -1
    for _, _, kind, payload in events:
        if kind == "imu":
            f.add_imu(payload)  # type: ignore[arg-type]
            k += 1
            if k % checkpoint_every != checkpoint_every - 1:
                continue
            stamps.append(t_imu[k])
            x = f.nominal_state()
            P = f.error_state_covariance()[:15, :15]
            err = np.concatenate(
                [
                    truth.position_ned_m[k] - x[model.P_SL],
                    truth.velocity_ned_m_s[k] - x[model.V_SL],
                    so3.log(model.rotation(x).T @ truth.R_ned_body[k]),
                    imu.gyro_bias_rad_s[k] - x[model.BG_SL],
                    imu.accel_bias_m_s2[k] - x[model.BA_SL],
                ]
            )
            errors.append(err)
            nees.append(float(err @ np.linalg.solve(P, err)))
            sigma.append(np.sqrt(np.diag(P)))
            continue
        stamp = payload[0]  # type: ignore[index]
        if dropout_s is not None and dropout_s[0] <= stamp < dropout_s[1]:
            continue
        if kind == "rack":
            f.add_absolute_pose(stamp, payload[1], RACK_COV)  # type: ignore[index]
        elif kind == "ground":
            d = payload[1]  # type: ignore[index]
            f.add_relative_pose(stamp, d[0], d[1], d[2], GROUND_COV, restart=bool(payload[2]))  # type: ignore[index]
        else:
            f.add_range(payload[1], stamp)  # type: ignore[index]
    return ScenarioResult(np.array(stamps), np.array(errors), np.array(nees), np.array(sigma), f,
                          (imu.gyro_bias_rad_s[-1], imu.accel_bias_m_s2[-1]))


def pose_of(x: np.ndarray) -> np.ndarray:
    return se3.make(model.rotation(x), x[model.P_SL])
