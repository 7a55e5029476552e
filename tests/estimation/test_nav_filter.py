"""Behaviour of NavigationFilter: time alignment, rejections, gating, source selection, outputs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from companion.errors import InputError
from companion.estimation import (
    GroundEstimateLike,
    ImuNoiseModel,
    ImuSample,
    NavFilterConfig,
    NavigationFilter,
    RackEstimateLike,
    model,
)
from companion.estimation import simulate as sim
from companion.geometry import frames, se3, so3

RACK_COV = np.diag([0.01**2] * 3 + [0.005**2] * 3)
GROUND_COV = np.diag([0.005**2, 0.005**2, 0.003**2])
IMU_DT = 0.01


@dataclass(frozen=True)
class FakeRack:
    ok: bool
    T_rack_cam: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class FakeGround:
    ok: bool
    dx_m: float
    dy_m: float
    dyaw_rad: float
    covariance: np.ndarray


def _accepts_protocols(r: RackEstimateLike, g: GroundEstimateLike) -> None:
    """Type-level check (mypy): the fakes satisfy the filter's Protocols."""


_accepts_protocols(FakeRack(True, np.eye(4), np.eye(6)), FakeGround(True, 0.0, 0.0, 0.0, np.eye(3)))

T0 = se3.make(frames.rotation_from_euler_zyx(0.05, -0.03, 0.7), np.array([1.0, 2.0, -3.0]))


def static_imu(t_s: float, R_ned_body: np.ndarray = T0[:3, :3]) -> ImuSample:
    """Noise-free IMU reading of a vehicle at rest."""
    return ImuSample(t_s, np.zeros(3), R_ned_body.T @ np.array([0.0, 0.0, -9.80665]))


def static_filter(config: NavFilterConfig | None = None, pose_std: float = 0.01) -> NavigationFilter:
    f = NavigationFilter(config)
    P = np.diag([pose_std**2] * 3 + [0.01**2] * 3 + [0.002**2] * 3 + [1e-4**2] * 3 + [1e-3**2] * 3)
    f.initialize(0.0, T0, covariance=P)
    return f


def run_static(f: NavigationFilter, t0: float, t1: float) -> float:
    """Feed static IMU samples on (t0, t1]; returns the last stamp."""
    n0 = round(t0 / IMU_DT)
    n1 = round(t1 / IMU_DT)
    for k in range(n0 + 1, n1 + 1):
        f.add_imu(static_imu(k * IMU_DT))
    return n1 * IMU_DT


# --------------------------------------------------------------------------- time alignment


def moving_scenario(seed: int) -> tuple[list[ImuSample], list[tuple[float, np.ndarray]], sim.TruthSamples]:
    rng = np.random.default_rng(seed)
    traj = sim.SineTrajectory.random(rng)
    t = np.arange(0.0, 2.0, IMU_DT)
    truth = traj.at(t)
    imu = sim.simulate_imu(rng, truth, ImuNoiseModel()).samples()
    t_cam = np.arange(0.1133, 1.9, 0.05)  # after the first IMU samples, even when they lag
    poses = sim.noisy_absolute_poses(rng, traj.at(t_cam), RACK_COV)
    return imu, list(zip(t_cam.tolist(), poses, strict=True)), truth


def fresh_moving_filter(truth: sim.TruthSamples) -> NavigationFilter:
    f = NavigationFilter(NavFilterConfig(rack_frames_to_switch_in=1))
    f.initialize(0.0, truth.T_ned_body[0], truth.velocity_ned_m_s[0])
    return f


@pytest.mark.parametrize("delay_s", [0.0, 0.05, 0.3])
def test_late_measurements_give_the_same_result_as_timely_ones(delay_s: float) -> None:
    """Rollback + replay: feeding a frame `delay_s` after its capture equals feeding it on time."""
    imu, cams, truth = moving_scenario(3)

    def run(delay: float) -> NavigationFilter:
        f = fresh_moving_filter(truth)
        events = [(s.stamp_s, 1, s) for s in imu] + [(t + delay, 0, (t, T)) for t, T in cams]
        for _, _, e in sorted(events, key=lambda e: (e[0], e[1])):
            if isinstance(e, ImuSample):
                f.add_imu(e)
            else:
                f.add_absolute_pose(e[0], e[1], RACK_COV)
        return f

    ref = run(0.0)  # each frame arrives before the IMU sample after it: applied by extrapolation, then replayed
    late = run(delay_s)
    assert late.stats.count("applied_rack") == len(cams)
    np.testing.assert_allclose(late.nominal_state(), ref.nominal_state(), atol=1e-9)
    np.testing.assert_allclose(late.error_state_covariance(), ref.error_state_covariance(), atol=1e-12)
    assert late.estimate().stamp_s == ref.estimate().stamp_s == cams[-1][0]


