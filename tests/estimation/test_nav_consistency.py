"""Statistical consistency (NEES over 100 seeded runs) and closed-loop accuracy of the navigation filter."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.stats import chi2

from companion.estimation import ImuNoiseModel, NavFilterConfig, model
from tests.estimation.scenarios import RANGE_STD_M, run_scenario

RUNS = 100
DOF = 15


@pytest.mark.parametrize(("mode", "range_rate_hz"), [("ground", 10.0), ("rack", 0.0)])
def test_average_nees_within_chi2_bounds(mode: str, range_rate_hz: float) -> None:
    """Bar-Shalom's average-NEES test on the 15 navigation error states.

    At each checkpoint the NEES averaged over 100 runs, times 100, is chi2 with
    100 * 15 dof for a consistent filter: its two-sided 95 % interval divided by
    100 is about [13.9, 16.1]. Every update goes through the rollback path
    (camera frames arrive 30 ms late, off the IMU grid).
    """
    results = [
        run_scenario(seed, mode=mode, range_rate_hz=range_rate_hz, duration_s=3.0, checkpoint_every=25)
        for seed in range(RUNS)
    ]
    nees = np.array([r.nees for r in results])  # (runs, checkpoints)
    avg = nees.mean(axis=0)
    lo, hi = chi2.ppf([0.025, 0.975], RUNS * DOF) / RUNS
    inside = (avg >= lo) & (avg <= hi)
    # ~95 % of checkpoints inside for a consistent filter; checkpoints are correlated in time.
    assert inside.mean() >= 0.75, (lo, hi, np.round(avg, 2))
    lo_all, hi_all = chi2.ppf([0.0005, 0.9995], RUNS * DOF) / RUNS
    assert np.all((avg > lo_all) & (avg < hi_all)), np.round(avg, 2)
    assert lo <= avg.mean() <= hi
    # Every run used its measurements (none gated, none rejected as too old or new).
    counts = results[0].filter.stats.counts
    assert counts.get(f"applied_{mode}", 0) >= 50
    assert not any(key.startswith(("gated", "too_", "out_of")) for key in counts)


def test_overconfident_filter_fails_the_nees_test() -> None:
    """The test has teeth: with the IMU noise understated 3x the average NEES leaves the interval."""
    true_noise = ImuNoiseModel()
    cfg = NavFilterConfig(
        imu=ImuNoiseModel(
            gyro_noise_density_rad_s_sqrt_hz=true_noise.gyro_noise_density_rad_s_sqrt_hz / 3,
            accel_noise_density_m_s2_sqrt_hz=true_noise.accel_noise_density_m_s2_sqrt_hz / 3,
        ),
        rack_frames_to_switch_in=1, max_position_std_m=10.0, range_std_m=RANGE_STD_M,
    )
    results = []
    for seed in range(30):
        # The truth uses the default (larger) noise; only the filter's model is wrong.
        r = run_scenario(seed, mode="ground", range_rate_hz=10.0, duration_s=3.0, checkpoint_every=100,
                         config=cfg, imu_noise=true_noise)
        results.append(r.nees)
    avg = np.mean(results, axis=0)
    assert avg[-1] > chi2.ppf(0.975, 30 * DOF) / 30


def test_filter_with_a_wrong_jacobian_fails_the_nees_test(monkeypatch: pytest.MonkeyPatch) -> None:
    """The test also catches a wrong model, not only wrong noise: F without the gyro-bias block."""
    propagate = model.propagate_in_place

    def broken(x: np.ndarray, gyro: Any, accel: Any, dt_s: float, gravity_m_s2: float, F_out: np.ndarray) -> None:
        propagate(x, gyro, accel, dt_s, gravity_m_s2, F_out)
        F_out[6:9, 9:12] = 0.0  # attitude error no longer driven by the gyro-bias error

    monkeypatch.setattr(model, "propagate_in_place", broken)
    runs = [run_scenario(seed, mode="ground", range_rate_hz=10.0, duration_s=3.0, checkpoint_every=100).nees
            for seed in range(30)]
    avg = np.mean(runs, axis=0)
    assert avg[-1] > chi2.ppf(0.975, 30 * DOF) / 30


def test_static_vehicle_stays_put_and_biases_converge() -> None:
    """At rest with rack poses (and the rangefinder): position holds, gyro and accel biases are learnt."""
    bg = np.array([0.01, -0.008, 0.012])
    ba = np.array([0.12, -0.08, 0.1])
    r = run_scenario(7, mode="rack", range_rate_hz=10.0, static=True, duration_s=20.0, checkpoint_every=100,
                     gyro_bias0=bg, accel_bias0=ba)
    err, sigma = r.error, r.sigma
    # Position error over the last 10 s (rack poses have 1 cm noise per frame).
    assert np.abs(err[-10:, 0:3]).max() < 0.02
    assert np.abs(err[-1, 3:6]).max() < 0.05
    # Biases: within 3.5 sigma, and sigma far below the initial one (observable and learnt).
    assert np.all(np.abs(err[-1, 9:15]) < 3.5 * sigma[-1, 9:15])
    assert np.abs(err[-1, 9:12]).max() < 2e-3  # true gyro bias ~1e-2 rad/s
    assert np.abs(err[-1, 12:15]).max() < 0.03  # true accel bias ~0.1 m/s^2
    imu = NavFilterConfig().imu
    assert np.all(sigma[-1, 9:12] < 0.1 * imu.gyro_bias_initial_std_rad_s)
    assert np.all(sigma[-1, 12:15] < 0.1 * imu.accel_bias_initial_std_m_s2)
    est = r.filter.estimate()
    assert est.ok and est.source == "rack"
    np.testing.assert_allclose(est.gyro_bias_rad_s, r.truth_bias[0], atol=2e-3)


def test_static_vehicle_with_ground_increments_holds_position_and_learns_gyro_bias() -> None:
    bg = np.array([0.01, -0.008, 0.012])
    r = run_scenario(8, mode="ground", range_rate_hz=10.0, static=True, duration_s=20.0, checkpoint_every=100,
                     gyro_bias0=bg, accel_bias0=np.array([0.05, -0.05, 0.08]))
    err, sigma = r.error, r.sigma
    # Relative increments cannot remove the initial position error; the drift
    # from it is the odometer's random walk (5 mm per frame at 20 Hz: ~0.1 m in 20 s).
    drift = np.linalg.norm(err[:, 0:2] - err[0, 0:2], axis=1)
    assert drift.max() < 0.3
    assert np.abs(err[:, 2]).max() < 0.05  # the rangefinder holds the height
    assert np.abs(err[-1, 3:6]).max() < 0.1
    # Gyro biases are observable from yaw increments (z) and through gravity (x, y).
    assert np.abs(err[-1, 9:11]).max() < 2e-3
    assert abs(err[-1, 11]) < 1e-2
    assert sigma[-1, 9:12].max() < 0.5 * NavFilterConfig().imu.gyro_bias_initial_std_rad_s
    assert np.all(np.abs(err) < 3.5 * sigma)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_vision_gap_of_one_second(seed: int) -> None:
    """After convergence, 1 s of IMU only keeps the error under 10 cm; 0.5 s of vision recovers it."""
    r = run_scenario(seed, mode="rack", duration_s=12.0, imu_rate_hz=200.0, camera_rate_hz=30.0,
                     dropout_s=(10.0, 11.0), checkpoint_every=10)
    t = r.stamp_s
    pos_err = np.linalg.norm(r.error[:, 0:3], axis=1)
    before = pos_err[(t > 9.0) & (t < 10.0)].max()
    gap_end = pos_err[np.argmin(np.abs(t - 11.0))]
    recovered = pos_err[(t >= 11.5)].max()
    assert before < 0.03
    assert gap_end < 0.10
    assert recovered < 0.03
    # The filter's uncertainty grew during the gap and is honest about it.
    sig = np.linalg.norm(r.sigma[:, 0:3], axis=1)
    assert sig[np.argmin(np.abs(t - 11.0))] > 2 * sig[np.argmin(np.abs(t - 9.9))]
