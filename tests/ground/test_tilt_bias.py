"""Slow roll/pitch bias estimation (`tilt_bias`, exact tilt model of `refine`): Jacobians vs central
differences, consistency with the first-order fields, prior bookkeeping, and known answers on an
exactly simulated flight (a synthetic tilt bias is recovered; hovering does not invent one)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import ConfigError
from companion.geometry import frames
from companion.vision.ground import GroundOdometerConfig, tilt_bias
from companion.vision.ground.backproject import ground_rays_level, rays_from_pixels
from companion.vision.ground.closed_form import gen_to_increment, solve_gen
from companion.vision.ground.refine import (
    _corrected_points,
    refine_tilt_exact,
    refine_with_nuisance,
    refine_with_tilt,
    residuals_and_jacobian_exact,
    residuals_and_jacobian_nuisance,
    tilt_corrected_points,
    tilt_fields,
)
from tests.numdiff import central_jacobian

MAP_B, MAP_A = tilt_bias.MAP_B, tilt_bias.MAP_A


def _rays(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-0.8, 0.8, (n, 2)), np.ones(n)])


def test_corrected_points_jacobian_matches_central_differences(rng: np.random.Generator) -> None:
    rays = _rays(rng, 12)
    nadir = np.array([0.02, -0.01])
    for e in (np.zeros(3), np.array([0.02, -0.03, 0.01])):
        _, J = tilt_corrected_points(rays, 1.3, nadir, e)
        Jn = central_jacobian(lambda x: tilt_corrected_points(rays, 1.3, nadir, x)[0], e)
        np.testing.assert_allclose(J.reshape(-1, 3), Jn, atol=1e-8)


def test_corrected_points_agree_with_fields_and_fast_path(rng: np.random.Generator) -> None:
    rays = _rays(rng, 50)
    nadir = np.array([0.02, -0.01])
    h = 1.3
    P0, _ = tilt_corrected_points(rays, h, nadir, np.zeros(3))
    np.testing.assert_allclose(P0, nadir + h * rays[:, :2], atol=1e-15)
    # First order: e_0 field 0 + e_1 field 1 + s field 2 (the uniform nadir shift removed).
    de = np.array([1e-4, -2e-4, 3e-4])
    P1, _ = tilt_corrected_points(rays, h, nadir, de)
    first = np.tensordot(de, tilt_fields(P0, nadir, h), 1)
    assert np.abs(P1 - P0 - first).max() < 1e-3 * np.abs(first).max()
    e = np.array([0.03, -0.02, 0.01])
    np.testing.assert_allclose(_corrected_points(rays, h, nadir, e), tilt_corrected_points(rays, h, nadir, e)[0])


def test_corrected_points_undo_a_real_attitude_error(rng: np.random.Generator) -> None:
    """Rays back-projected with a wrong roll/pitch, corrected by the matching e, give the true points
    up to the uniform nadir shift (which the model leaves to the translation)."""
    T_body_cam = frames.default_T_body_cam()
    rays_cam = _rays(rng, 40)
    roll, pitch, h = 0.05, -0.03, 1.2
    d_roll, d_pitch = math.radians(0.4), math.radians(-0.3)
    true_L, nadir, _ = ground_rays_level(rays_cam, roll, pitch, T_body_cam)
    meas_L, _, _ = ground_rays_level(rays_cam, roll + d_roll, pitch + d_pitch, T_body_cam)
    truth = nadir + h * true_L[:, :2]
    fixed, _ = tilt_corrected_points(meas_L, h, nadir, np.array([d_roll, -d_pitch, 0.0]))
    err = fixed - truth
    raw = meas_L[:, :2] * h + nadir - truth
    # Not corrected: the non-uniform part of the warp is ~ h e |q|^2 / h^2, up to ~1 mm here.
    assert np.ptp(raw - raw.mean(0), axis=0).max() > 5e-4
    assert np.ptp(err - err.mean(0), axis=0).max() < 0.05 * np.ptp(raw - raw.mean(0), axis=0).max()


def test_exact_residual_jacobian_matches_central_differences(rng: np.random.Generator) -> None:
    rays_a = _rays(rng, 8)
    rays_b = rays_a + rng.normal(0.0, 0.01, rays_a.shape) * np.array([1.0, 1.0, 0.0])
    nadir_a, nadir_b = np.array([0.01, -0.02]), np.zeros(2)
    p = np.array([0.02, -0.01, 0.05, *rng.normal(0.0, 0.01, 8)])

    def f(x: np.ndarray) -> np.ndarray:
        return residuals_and_jacobian_exact(x, rays_a, 1.2, nadir_a, rays_b, 1.3, nadir_b, MAP_B, MAP_A)[0]

    _, J = residuals_and_jacobian_exact(p, rays_a, 1.2, nadir_a, rays_b, 1.3, nadir_b, MAP_B, MAP_A)
    np.testing.assert_allclose(J.reshape(-1, 11), central_jacobian(f, p), atol=1e-8)


def test_instrument_columns_match_the_exact_ones_on_consistent_data(rng: np.random.Generator) -> None:
    """Noise-free points that obey the motion: the instruments equal the exact columns up to O(e)."""
    rays_a = _rays(rng, 60)
    h_a, h_b, dyaw, d = 1.2, 1.25, 0.02, np.array([0.03, -0.01])
    qa = h_a * rays_a[:, :2]
    c, s = math.cos(dyaw), math.sin(dyaw)
    qb = (qa - d) @ np.array([[c, -s], [s, c]])  # qa = d + R qb
    rays_b = np.column_stack([qb / h_b, np.ones(len(qb))])
    p = np.array([d[0], d[1], dyaw, *np.zeros(8)])
    r, J = residuals_and_jacobian_exact(p, rays_a, h_a, np.zeros(2), rays_b, h_b, np.zeros(2), MAP_B, MAP_A)
    ri, Ji = residuals_and_jacobian_exact(
        p, rays_a, h_a, np.zeros(2), rays_b, h_b, np.zeros(2), MAP_B, MAP_A, instrument=True
    )
    np.testing.assert_allclose(r, 0.0, atol=1e-12)
    np.testing.assert_allclose(ri, r)
    np.testing.assert_allclose(Ji, J, atol=1e-12)


def test_nuisance_jacobian_and_reduction_to_refine_with_tilt(rng: np.random.Generator) -> None:
    b = rng.uniform(-0.8, 0.8, (60, 2))
    a = np.array([0.02, -0.01]) + b + rng.normal(0.0, 1e-3, b.shape)
    fb = tilt_fields(b, np.zeros(2), 1.2)
    fa = tilt_fields(a, np.zeros(2), 1.25)
    p = np.array([0.02, -0.01, 0.03, *rng.normal(0.0, 0.01, 8)])
    _, J = residuals_and_jacobian_nuisance(p, a[:7], b[:7], fb[:, :7], fa[:, :7], MAP_B, MAP_A)
    Jn = central_jacobian(
        lambda x: residuals_and_jacobian_nuisance(x, a[:7], b[:7], fb[:, :7], fa[:, :7], MAP_B, MAP_A)[0], p
    )
    np.testing.assert_allclose(J.reshape(-1, 11), Jn, atol=1e-8)
    # Identity maps and a diagonal prior: the same MAP estimate as refine_with_tilt.
    prior_std = np.array([0.01, 0.01, 0.008, 0.01, 0.01, 0.008])
    ref = refine_with_tilt(a, b, fb, fa, np.zeros(3), 1e-3, prior_std, 10)
    out = refine_with_nuisance(
        a, b, fb, fa, np.zeros(3), 1e-3, np.zeros(6), np.diag(prior_std**2), np.eye(6)[:3], np.eye(6)[3:], 10
    )
    np.testing.assert_allclose(out.result.increment, ref.increment, atol=1e-12)
    np.testing.assert_allclose(out.result.covariance, ref.covariance, rtol=1e-8)


def test_pair_prior_carries_the_reference_frame_and_propagates_the_bias() -> None:
    sb, sw, tau = 0.004, 0.009, 20.0
    fresh_mean, fresh_cov = tilt_bias.pair_prior(None, 0.0, 0.05, sb, tau, sw, 0.008, 0.009)
    np.testing.assert_allclose(fresh_mean, 0.0)
    np.testing.assert_allclose(np.diag(fresh_cov), [sb**2, sb**2, sw**2, sw**2, 0.009**2, sw**2, sw**2, 0.008**2])
    state = tilt_bias.TiltState(
        np.array([0.002, -0.001, 0.003, 0.004, 0.005]), np.diag([1.0, 2.0, 3.0, 4.0, 5.0]) * 1e-6, 1.0
    )
    phi = math.exp(-0.05 / tau)
    mean, cov = tilt_bias.pair_prior(state, 1.0, 1.05, sb, tau, sw, 0.008, 0.009)
    np.testing.assert_allclose(mean, [0.002 * phi, -0.001 * phi, 0.0, 0.0, 0.0, 0.003, 0.004, 0.005])
    assert cov[0, 0] == pytest.approx(phi**2 * 1e-6 + (1.0 - phi**2) * sb**2)
    np.testing.assert_allclose(np.diag(cov)[5:], [3e-6, 4e-6, 5e-6])
    # The state belongs to another frame than the reference: only its bias is carried.
    mean2, cov2 = tilt_bias.pair_prior(state, 0.9, 1.05, sb, tau, sw, 0.008, 0.009)
    np.testing.assert_allclose(mean2[5:], 0.0)
    assert cov2[5, 5] == pytest.approx(sw**2)
    after = tilt_bias.state_after(np.arange(8.0), np.diag(np.arange(1.0, 9.0)), 2.0)
    np.testing.assert_allclose(after.mean, [0, 1, 2, 3, 4])
    np.testing.assert_allclose(after.bias_rad, [0, 1])
    assert after.stamp_s == 2.0


def test_config_validates_the_bias_model() -> None:
    with pytest.raises(ConfigError):
        GroundOdometerConfig(tilt_bias_tau_s=0.0)
    with pytest.raises(ConfigError):
        GroundOdometerConfig(tilt_bias_std_rad=-1.0)
    with pytest.raises(ConfigError):
        GroundOdometerConfig(feature_std_min_px=0.0)


# ---------------------------------------------------------------- simulated flights (exact geometry)
CAM = PinholeCamera(width=752, height=480, fx=450.0, fy=450.0, cx=375.5, cy=239.5)


def _fly(
    rng: np.random.Generator,
    n: int,
    speed_m_s: float,
    bias_rad: tuple[float, float] | np.ndarray,
    white_rad: float,
    estimate_bias: bool,
    px_std: float = 0.05,
    still: bool = False,
) -> tuple[np.ndarray, float]:
    """Frame pairs of a camera flying a circle over random ground points, measured roll/pitch =
    truth + bias (constant (2,) or per frame (n, 2)) + white noise, height + 1 cm noise, pixel
    noise; each pair refined with the exact tilt model. Returns the bias estimates (n - 1, 2) as
    (roll, pitch) and the RMS over the flight of the accumulated yaw error (rad). `still`: constant
    yaw, height and attitude."""
    T_body_cam = frames.default_T_body_cam()
    dt = 0.05
    t = np.arange(n) * dt
    ang = speed_m_s * t / 2.0
    x, y = 2.0 * np.sin(ang), 2.0 * (1.0 - np.cos(ang))
    amp = 0.0 if still else 1.0
    yaw = amp * 0.5 * np.sin(0.3 * t)
    h = 1.2 + amp * 0.2 * np.sin(0.2 * t)
    roll, pitch = amp * 0.03 * np.sin(0.7 * t), amp * 0.03 * np.cos(0.5 * t)
    bias = np.broadcast_to(np.asarray(bias_rad, dtype=np.float64), (n, 2))
    roll_m = roll + bias[:, 0] + rng.normal(0.0, white_rad, n)
    pitch_m = pitch + bias[:, 1] + rng.normal(0.0, white_rad, n)
    h_m = h + rng.normal(0.0, 0.01, n)
    ground = np.column_stack([rng.uniform(-2.0, 4.0, 8000), rng.uniform(-2.0, 6.0, 8000), np.zeros(8000)])
    sb, tau = math.radians(0.25), 20.0
    state = None
    prev = None
    yaw_err = 0.0
    yaw_errs = []
    est = []
    for k in range(n):
        T_ned_body = np.eye(4)
        T_ned_body[:3, :3] = frames.rotation_from_euler_zyx(roll[k], pitch[k], yaw[k])
        T_ned_body[:3, 3] = [x[k], y[k], -h[k]]
        T_ned_cam = T_ned_body @ T_body_cam
        p_cam = (ground - T_ned_cam[:3, 3]) @ T_ned_cam[:3, :3]
        uv = CAM.project(p_cam) + rng.normal(0.0, px_std, (len(ground), 2))
        seen = CAM.in_image(np.nan_to_num(uv, nan=-1e9), margin_px=5)
        rays_L, nadir, _ = ground_rays_level(
            rays_from_pixels(CAM.fx, CAM.fy, CAM.cx, CAM.cy, 0.0, np.nan_to_num(uv)), roll_m[k], pitch_m[k], T_body_cam
        )
        if prev is not None:
            rays_prev, seen_prev = prev
            both = np.flatnonzero(seen & seen_prev)[:150]
            ra, rb = rays_prev[both], rays_L[both]
            qa, qb = h_m[k - 1] * ra[:, :2], h_m[k] * rb[:, :2]
            initial = gen_to_increment(solve_gen(qa, qb))
            z0, Pz = tilt_bias.pair_prior(
                state if estimate_bias else None, t[k - 1], t[k], sb, tau, white_rad, 0.01 / h_m[k - 1], 0.01 / h_m[k]
            )
            if not estimate_bias:  # the bias left out: its prior pinned to zero
                Pz[:2, :] *= 1e-6
                Pz[:, :2] *= 1e-6
            out = refine_tilt_exact(
                ra, h_m[k - 1], nadir, rb, h_m[k], nadir, initial, 2e-4, z0, Pz, MAP_B, MAP_A, 8, data_std_floor_m=2e-5
            )
            state = tilt_bias.state_after(out.nuisance_mean, out.nuisance_cov, t[k])
            yaw_err += float(out.result.increment[2]) - (yaw[k] - yaw[k - 1])
            yaw_errs.append(yaw_err)
            est.append([state.mean[0], -state.mean[1]])
        prev = (rays_L, seen)
    return np.array(est), float(np.sqrt(np.mean(np.square(yaw_errs))))


def test_a_synthetic_tilt_bias_is_recovered(rng: np.random.Generator) -> None:
    bias = (math.radians(0.3), math.radians(-0.2))
    est, _ = _fly(rng, 260, 0.5, bias, math.radians(0.5), estimate_bias=True)
    np.testing.assert_allclose(est[-60:].mean(axis=0), bias, atol=math.radians(0.08))


def test_a_wandering_tilt_bias_is_kept_out_of_yaw() -> None:
    """A bias that wanders (0.4 deg, 8 s period) leaks into yaw and accumulates; tracked, it does not
    (RMS accumulated yaw error 0.08 -> 0.02 deg with this seed)."""
    n = 260
    t = np.arange(n) * 0.05
    bias = math.radians(0.4) * np.column_stack([np.sin(2 * math.pi * t / 8.0), np.cos(2 * math.pi * t / 8.0)])
    errs = {}
    for estimate in (False, True):
        _, errs[estimate] = _fly(np.random.default_rng(5), n, 0.6, bias, math.radians(0.5), estimate_bias=estimate)
    assert abs(errs[False]) > math.radians(0.05)
    assert abs(errs[True]) < 0.4 * abs(errs[False])


def test_hovering_does_not_invent_a_bias(rng: np.random.Generator) -> None:
    """No motion, perfect attitude, 1 cm height noise: the shared bias is unobservable and must
    stay at its prior mean (with Jacobians taken at the noisy points, or at the uncorrected heights,
    it drifted by ~0.05 deg per frame)."""
    est, _ = _fly(rng, 120, 0.0, (0.0, 0.0), 1e-7, estimate_bias=True, still=True)
    assert np.abs(est).max() < math.radians(0.05)