@pytest.mark.parametrize("delay_s", [0.03, 0.3])
def test_rollback_matches_in_order_processing_without_any_replay(delay_s: float) -> None:
    """Oracle without rollback: frames stamped on IMU sample times and fed right after that sample
    are applied directly (stamp == filter time, nothing to replay); the same frames `delay_s` late
    go through rollback + replay and must give the same state, covariance and outputs."""
    rng = np.random.default_rng(21)
    traj = sim.SineTrajectory.random(rng)
    truth = traj.at(np.arange(0.0, 2.0, IMU_DT))
    imu = sim.simulate_imu(rng, truth, ImuNoiseModel()).samples()
    cam_idx = np.arange(12, len(imu) - 40, 5)
    t_cam = np.array([imu[k].stamp_s for k in cam_idx])
    poses = sim.noisy_absolute_poses(rng, traj.at(t_cam), RACK_COV)
    ranges = 2.0 + 0.01 * rng.standard_normal(len(t_cam))

    def run(delay: float) -> NavigationFilter:
        f = fresh_moving_filter(truth)
        events = [(s.stamp_s, 0, s) for s in imu] + [(t + delay, 1, (t, T, h)) for t, T, h in
                                                    zip(t_cam, poses, ranges, strict=True)]
        for _, _, e in sorted(events, key=lambda e: (e[0], e[1])):
            if isinstance(e, ImuSample):
                f.add_imu(e)
            else:
                f.add_absolute_pose(e[0], e[1], RACK_COV)
                f.add_range(float(e[2]), e[0])
        return f

    oracle, late = run(0.0), run(delay_s)
    assert oracle.stats.count("applied_rack") == late.stats.count("applied_rack") == len(t_cam)
    np.testing.assert_allclose(late.nominal_state(), oracle.nominal_state(), atol=1e-9)
    np.testing.assert_allclose(late.error_state_covariance(), oracle.error_state_covariance(), atol=1e-12)
    a, b = late.estimate(), oracle.estimate()
    assert a.stamp_s == b.stamp_s == t_cam[-1]
    np.testing.assert_allclose(a.T_ned_body, b.T_ned_body, atol=1e-9)


def test_frame_newer_than_the_imu_is_extrapolated_then_replayed() -> None:
    """IMU lagging 80 ms behind the camera: same final state as with the IMU on time."""
    imu, cams, truth = moving_scenario(4)

    def run(imu_delay: float) -> NavigationFilter:
        f = fresh_moving_filter(truth)
        events = [(s.stamp_s + imu_delay, 1, s) for s in imu] + [(t, 0, (t, T)) for t, T in cams]
        for _, _, e in sorted(events, key=lambda e: (e[0], e[1])):
            if isinstance(e, ImuSample):
                f.add_imu(e)
            else:
                f.add_absolute_pose(e[0], e[1], RACK_COV)
        return f

    ref, lagging = run(0.0), run(0.08)
    np.testing.assert_allclose(lagging.nominal_state(), ref.nominal_state(), atol=1e-9)
    assert lagging.stats.count("too_new") == 0


