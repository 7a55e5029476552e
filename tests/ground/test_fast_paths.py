"""The hot-path rewrites agree with their plain formulations (same results, less Python overhead)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.vision.ground import tilt_bias
from companion.vision.ground.backproject import ground_rays_level, level_camera, rays_to_level
from companion.vision.ground.refine import (
    _corrected_points,
    _instrument_system,
    _stacked_maps,
    residuals_and_jacobian_exact,
    tilt_fields,
)
from companion.vision.ground.robust import ransac_rigid, residual_norms


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


def _rays(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-0.6, 0.6, (n, 2)), np.ones(n)])


def _instrument_reference(
    params: np.ndarray, rays_a: np.ndarray, height_a_m: float, nadir_a_m: np.ndarray, rays_b: np.ndarray,
    height_b_m: float, nadir_b_m: np.ndarray, map_b: np.ndarray, map_a: np.ndarray,
) -> np.ndarray:
    """The instrument Jacobian (N, 2, 3 + m) in its plain form: `tilt_fields` of both frames at the
    noise-averaged midpoints m = (P_a + d + R P_b) / 2 (and their image in frame b)."""
    z = params[3:]
    ea, eb = map_a @ z, map_b @ z
    Pa = _corrected_points(rays_a, height_a_m, nadir_a_m, ea)
    Pb = _corrected_points(rays_b, height_b_m, nadir_b_m, eb)
    c, s = np.cos(params[2]), np.sin(params[2])
    rb = np.stack([c * Pb[:, 0] - s * Pb[:, 1], s * Pb[:, 0] + c * Pb[:, 1]], axis=-1)
    n = rays_a.shape[0]
    J = np.zeros((n, 2, 3 + z.size))
    J[:, 0, 0] = 1.0
    J[:, 1, 1] = 1.0
    J[:, 0, 2] = -rb[:, 1]
    J[:, 1, 2] = rb[:, 0]
    d = params[:2]
    mid_a = 0.5 * (Pa + d + rb)
    ma = mid_a - d
    mid_b = np.stack([c * ma[:, 0] + s * ma[:, 1], -s * ma[:, 0] + c * ma[:, 1]], axis=-1)
    Fa = np.transpose(tilt_fields(mid_a, nadir_a_m, height_a_m * (1.0 + ea[2])), (1, 2, 0))  # (N, 2, 3)
    Fb = np.transpose(tilt_fields(mid_b, nadir_b_m, height_b_m * (1.0 + eb[2])), (1, 2, 0))
    Fa[:, :, 2] /= 1.0 + ea[2]
    Fb[:, :, 2] /= 1.0 + eb[2]
    Fb_rot = np.empty_like(Fb)
    Fb_rot[:, 0] = c * Fb[:, 0] - s * Fb[:, 1]
    Fb_rot[:, 1] = s * Fb[:, 0] + c * Fb[:, 1]
    J[:, :, 3:] = Fb_rot @ map_b - Fa @ map_a
    return J


def test_instrument_system_matches_the_instrument_jacobian(rng: np.random.Generator) -> None:
    rays_a, rays_b = _rays(rng, 40), _rays(rng, 40)
    nadir_a, nadir_b = np.array([0.02, -0.01]), np.array([-0.03, 0.04])
    p = np.concatenate([[0.05, -0.03, 0.02], rng.normal(0.0, 0.01, tilt_bias.NUM_NUISANCE)])
    args = (rays_a, 1.2, nadir_a, rays_b, 1.35, nadir_b, tilt_bias.MAP_B, tilt_bias.MAP_A)
    J = _instrument_reference(p, *args)
    _, J_public = residuals_and_jacobian_exact(p, *args, instrument=True)
    np.testing.assert_array_equal(J_public.reshape(-1, J.shape[2]), _instrument_system(p, *args))
    Jf = _instrument_system(p, *args)
    np.testing.assert_allclose(Jf, J.reshape(Jf.shape), rtol=1e-12, atol=1e-14)


def test_stacked_maps_are_cached_only_for_read_only_maps(rng: np.random.Generator) -> None:
    const = _stacked_maps(tilt_bias.MAP_A, tilt_bias.MAP_B)
    assert _stacked_maps(tilt_bias.MAP_A, tilt_bias.MAP_B) is const
    np.testing.assert_array_equal(const, np.stack([tilt_bias.MAP_A, tilt_bias.MAP_B]))
    map_a, map_b = rng.normal(size=(3, 4)), rng.normal(size=(3, 4))
    first = _stacked_maps(map_a, map_b)
    map_a[0, 0] += 1.0  # a caller reusing its (writable) arrays must never see a stale stack
    np.testing.assert_array_equal(_stacked_maps(map_a, map_b), np.stack([map_a, map_b]))
    assert not np.array_equal(first, _stacked_maps(map_a, map_b))


def test_split_back_projection_equals_the_one_call_form(rng: np.random.Generator) -> None:
    rays = _rays(rng, 30)
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.05, 0.02]
    rays_L, offset, valid = ground_rays_level(rays, 0.1, -0.2, T)
    R_L_cam, offset2 = level_camera(0.1, -0.2, T)
    rays_L2, valid2 = rays_to_level(rays, R_L_cam)
    np.testing.assert_array_equal(rays_L, rays_L2)
    np.testing.assert_array_equal(offset, offset2)
    np.testing.assert_array_equal(valid, valid2)


def _ransac_reference(a: np.ndarray, b: np.ndarray, threshold_m: float, hypotheses: int, seed: int) -> np.ndarray:
    """One hypothesis at a time, with the documented scoring (count, then truncated residual sum)."""
    n = a.shape[0]
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, size=hypotheses)
    j = (i + rng.integers(1, n, size=hypotheses)) % n
    t2 = threshold_m * threshold_m
    best, best_score = None, -np.inf
    for h in range(hypotheses):
        va, vb = a[j[h]] - a[i[h]], b[j[h]] - b[i[h]]
        if np.hypot(vb[0], vb[1]) < 1e-3:
            continue
        theta = np.arctan2(vb[0] * va[1] - vb[1] * va[0], vb[0] * va[0] + vb[1] * va[1])
        c, s = np.cos(theta), np.sin(theta)
        mb, ma = 0.5 * (b[i[h]] + b[j[h]]), 0.5 * (a[i[h]] + a[j[h]])
        d = np.array([ma[0] - (c * mb[0] - s * mb[1]), ma[1] - (s * mb[0] + c * mb[1])])
        r2 = residual_norms(a, b, np.array([d[0], d[1], theta])) ** 2
        score = np.count_nonzero(r2 <= t2) - np.minimum(r2, t2).sum() / (t2 * (n + 1))
        if score > best_score:
            best, best_score = r2 <= t2, score
    assert best is not None
    return best


def test_ransac_matches_a_per_hypothesis_reference(rng: np.random.Generator) -> None:
    n = 120
    b = rng.uniform(-1.0, 1.0, (n, 2))
    c, s = np.cos(0.05), np.sin(0.05)
    a = b @ np.array([[c, -s], [s, c]]).T + [0.03, -0.02] + rng.normal(0.0, 1e-3, (n, 2))
    a[:40] += rng.uniform(-0.3, 0.3, (40, 2))  # a third of the matches are wrong
    mask = ransac_rigid(a, b, 0.004, 48, np.random.default_rng(5))
    np.testing.assert_array_equal(mask, _ransac_reference(a, b, 0.004, 48, 5))
    assert mask[40:].mean() > 0.9 and mask[:40].mean() < 0.2
