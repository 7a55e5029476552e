"""The ground's height from vertical baselines with the along-pipe travel free: derivatives, fit, and in the tracker."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import se3, so3
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig
from companion.vision.rack.ground_height import SETTLE_FRAMES, fit_ground_height
from companion.vision.rack.ground_height_vertical import (
    SETTLE_FRAMES_VERTICAL,
    fit_ground_height_vertical,
    vertical_rows,
)
from tests.numdiff import central_jacobian

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def _along_flight(rng: np.random.Generator, dz_m: float, z_true: float = -2.0, travel_scale: float = 1.0,
                  n_per_anchor: int = 20, noise_px: float = 0.2) -> tuple[np.ndarray, ...]:
    """Ground points at `z_true` anchored at three poses of a flight along the pipes (rack +y, 0.2 m apart) whose
    heights differ by up to `dz_m` from the current pose's; the poses' along-pipe travel is reported times
    `travel_scale` (as a tracker that took the ground's flow at a wrong height would).
    Returns (current pose as reported, anchor centres (K, 3) and rays (K, 3) as reported, current pixels (K, 2))."""
    y_now, c_now = 4.6, 2.4
    T_now = se3.make(so3.exp(np.radians([0.3, -0.2, 1.0])) @ R_DOWN, [0.5, y_now, c_now])
    o_rep, d_rep, uv_now = [], [], []
    for i, (y_a, dz) in enumerate(((4.0, dz_m), (4.2, -dz_m), (4.4, 0.5 * dz_m))):
        T_a = se3.make(so3.exp(np.radians([0.2 * i, 0.1, 1.0 - 0.3 * i])) @ R_DOWN, [0.5, y_a, c_now + dz])
        uv_a = rng.uniform([40, 40], [680, 440], (n_per_anchor, 2))
        d = CAM.unproject(uv_a) @ T_a[:3, :3].T
        X = T_a[:3, 3] + ((z_true - T_a[2, 3]) / d[:, 2])[:, None] * d
        p = (X - T_now[:3, 3]) @ T_now[:3, :3]
        seen = p[:, 2] > 0.1
        uv_now.append(CAM.project(p[seen]) + rng.normal(0.0, noise_px, (int(seen.sum()), 2)))
        o = T_a[:3, 3].copy()
        o[1] = y_now - travel_scale * (y_now - y_a)  # the reported travel since this anchor
        o_rep.append(np.tile(o, (int(seen.sum()), 1)))
        d_rep.append(d[seen])
    return T_now, np.vstack(o_rep), np.vstack(d_rep), np.vstack(uv_now)


def test_rows_match_central_differences(rng: np.random.Generator) -> None:
    T, o, d, uv = _along_flight(rng, 0.02, n_per_anchor=4)
    group = np.repeat(np.arange(3), 4)
    uv = uv + rng.normal(0.0, 3.0, uv.shape)  # away from the solution
    for z in (-2.6, -1.7):
        rows = vertical_rows(T, CAM, o, d, uv, z, group, 3)
        assert rows.ok.all()

        def r_at(p: np.ndarray) -> np.ndarray:
            T_w = T.copy()
            T_w[:3, :3] = T[:3, :3] @ so3.exp(p[1:4])
            o_w = o.copy()
            o_w[:, 1] += p[4:][group]
            return vertical_rows(T_w, CAM, o_w, d, uv, float(p[0]), group, 3).r

        p0 = np.concatenate([[z], np.zeros(3 + 3)])
        np.testing.assert_allclose(rows.A, central_jacobian(r_at, p0), rtol=1e-5, atol=1e-6)


def test_a_wrong_along_travel_does_not_pass_for_the_height(rng: np.random.Generator) -> None:
    """The poses' along travel 29 % long (what a first guess 1.3 m low makes): a fit that trusted it would read the
    height the tracker used (-3.3 m); with each anchor's along position free the vertical baselines of 1-2 cm give
    the true height back within twice the fit's stated deviation (0.46 m here: its floor), as with the true travel."""
    for scale in (1.0, 1.29):
        T, o, d, uv = _along_flight(rng, 0.02, travel_scale=scale, n_per_anchor=40)
        fit = fit_ground_height_vertical(T, CAM, o, d, uv, -3.3, 0.008)
        assert fit is not None
        assert abs(fit.z_m + 2.0) < min(0.5, 2.0 * np.sqrt(fit.var_m2)), (scale, fit)
        assert fit.var_m2 >= (4.4 * 0.002 / 0.02) ** 2 * 0.5  # the floor: the poses' relative height error
    # the across fit has no sideways baseline here
    assert fit_ground_height(T, CAM, o, d, uv, -3.3, 0.1) is None


def test_no_fit_without_a_vertical_baseline_or_enough_points(rng: np.random.Generator) -> None:
    T, o, d, uv = _along_flight(rng, 0.004)
    assert fit_ground_height_vertical(T, CAM, o, d, uv, -3.0, 0.008) is None
    T, o, d, uv = _along_flight(rng, 0.02, n_per_anchor=2)
    assert fit_ground_height_vertical(T, CAM, o, d, uv, -3.0, 0.008) is None


def test_the_fit_is_unbiased_over_seeds() -> None:
    """30 seeds of 0.2 px noise, vertical baselines of 1-2 cm: mean within 3 cm of the truth, and the spread within
    what the stated variance says (the floor makes it conservative)."""
    z, sd = [], []
    for seed in range(30):
        T, o, d, uv = _along_flight(np.random.default_rng(seed), 0.02, travel_scale=1.2, n_per_anchor=40)
        fit = fit_ground_height_vertical(T, CAM, o, d, uv, -3.0, 0.008)
        assert fit is not None
        z.append(fit.z_m)
        sd.append(np.sqrt(fit.var_m2))
    assert abs(np.mean(z) + 2.0) < 0.03
    assert np.std(z) < np.median(sd)


def test_the_tracker_fits_vertically_from_a_full_anchor_window_and_across_only_after_the_settling(
        rng: np.random.Generator) -> None:
    """On a ground-held frame the vertical fit runs from `SETTLE_FRAMES_VERTICAL` on; on a frame whose travel
    texture measured, nothing runs before `SETTLE_FRAMES` (the across fit's wait)."""
    assert SETTLE_FRAMES_VERTICAL < SETTLE_FRAMES
    T, o, d, uv = _along_flight(rng, 0.02, travel_scale=1.29, n_per_anchor=40)
    model = RackModel.parallel(radii=[0.1, 0.1, 0.1, 0.1], gaps=[0.3, 0.3, 0.3], length=10.0)
    for frames, held, fitted in ((SETTLE_FRAMES_VERTICAL - 1, True, False), (SETTLE_FRAMES_VERTICAL, True, True),
                                 (SETTLE_FRAMES_VERTICAL, False, False), (SETTLE_FRAMES - 1, False, False)):
        tr = RackTracker(model, CAM, RackTrackerConfig())
        tr.reset(T)
        tr._z_g, tr._z_g_var, tr._frames = -3.3, 4.0, frames
        tr._fuse_ground_height(T, uv, o, d, held)
        if fitted:
            assert tr._zf is not None and tr._zf_var < 2.0**2 and abs(tr._zf + 2.0) < abs(-3.3 + 2.0)
        else:
            assert tr._zf is None, (frames, held)


def test_without_vertical_fits_a_ground_held_frame_waits_for_the_settling_too(rng: np.random.Generator) -> None:
    """With `ground_height_vertical_m=0` nothing fits early, so the height filter is not started early either."""
    T, o, d, uv = _along_flight(rng, 0.02, travel_scale=1.29, n_per_anchor=40)
    model = RackModel.parallel(radii=[0.1, 0.1, 0.1, 0.1], gaps=[0.3, 0.3, 0.3], length=10.0)
    tr = RackTracker(model, CAM, RackTrackerConfig(ground_height_vertical_m=0.0))
    tr.reset(T)
    tr._z_g, tr._z_g_var, tr._frames = -3.3, 4.0, SETTLE_FRAMES - 1
    tr._fuse_ground_height(T, uv, o, d, True)
    assert tr._zf is None


def test_config_refuses_a_negative_baseline() -> None:
    with pytest.raises(InputError, match="ground_height_vertical_m"):
        RackTrackerConfig(ground_height_vertical_m=-0.01)
    assert RackTrackerConfig(ground_height_vertical_m=0.0).ground_height_vertical_m == 0.0