def test_rejections_are_counted_and_never_crash() -> None:
    f = NavigationFilter()
    f.add_absolute_pose(0.0, T0, RACK_COV)
    assert f.stats.count("not_initialized") == 1
    f = static_filter()
    t = run_static(f, 0.0, 2.0)
    x_before = f.nominal_state()
    # IMU sample not newer than the last one.
    f.add_imu(static_imu(t))
    f.add_imu(static_imu(t - 0.5))
    assert f.stats.count("imu_out_of_order") == 2
    # Older than the 1 s buffer, newer than the IMU plus max_extrapolation.
    f.add_absolute_pose(t - 1.5, T0, RACK_COV)
    assert f.stats.count("too_old") == 1
    f.add_absolute_pose(t + 0.5, T0, RACK_COV)
    assert f.stats.count("too_new") == 1
    # Out of order within one kind.
    f.add_relative_pose(t - 0.1, 0.0, 0.0, 0.0, GROUND_COV)
    f.add_relative_pose(t - 0.2, 0.0, 0.0, 0.0, GROUND_COV)
    assert f.stats.count("out_of_order") == 1
    # Invalid numbers: NaN, non positive-definite covariance, non-rotation.
    f.add_absolute_pose(t, T0, np.full((6, 6), np.nan))
    f.add_relative_pose(t, 0.0, 0.0, 0.0, -GROUND_COV)
    f.add_relative_pose(t, float("nan"), 0.0, 0.0, GROUND_COV)
    bad = T0.copy()
    bad[:3, :3] *= 2.0
    f.add_absolute_pose(t, bad, RACK_COV)
    f.add_range(float("inf"), t)
    assert f.stats.count("invalid") == 5
    f.add_range(100.0, t)
    assert f.stats.count("out_of_range") == 1
    # Wrong shapes are programming errors: they raise.
    with pytest.raises(InputError):
        f.add_absolute_pose(t, np.eye(3), RACK_COV)
    with pytest.raises(InputError):
        f.add_relative_pose(t, 0.0, 0.0, 0.0, np.eye(2))
    with pytest.raises(InputError):
        f.add_absolute_pose(t, T0, RACK_COV, source="ground")
    # The state only moved by the accepted (consistent) ground anchor.
    np.testing.assert_allclose(f.nominal_state()[:21], x_before[:21], atol=1e-9)


# --------------------------------------------------------------------------- gating


def test_gating_rejects_outliers_of_every_kind() -> None:
    cfg = NavFilterConfig(rack_frames_to_switch_in=1)
    f = static_filter(cfg)
    t = 0.0
    for _ in range(40):
        t = run_static(f, t, t + 0.05)
        f.add_absolute_pose(t, T0, RACK_COV)
    assert f.source == "rack" and f.stats.count("applied_rack") == 40
    x0 = f.nominal_state()
    t = run_static(f, t, t + 0.05)
    f.add_absolute_pose(t, T0 @ se3.exp(np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0])), RACK_COV)
    assert f.stats.count("gated_rack") == 1
    assert f.source == "rack"  # one outlier does not switch the source
    height = -T0[2, 3] / T0[2, 2]
    f.add_range(height - 0.6, t + 0.001)  # e.g. the top of a pipe under the drone
    assert f.stats.count("gated_range") == 1
    f.add_range(height, t + 0.002)
    assert f.stats.count("applied_range") == 1
    assert np.abs(f.nominal_state()[0:3] - x0[0:3]).max() < 2e-3

    g = static_filter()
    t = 0.0
    for k in range(20):
        t = run_static(g, t, t + 0.05)
        g.add_relative_pose(t, 0.0, 0.0, 0.0, GROUND_COV, restart=(k == 0))
    t = run_static(g, t, t + 0.05)
    g.add_relative_pose(t, 0.3, 0.0, 0.0, GROUND_COV)
    assert g.stats.count("gated_ground") == 1
    assert abs(g.nominal_state()[0] - T0[0, 3]) < 2e-3


# --------------------------------------------------------------------------- source selection


def test_source_switch_hysteresis_and_reset_counter() -> None:
    cfg = NavFilterConfig(rack_frames_to_switch_in=3, rack_failures_to_switch_out=4)
    f = static_filter(cfg)
    t = 0.0

    def frame(rack: FakeRack | None) -> None:
        nonlocal t
        t = run_static(f, t, t + 0.05)
        f.add_ground(FakeGround(True, 0.0, 0.0, 0.0, GROUND_COV), t)
        if rack is not None:
            f.add_rack(rack, t)

    T_rack_cam = frames.T_rack_cam_from_T_ned_body(T0, frames.default_T_ned_rack(), frames.default_T_body_cam())
    good = FakeRack(True, T_rack_cam, RACK_COV)
    failed = FakeRack(False, T_rack_cam, RACK_COV)
    for _ in range(5):
        frame(None)
    assert f.source == "ground" and f.estimate().source == "ground" and f.estimate().ok
    # N - 1 healthy rack frames: still on the ground odometer.
    frame(good)
    frame(good)
    assert f.source == "ground" and f.stats.count("standby_rack") == 2
    frame(good)
    assert f.source == "rack" and f.estimate().source == "rack"
    assert f.reset_counter == 0  # the rack agrees with the estimate: a smooth correction
    # M - 1 failures keep the rack; the M-th switches to the (healthy) ground odometer.
    for _ in range(3):
        frame(failed)
    assert f.source == "rack"
    frame(good)  # a success in between restarts the count
    for _ in range(3):
        frame(failed)
    assert f.source == "rack"
    frame(failed)
    assert f.source == "ground"
    assert f.stats.count("failed_rack") == 7

    # The rack re-localizes 0.4 m away: switching back is a reset, not a smooth correction.
    shift = se3.make(np.eye(3), np.array([0.4, -0.1, 0.0]))
    moved = FakeRack(True, frames.T_rack_cam_from_T_ned_body(
        shift @ T0, frames.default_T_ned_rack(), frames.default_T_body_cam()), RACK_COV)
    frame(moved)
    frame(moved)
    p_before = f.estimate().position_ned_m
    frame(moved)
    est = f.estimate()
    assert est.source == "rack" and f.reset_counter == 1 and est.reset_counter == 1
    assert f.stats.count("reset_rack") == 1
    step = np.linalg.norm(est.position_ned_m - p_before)
    disagreement = np.linalg.norm((shift @ T0)[:3, 3] - p_before)
    assert step <= disagreement + 1e-9
    np.testing.assert_allclose(est.position_ned_m, (shift @ T0)[:3, 3], atol=2e-3)
    # After the reset the rack is consistent again: further frames are ordinary updates.
    for _ in range(5):
        frame(moved)
    assert f.reset_counter == 1 and f.stats.count("gated_rack") == 0


