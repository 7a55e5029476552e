"""The rack tracker's compiled kernels (`rack_jit.py`, `limbs_jit.py`) against the numpy code they replace:
the same results, sample by sample and over a tracked sequence of the field appearance."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import pytest

from companion import jit
from companion.camera import PinholeCamera
from companion.geometry import se3, so3
from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig, limbs_jit, rack_jit
from companion.vision.rack.edges import refine_silhouette, search_edges
from companion.vision.rack.ground import plane_points
from companion.vision.rack.limbs import clip_lines_to_view, limb_lines, occluded, sample_limbs
from companion.vision.rack.motion import median_1d, pose_jacobian

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MODEL = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175], gaps=[0.1] * 3, length=10.0)
JIT_NAMES = ("rack", "rack.limbs", "rack.ground_height", "camera.pinhole")
T = TypeVar("T")

pytestmark = pytest.mark.skipif(rack_jit.kernels() is None, reason="numba not available here")


def _both(mp: pytest.MonkeyPatch, f: Callable[..., T], *args: Any, **kwargs: Any) -> tuple[T, T]:
    """f's result with the kernels, then with every kernel set reported unavailable (numpy)."""
    compiled = f(*args, **kwargs)
    with mp.context() as m:
        m.setattr(jit, "_compiled", dict.fromkeys(JIT_NAMES))
        plain = f(*args, **kwargs)
    return compiled, plain