def test_rack_silence_switches_to_ground_after_timeout() -> None:
    cfg = NavFilterConfig(rack_frames_to_switch_in=1, source_timeout_s=0.32)
    f = static_filter(cfg)
    T_rack_cam = frames.T_rack_cam_from_T_ned_body(T0, frames.default_T_ned_rack(), frames.default_T_body_cam())
    t = 0.0
    for _ in range(5):
        t = run_static(f, t, t + 0.05)
        f.add_rack(FakeRack(True, T_rack_cam, RACK_COV), t)
        f.add_ground(FakeGround(True, 0.0, 0.0, 0.0, GROUND_COV), t)
    assert f.source == "rack"
    t_last_rack = t
    while t < t_last_rack + 0.5:
        t = run_static(f, t, t + 0.05)
        f.add_ground(FakeGround(True, 0.0, 0.0, 0.0, GROUND_COV), t)
        assert f.source == ("rack" if t - t_last_rack <= 0.32 else "ground")
    assert f.source == "ground"
    assert f.estimate().stamp_s == pytest.approx(t)


def test_failed_ground_frame_makes_no_correction_and_reclones() -> None:
    """A failed frame: no update; the next increment is relative to the failed frame (the new clone)."""
    rng = np.random.default_rng(9)
    traj = sim.SineTrajectory.random(rng, position_amplitude_m=2.0)
    t = np.arange(0.0, 3.0, IMU_DT)
    truth = traj.at(t)
    imu = sim.simulate_imu(rng, truth, ImuNoiseModel(0.0, 0.0, 0.0, 0.0)).samples()
    t_cam = np.arange(0.005, 2.9, 0.05)
    inc = sim.noisy_relative_increments(rng, traj.at(t_cam), GROUND_COV * 1e-4)
    f = NavigationFilter()
    f.initialize(0.0, truth.T_ned_body[0], truth.velocity_ned_m_s[0])
    j = 0
    for s in imu:
        f.add_imu(s)
        while j < len(t_cam) and t_cam[j] <= s.stamp_s:
            failed = j % 10 == 5
            cov = GROUND_COV * 1e-4
            # When frame j fails, the odometer's increment j + 1 is measured from frame j.
            dx, dy, dyaw = inc[j]
            f.add_relative_pose(t_cam[j], dx, dy, dyaw, cov, ok=not failed, restart=(j == 0))
            j += 1
    assert f.stats.count("failed_ground") == len(range(5, len(t_cam), 10))
    assert f.stats.count("gated_ground") == 0
    err = f.estimate_latest().position_ned_m - truth.position_ned_m[-1]
    assert np.abs(err[:2]).max() < 0.01  # (no rangefinder here: the height is not observed)


def test_ground_increments_after_a_long_failure_still_apply() -> None:
    f = static_filter()
    t = 0.0
    for k in range(10):
        t = run_static(f, t, t + 0.05)
        f.add_ground(FakeGround(k < 3, 0.0, 0.0, 0.0, GROUND_COV), t, restart=(k == 0))
    assert f.stats.count("failed_ground") == 7
    assert f.source == "ground"  # 7 < ground_failures_to_switch_out
    for _ in range(5):
        t = run_static(f, t, t + 0.05)
        f.add_ground(FakeGround(False, 0.0, 0.0, 0.0, GROUND_COV), t)
    assert f.source == "none" and not f.estimate_latest().ok and not f.estimate().ok
    t = run_static(f, t, t + 0.05)
    f.add_ground(FakeGround(True, 0.0, 0.0, 0.0, GROUND_COV), t)
    assert f.source == "ground" and f.stats.count("applied_ground") == 3


# --------------------------------------------------------------------------- conversions and outputs


def test_add_rack_maps_pose_and_covariance_through_the_mounts() -> None:
    """T_ned_body = T_ned_rack T_rack_cam T_cam_body; cov_body = Ad(T_body_cam) cov_cam Ad^T."""
    rng = np.random.default_rng(2)
    T_ned_rack = se3.make(so3.exp(np.array([0.1, -0.2, 1.2])) @ frames.R_NED_RACK_DEFAULT, np.array([5.0, -3.0, 0.4]))
    T_body_cam = se3.make(so3.exp(np.array([0.3, 0.1, 0.0])) @ frames.R_BODY_CAM_DEFAULT, np.array([0.1, 0.0, 0.05]))
    f = NavigationFilter(NavFilterConfig(rack_frames_to_switch_in=1), T_ned_rack=T_ned_rack, T_body_cam=T_body_cam)
    P0 = np.diag([1.0] * 3 + [0.01**2] * 3 + [0.1**2] * 3 + [1e-4**2] * 3 + [1e-3**2] * 3)
    f.initialize(0.0, T0, covariance=P0)
    run_static(f, 0.0, 0.1)
    A = rng.normal(size=(6, 6))
    cov_cam = (A @ A.T + np.eye(6)) * 1e-6
    T_rack_cam = frames.T_rack_cam_from_T_ned_body(T0, T_ned_rack, T_body_cam)
    f.add_rack(FakeRack(True, T_rack_cam, cov_cam), 0.1)
    assert f.stats.count("applied_rack") == 1
    np.testing.assert_allclose(f.estimate().T_ned_body, T0, atol=1e-9)
    Ad = se3.adjoint(T_body_cam)
    expected = model.body_to_error_pose_covariance(T0[:3, :3], Ad @ cov_cam @ Ad.T)
    post = f.error_state_covariance()[np.ix_(model.POSE_IDX, model.POSE_IDX)]
    # The prior is 1e4 x broader, so the posterior is the measurement's covariance (to ~1 %).
    np.testing.assert_allclose(post, expected, rtol=0.02, atol=2e-3 * np.abs(expected).max())
    wrong = model.body_to_error_pose_covariance(T0[:3, :3], cov_cam)
    assert np.abs(post - wrong).max() > 0.1 * np.abs(expected).max()


def test_estimate_fields_and_position_bound() -> None:
    cfg = NavFilterConfig(rack_frames_to_switch_in=1, max_position_std_m=0.1)
    f = static_filter(cfg)
    assert not f.estimate().ok  # no visual correction yet
    t = run_static(f, 0.0, 0.5)
    f.add_absolute_pose(t - 0.033, T0, RACK_COV)
    est = f.estimate()
    assert est.ok and est.source == "rack" and est.stamp_s == pytest.approx(t - 0.033)
    np.testing.assert_allclose(est.T_ned_body[:3, 3], est.position_ned_m)
    np.testing.assert_allclose(est.T_ned_body, T0, atol=1e-3)
    np.testing.assert_array_equal(est.pose_covariance, est.pose_covariance.T)
    assert np.all(np.linalg.eigvalsh(est.pose_covariance) > 0.0)
    # Position block is the NED position covariance; the angle block is the ZYX Euler covariance.
    now = f.estimate_latest()
    P, P_err = now.pose_covariance, f.error_state_covariance()
    np.testing.assert_allclose(P[:3, :3], P_err[0:3, 0:3], atol=1e-15)
    E = model.euler_rate_matrix(now.T_ned_body[:3, :3])
    np.testing.assert_allclose(P[3:, 3:], E @ P_err[6:9, 6:9] @ E.T, atol=1e-15)
    np.testing.assert_allclose(now.velocity_covariance, P_err[3:6, 3:6], atol=1e-15)
    assert est.velocity_covariance.shape == (3, 3)
    # IMU only: the position uncertainty grows past the bound and the latest estimate says so.
    noisy = NavFilterConfig(rack_frames_to_switch_in=1, max_position_std_m=0.1)
    g = NavigationFilter(noisy)
    g.initialize(0.0, T0)
    g.add_imu(static_imu(0.01))
    g.add_absolute_pose(0.01, T0, RACK_COV)
    assert g.estimate_latest().ok
    run_static(g, 0.01, 6.0)
    assert not g.estimate_latest().ok
    assert g.estimate().stamp_s == pytest.approx(0.01)  # still the last visual correction