def _profiles_case(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An image with blurred steps and noise, samples (uv, normal) and polarities (0 and ±1 mixed)."""
    img = np.zeros((120, 160), dtype=np.float32)
    img[:, 60:] = 90.0
    img[:, 100:] += 60.0 * np.sin(np.arange(60) / 3.0)[None, :].astype(np.float32)
    img += rng.normal(0.0, 6.0, img.shape).astype(np.float32)
    uv = np.column_stack([rng.uniform(30, 130, n), rng.uniform(20, 100, n)])
    ang = rng.uniform(-0.4, 0.4, n)
    normal = np.column_stack([np.cos(ang), np.sin(ang)])
    pol = rng.choice([-1.0, 0.0, 1.0], n)
    return img, uv, normal, pol


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_edge_search_kernel_matches_numpy(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(seed)
    img, uv, normal, pol = _profiles_case(rng, 300)
    ref = rng.normal(0.0, 1.0, (300, 8))
    ref -= ref.mean(axis=1, keepdims=True)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    ref[::5] = 0.0  # samples without a learnt reference
    cases = [dict(), dict(prior_sigma_px=4.0, innermost_ratio=0.6), dict(inner_ref=ref),
             dict(inner_ref=ref, prior_sigma_px=4.0, innermost_ratio=0.6)]
    for kw in cases:
        for R, thr in ((12, 8.0), (6, 8.0 * 1.5 / 2.3)):  # a threshold float32 does not hold exactly
            a, b = _both(monkeypatch, search_edges, img, uv, normal, pol, R, thr, **kw)
            np.testing.assert_array_equal(a.found, b.found)
            np.testing.assert_allclose(a.offset_px, b.offset_px, rtol=0.0, atol=1e-9)
            np.testing.assert_array_equal(a.sign, b.sign)
            np.testing.assert_allclose(a.strength, b.strength, rtol=0.0, atol=1e-9)
            np.testing.assert_allclose(a.inner, b.inner, rtol=0.0, atol=1e-6)
            assert a.inner.shape == b.inner.shape


@pytest.mark.parametrize("max_rel_rms", [0.0, 0.08])
def test_silhouette_fit_kernel_matches_numpy(max_rel_rms: float, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(3)
    img, uv, normal, _ = _profiles_case(rng, 300)
    offset = rng.uniform(-3.0, 3.0, 300)
    a, b = _both(monkeypatch, refine_silhouette, img, uv, normal, offset, 6, 5, max_rel_rms=max_rel_rms)
    np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)


def test_pose_jacobian_median_and_ground_point_kernels_match_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(4)
    J = rng.normal(size=(57, 2, 3))
    p = rng.normal(size=(57, 3))
    a, b = _both(monkeypatch, pose_jacobian, J, p)
    np.testing.assert_array_equal(a, b)
    for n in (1, 2, 7, 300, 301):
        x = rng.normal(size=n)
        a, b = _both(monkeypatch, median_1d, x)
        assert a == b == np.median(x)
    x[3] = np.nan
    assert np.isnan(median_1d(x))
    d = rng.normal(size=(200, 3))  # half of them point up: NaN rows
    for o in (rng.normal(size=3), rng.normal(size=(200, 3))):
        (X, dX), (X_np, dX_np) = _both(monkeypatch, plane_points, o, d, -1.5)
        np.testing.assert_array_equal(X, X_np)
        np.testing.assert_array_equal(dX, dX_np)
        assert 50 < np.isnan(X[:, 0]).sum() < 150


def test_limb_clipping_occlusion_and_sampling_kernels_match_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(5)
    pipes = MODEL.pipe_arrays()
    n_hidden = n_samples = 0
    for _ in range(20):
        # from beside the rack and low (neighbours hide each other) to high above it
        T = se3.make(so3.exp(rng.normal(0.0, 0.3, 3)) @ R_DOWN, [rng.uniform(-3.0, 3.5), rng.uniform(2, 8),
                                                                   rng.uniform(0.3, 3.0)])
        o = T[:3, 3]
        lines = limb_lines(o, pipes)
        A_cam = (lines.point - o) @ T[:3, :3]
        D_cam = lines.direction @ T[:3, :3]
        a, b = _both(monkeypatch, clip_lines_to_view, A_cam, D_cam, lines.s_min, lines.s_max, CAM, 6.0, 0.1)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
        # points on every pipe's surface, some hidden behind a neighbour from a low, slanted view
        k = rng.integers(0, 4, 400)
        phi = rng.uniform(0, 2 * np.pi, 400)
        y = rng.uniform(0.0, 10.0, 400)
        p_rack = pipes.starts[k] + y[:, None] * pipes.directions[k]
        p_rack[:, 0] += pipes.radii[k] * np.cos(phi)
        p_rack[:, 2] += pipes.radii[k] * np.sin(phi)
        margin = rng.uniform(0.0, 0.01, 400)
        a, b = _both(monkeypatch, occluded, o, p_rack, k, pipes, margin)
        np.testing.assert_array_equal(a, b)
        n_hidden += int(a.sum())
        # and the whole sampling (lines to samples, with numpy's fused multiply-adds in p_rack, and the normals)
        sa, sb = _both(monkeypatch, sample_limbs, T, CAM, pipes, 16, 6.0, 12.0, 0.1, 3.0)
        for name in ("p_rack", "p_cam", "uv", "normal_px", "J_uv_pcam", "pipe", "limb", "segments_uv", "segment_limb"):
            np.testing.assert_array_equal(getattr(sa, name), getattr(sb, name), err_msg=name)
        n_samples += sa.uv.shape[0]
    assert 100 < n_hidden < 20 * 400 - 100, n_hidden  # both answers exercised
    assert n_samples > 500, n_samples


def test_kernels_can_be_switched_off(monkeypatch: pytest.MonkeyPatch) -> None:
    """`COMPANION_JIT=0` (or no numba): the getters say so and the callers keep numpy."""
    monkeypatch.setenv("COMPANION_JIT", "0")
    monkeypatch.setattr(jit, "_compiled", {})
    assert rack_jit.kernels() is None and limbs_jit.kernels() is None
    assert search_edges(np.zeros((20, 20), np.float32), np.array([[10.0, 10.0]]), np.array([[1.0, 0.0]]),
                        np.array([1.0]), 3, 8.0).found.tolist() == [False]


def test_tracking_is_the_same_with_and_without_kernels() -> None:
    """A tracked sequence of the field appearance (texture spots, ground points, learnt edge profiles, the
    silhouette fit, occlusion) gives the same poses with the kernels as with numpy."""
    scene = FieldRackScene(MODEL, seed=3, config=FieldSceneConfig(num_spots=40, spots_y_m=(3.0, 5.0)))
    rng = np.random.default_rng(6)
    poses = [se3.make(so3.exp([0.01 * k, 0.0, 0.05]) @ R_DOWN, [0.3 + 0.01 * k, 4.0 + 0.01 * k, 2.2])
             for k in range(12)]
    frames = [scene.render(T, CAM, noise_std=4.0, rng=rng) for T in poses]
    out = {}
    with pytest.MonkeyPatch.context() as m:
        for label in ("jit", "numpy"):
            if label == "numpy":
                m.setattr(jit, "_compiled", dict.fromkeys(JIT_NAMES))
            tr = RackTracker(MODEL, CAM, RackTrackerConfig())
            tr.reset(poses[0] @ se3.exp(np.array([0.005, -0.005, 0.0, 0.004, 0.0, -0.004])))
            out[label] = [tr.track(img, 0.04 * k).T_rack_cam for k, img in enumerate(frames)]
            assert len(tr._texture) > 0 and len(tr._ground_uv) > 0  # both kinds of points in the solve
    err = [float(np.linalg.norm(a[:3, 3] - t[:3, 3])) for a, t in zip(out["jit"], poses, strict=True)]
    assert max(err[3:]) < 0.03, err  # it tracks (the comparison below is not between two failures)
    for a, b in zip(out["jit"], out["numpy"], strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)