def test_auto_initialization_levels_from_the_accelerometer() -> None:
    f = NavigationFilter(NavFilterConfig(initial_yaw_rad=0.3))
    R = frames.rotation_from_euler_zyx(0.1, -0.05, 1.0)
    f.add_imu(static_imu(5.0, R))
    rpy = frames.euler_zyx_from_rotation(f.estimate_latest().T_ned_body[:3, :3])
    np.testing.assert_allclose(rpy, [0.1, -0.05, 0.3], atol=1e-12)
    assert f.stamp_s == 5.0 and f.stats.imu_samples == 1


@dataclass(frozen=True)
class FakeGroundWithSpan(FakeGround):
    dt_s: float = 0.0


def test_ground_increment_must_start_at_the_clone() -> None:
    """With `dt_s` the filter checks the increment's reference frame against the clone's stamp."""
    f = static_filter()
    t = run_static(f, 0.0, 0.05)
    f.add_ground(FakeGroundWithSpan(True, 0.0, 0.0, 0.0, GROUND_COV, dt_s=0.0), t)  # first frame
    assert f.stats.count("anchor_ground") == 1
    t = run_static(f, t, t + 0.05)
    f.add_ground(FakeGroundWithSpan(True, 0.0, 0.0, 0.0, GROUND_COV, dt_s=0.05), t)
    assert f.stats.count("applied_ground") == 1
    # A failed frame; the odometer kept its older reference (a blank image), so the
    # next increment spans two frames and does not start at the clone (the failed frame).
    t = run_static(f, t, t + 0.05)
    f.add_ground(FakeGroundWithSpan(False, 0.0, 0.0, 0.0, np.zeros((3, 3)), dt_s=0.0), t)
    t = run_static(f, t, t + 0.05)
    f.add_ground(FakeGroundWithSpan(True, 0.0, 0.0, 0.0, GROUND_COV, dt_s=0.1), t)
    assert f.stats.count("unanchored_ground") == 1 and f.stats.count("applied_ground") == 1
    # Failed again, but this time the odometer moved its reference to the failed frame.
    t = run_static(f, t, t + 0.05)
    f.add_ground(FakeGroundWithSpan(False, 0.0, 0.0, 0.0, np.zeros((3, 3)), dt_s=0.0), t)
    t = run_static(f, t, t + 0.05)
    f.add_ground(FakeGroundWithSpan(True, 0.0, 0.0, 0.0, GROUND_COV, dt_s=0.05), t)
    assert f.stats.count("applied_ground") == 2 and f.stats.count("failed_ground") == 2


def _on_the_rack(cfg: NavFilterConfig) -> tuple[NavigationFilter, float]:
    """A static filter that has switched to the rack (5 frames at T0); returns it and the time reached."""
    f = static_filter(cfg)
    T_rack_cam = frames.T_rack_cam_from_T_ned_body(T0, frames.default_T_ned_rack(), frames.default_T_body_cam())
    t = 0.0
    for _ in range(5):
        t = run_static(f, t, t + 0.05)
        f.add_rack(FakeRack(True, T_rack_cam, RACK_COV), t)
    assert f.source == "rack" and f.reset_counter == 0
    return f, t


def test_rack_back_after_silence_is_reacquired_with_a_reset_if_needed() -> None:
    cfg = NavFilterConfig(rack_frames_to_switch_in=3, source_timeout_s=0.3)
    f, t = _on_the_rack(cfg)
    t = run_static(f, t, t + 1.0)  # no frames at all for 1 s: the source stays "rack"
    assert f.source == "rack"
    shifted = se3.make(np.eye(3), np.array([0.0, 0.0, 0.5])) @ T0
    f.add_rack(FakeRack(True, frames.T_rack_cam_from_T_ned_body(
        shifted, frames.default_T_ned_rack(), frames.default_T_body_cam()), RACK_COV), t)
    # The first frame back is used at once (no hysteresis) and, disagreeing, resets the pose.
    assert f.reset_counter == 1 and f.estimate().stamp_s == t
    np.testing.assert_allclose(f.estimate().position_ned_m, shifted[:3, 3], atol=2e-3)


def test_a_rack_pose_marked_reset_is_taken_at_once_even_when_the_gate_rejects_it() -> None:
    """Issue #16: an acquired pose (or y from the rack's end) is better than the estimate: a reset."""
    cfg = NavFilterConfig(rack_frames_to_switch_in=3)
    f, t = _on_the_rack(cfg)
    shifted = se3.make(np.eye(3), np.array([0.3, 0.0, 0.0])) @ T0
    T_shifted = frames.T_rack_cam_from_T_ned_body(shifted, frames.default_T_ned_rack(), frames.default_T_body_cam())
    t = run_static(f, t, t + 0.05)
    f.add_rack(FakeRack(True, T_shifted, RACK_COV), t)  # 30 cm away, 1 cm std: gated out
    assert f.reset_counter == 0
    np.testing.assert_allclose(f.estimate().position_ned_m, T0[:3, 3], atol=0.02)
    t = run_static(f, t, t + 0.05)
    f.add_rack(FakeRack(True, T_shifted, RACK_COV), t, reset=True)
    assert f.reset_counter == 1 and f.estimate().stamp_s == t
    np.testing.assert_allclose(f.estimate().position_ned_m, shifted[:3, 3], atol=2e-3)


@pytest.mark.parametrize("yaw_error_rad", [0.3, 1.5, 3.0])
def test_reset_keeps_the_prior_along_axes_the_rack_barely_measures(yaw_error_rad: float) -> None:
    """A rack pose known well except along the pipes (north): the reset moves east/down/attitude only."""
    cfg = NavFilterConfig(rack_frames_to_switch_in=1)
    f = static_filter(cfg)
    t = run_static(f, 0.0, 0.1)
    R_off = so3.exp(np.array([0.0, 0.0, yaw_error_rad]))
    # Body-frame covariance whose NED-north variance is huge: rotate a NED covariance into the body frame.
    R = R_off @ T0[:3, :3]
    C_ned = np.diag([10.0**2, 0.01**2, 0.01**2])
    cov = np.zeros((6, 6))
    cov[:3, :3] = R.T @ C_ned @ R
    cov[3:, 3:] = np.eye(3) * 0.005**2
    target = se3.make(R, T0[:3, 3] + np.array([3.0, 0.3, 0.2]))
    f.add_absolute_pose(t, target, cov)
    est = f.estimate()
    assert f.reset_counter == 1
    np.testing.assert_allclose(so3.log(est.T_ned_body[:3, :3].T @ R), 0.0, atol=1e-3)
    np.testing.assert_allclose(est.position_ned_m[1:], target[1:3, 3], atol=3e-3)
    # North: the prior (1 cm) beats the measurement (10 m): the estimate stays at T0 and stays ok.
    assert abs(est.position_ned_m[0] - T0[0, 3]) < 1e-3
    assert est.ok


@pytest.mark.parametrize(("offset_m", "expect_reset"), [(0.015, False), (0.12, True)])
def test_switch_that_passes_the_gate_but_moves_the_estimate_is_a_reset(offset_m: float, expect_reset: bool) -> None:
    """A loose prior (after dead reckoning) accepts a disagreeing rack pose as an ordinary update; if that
    moves the pose by more than switch_reset_position_m it is still a step for the autopilot: a reset."""
    cfg = NavFilterConfig(rack_frames_to_switch_in=2)
    assert cfg.switch_reset_position_m == 0.03
    f = static_filter(cfg, pose_std=0.3)  # 30 cm: a 12 cm disagreement is well inside the gate
    t = 0.0
    for _ in range(3):
        t = run_static(f, t, t + 0.05)
        f.add_ground(FakeGround(True, 0.0, 0.0, 0.0, GROUND_COV), t)
    assert f.source == "ground"
    shifted = se3.make(np.eye(3), np.array([offset_m, 0.0, 0.0])) @ T0
    rack = FakeRack(True, frames.T_rack_cam_from_T_ned_body(
        shifted, frames.default_T_ned_rack(), frames.default_T_body_cam()), RACK_COV)
    for _ in range(2):
        t = run_static(f, t, t + 0.05)
        p_before = f.estimate_latest().position_ned_m
        f.add_rack(rack, t)
    est = f.estimate()
    step = float(np.linalg.norm(est.position_ned_m - p_before))
    assert est.source == "rack" and f.stats.count("gated_rack") == 0
    assert step <= offset_m + 1e-9  # never beyond the disagreement
    assert (step > cfg.switch_reset_position_m) is expect_reset
    assert f.reset_counter == int(expect_reset) and est.reset_counter == int(expect_reset)
    assert f.stats.count("reset_rack") == int(expect_reset)
    assert f.stats.count("applied_rack") == int(not expect_reset)


def test_rack_whose_tilt_disagrees_with_gravity_is_not_switched_to() -> None:
    """A tracker re-locking with a 3 deg pitch error (roll and pitch are held by the IMU) is left to settle:
    no switch, no reset; once its tilt agrees, the switch takes its position (a reset if it moved)."""
    cfg = NavFilterConfig(rack_frames_to_switch_in=2)
    f = static_filter(cfg, pose_std=0.2)
    t = 0.0
    for _ in range(3):
        t = run_static(f, t, t + 0.05)
        f.add_ground(FakeGround(True, 0.0, 0.0, 0.0, GROUND_COV), t)
    assert f.source == "ground"
    shifted = se3.make(np.eye(3), np.array([0.1, 0.0, 0.0])) @ T0
    pitched = shifted @ se3.make(so3.exp(np.array([0.0, np.radians(3.0), 0.0])), np.zeros(3))

    def rack_at(T_ned_body: np.ndarray) -> FakeRack:
        return FakeRack(True, frames.T_rack_cam_from_T_ned_body(
            T_ned_body, frames.default_T_ned_rack(), frames.default_T_body_cam()), RACK_COV)

    for _ in range(4):
        t = run_static(f, t, t + 0.05)
        f.add_rack(rack_at(pitched), t)
    assert f.source == "ground" and f.reset_counter == 0 and f.stats.count("unsettled_rack") == 4
    assert f.estimate().ok
    t = run_static(f, t, t + 0.05)
    f.add_rack(rack_at(shifted), t)
    assert f.source == "ground"  # one settled frame: the hysteresis starts again
    t = run_static(f, t, t + 0.05)
    f.add_rack(rack_at(shifted), t)
    est = f.estimate()
    assert est.source == "rack" and f.reset_counter == 1
    np.testing.assert_allclose(est.position_ned_m, shifted[:3, 3], atol=5e-3)


def test_a_rack_that_stays_tilted_is_taken_after_the_settling_limit() -> None:
    """The filter's own tilt may be the wrong one: after rack_unsettled_frames_max frames the rack wins."""
    cfg = NavFilterConfig(rack_frames_to_switch_in=2, rack_unsettled_frames_max=6)
    f = static_filter(cfg)
    t = 0.0
    for _ in range(3):
        t = run_static(f, t, t + 0.05)
        f.add_ground(FakeGround(True, 0.0, 0.0, 0.0, GROUND_COV), t)
    pitched = T0 @ se3.make(so3.exp(np.array([0.0, np.radians(4.0), 0.0])), np.zeros(3))
    rack = FakeRack(True, frames.T_rack_cam_from_T_ned_body(
        pitched, frames.default_T_ned_rack(), frames.default_T_body_cam()), RACK_COV)
    for _ in range(6):
        t = run_static(f, t, t + 0.05)
        f.add_rack(rack, t)
    assert f.source == "ground" and f.stats.count("unsettled_rack") == 6
    for _ in range(2):
        t = run_static(f, t, t + 0.05)
        f.add_rack(rack, t)
    est = f.estimate()
    assert est.source == "rack" and f.reset_counter == 1
    np.testing.assert_allclose(so3.log(est.T_ned_body[:3, :3].T @ pitched[:3, :3]), 0.0, atol=2e-3)
    # The limit counts one settling: lost and back, a tracker tilted against the new attitude waits again.
    failed = FakeRack(False, rack.T_rack_cam, RACK_COV)
    for _ in range(5):
        t = run_static(f, t, t + 0.05)
        f.add_ground(FakeGround(True, 0.0, 0.0, 0.0, GROUND_COV), t)
        f.add_rack(failed, t)
    assert f.source == "ground"
    level = FakeRack(True, frames.T_rack_cam_from_T_ned_body(
        T0, frames.default_T_ned_rack(), frames.default_T_body_cam()), RACK_COV)
    t = run_static(f, t, t + 0.05)
    f.add_rack(level, t)
    assert f.source == "ground" and f.stats.count("unsettled_rack") == 7
