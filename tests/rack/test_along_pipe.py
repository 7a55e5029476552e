"""The rack tracker's along-pipe standard deviation (`along_pipe.py`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.data import data_path
from companion.errors import InputError
from companion.geometry import se3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig, tracker_solve
from companion.vision.rack.along_pipe import along_pipe_std, edge_information_along, edges_see_along, widen_along
from tests.rack.spies import spy_edges_see_along

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
PARALLEL = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175], gaps=[0.1] * 3, length=10.0)
PAPER = RackModel.load(data_path("racks/paper_5pipe.toml"))


def _along_std(est_cov: np.ndarray, T_rack_cam: np.ndarray) -> float:
    e = T_rack_cam[:3, :3][1, :]
    return math.sqrt(float(e @ est_cov[:3, :3] @ e))


def test_std_grows_unobserved_is_held_by_points_and_shrinks_with_edges() -> None:
    s = along_pipe_std(0.01, 0.1, 0.05, False, math.inf, 0.5, 0.2)
    assert s == pytest.approx(0.06)  # unseen: 0.5 m/s for 0.1 s
    s = along_pipe_std(0.01, 0.1, 0.05, True, math.inf, 0.5, 0.2)
    assert s == pytest.approx(0.02)  # carried by points: 20 % of the 5 cm moved
    s = along_pipe_std(0.06, 0.1, 0.0, True, 0.01**2, 0.5, 0.2)
    assert s == pytest.approx(1.0 / math.sqrt(1 / 0.06**2 + 1 / 0.01**2))


def test_widen_along_adds_only_along_the_direction() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-4
    e = np.array([0.0, 0.6, 0.8])
    out = widen_along(cov, e, 1.0)
    assert float(e @ out[:3, :3] @ e) == pytest.approx(1.0)
    n = np.array([1.0, 0.0, 0.0])  # orthogonal to e: unchanged
    assert float(n @ out[:3, :3] @ n) == pytest.approx(float(n @ cov[:3, :3] @ n))
    assert np.array_equal(widen_along(cov, e, 1e-6), cov)  # never narrows


def test_limbs_of_parallel_pipes_carry_no_information_along_them() -> None:
    e = np.array([0.0, 1.0, 0.0])
    A = np.array([[1.0, 0.0, 0.3], [-0.5, 0.0, 0.1]])  # translation Jacobians of limb rows: no y part
    assert edge_information_along(A, np.ones(2), e) == 0.0
    assert edge_information_along(np.array([[0.0, 2.0, 0.0]]), np.array([3.0]), e) == pytest.approx(12.0)


def _run(model: RackModel, y0: float, y1: float, frames: int, cfg: RackTrackerConfig) -> tuple[RackTracker, list]:
    scene = RackScene(model, seed=5)
    tr = RackTracker(model, CAM, cfg)
    rng = np.random.default_rng(1)
    out = []
    for k, y in enumerate(np.linspace(y0, y1, frames)):
        T = se3.make(R_DOWN, [0.9, float(y), 2.4])
        if k == 0:
            tr.reset(T)
        est = tr.track(scene.render(T, CAM, noise_std=3.0, rng=rng), 0.04 * k)
        out.append((T, est))
    return tr, out


def test_reported_along_pipe_std_grows_without_texture_and_not_over_a_crossing_pipe() -> None:
    """Sliding 0.5 m along bare parallel pipes: the tracker cannot see it and now says so; over the paper
    rack's crossing pipe (y = 6 m) the edges hold the along-pipe position and the std stays small."""
    cfg = RackTrackerConfig(max_texture_points=0, ground_points=0)
    _tr, out = _run(PARALLEL, 4.0, 4.5, 26, cfg)
    T, est = out[-1]
    err = abs(float(est.T_rack_cam[1, 3] - T[1, 3]))
    std = _along_std(np.asarray(est.covariance), np.asarray(est.T_rack_cam))
    assert err > 0.1  # nothing observes the slide ...
    assert std >= err  # ... and the covariance covers it (it said ~1 cm before)
    _tr, out = _run(PAPER, 5.9, 6.1, 11, cfg)
    T, est = out[-1]
    assert est.ok
    assert abs(float(est.T_rack_cam[1, 3] - T[1, 3])) < 0.01
    assert _along_std(np.asarray(est.covariance), np.asarray(est.T_rack_cam)) < 0.02


def test_edges_see_along_the_pipes_only_with_rows_along_them() -> None:
    R = se3.make(R_DOWN, [0.0, 0.0, 2.0])[:3, :3]
    limbs = np.array([[1.0, 0.0, 0.3], [-0.5, 0.0, 0.1]])  # parallel limbs: rack x (camera x), no rack y part
    w = np.ones(2)
    assert not edges_see_along(limbs, w, R)
    crossing = np.array([[0.0, -0.5, 0.2]])  # a crossing pipe's limb: camera y is rack -y under R_DOWN
    assert edges_see_along(np.vstack([limbs, crossing]), np.ones(3), R)
    assert not edges_see_along(np.vstack([limbs, crossing]), np.array([1.0, 1.0, 0.01]), R)  # 1 % of across
    assert not edges_see_along(np.zeros((0, 3)), np.zeros(0), R)


def test_texture_weight_crossing_applies_over_a_crossing_pipe_with_fixed_gaps_only(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Over the paper rack's crossing pipe the texture rows take `texture_weight_crossing`; set to
    `texture_weight` it changes nothing, to another value it changes the poses; over parallel pipes only, or
    with the gaps estimated, it is not used."""
    seen = spy_edges_see_along(monkeypatch, tracker_solve)

    def poses(y0: float, y1: float, **kw: Any) -> np.ndarray:
        _tr, out = _run(PAPER, y0, y1, 8, RackTrackerConfig(ground_points=0, **kw))
        assert all(est.ok for _T, est in out)
        return np.array([est.T_rack_cam for _T, est in out])

    off = poses(5.9, 6.1, texture_weight_crossing=None)
    assert not seen  # None: not even asked
    same = poses(5.9, 6.1, texture_weight_crossing=RackTrackerConfig().texture_weight)
    assert any(seen)
    np.testing.assert_array_equal(same, off)
    assert not np.array_equal(poses(5.9, 6.1, texture_weight_crossing=1.0), off)
    seen.clear()
    away = poses(3.0, 3.2, texture_weight_crossing=1.0)  # the crossing pipe out of view
    assert seen and not any(seen)
    np.testing.assert_array_equal(away, poses(3.0, 3.2, texture_weight_crossing=None))
    seen.clear()
    gaps = poses(5.9, 6.1, texture_weight_crossing=1.0, estimate_gaps=True)
    assert not seen
    np.testing.assert_array_equal(gaps, poses(5.9, 6.1, texture_weight_crossing=None, estimate_gaps=True))
    with pytest.raises(InputError, match="texture_weight_crossing"):
        RackTrackerConfig(texture_weight_crossing=-1.0)


def test_the_along_pipe_std_can_be_kept_out_of_the_reported_covariance() -> None:
    """`along_pipe_widen_covariance=False`: the same poses and the same carried along-pipe std
    (`along_pipe_std_m`, which the along-pipe scan reads), but the reported covariance is the solver's own."""
    base = RackTrackerConfig(max_texture_points=0, ground_points=0)
    tr_w, out_w = _run(PARALLEL, 4.0, 4.5, 26, base)
    tr_n, out_n = _run(PARALLEL, 4.0, 4.5, 26, RackTrackerConfig(max_texture_points=0, ground_points=0,
                                                                along_pipe_widen_covariance=False))
    for (_T, a), (_T2, b) in zip(out_w, out_n, strict=True):
        assert np.array_equal(a.T_rack_cam, b.T_rack_cam)
    assert tr_n.along_pipe_std_m == tr_w.along_pipe_std_m > 0.1
    T_est = np.asarray(out_n[-1][1].T_rack_cam)
    widened = _along_std(np.asarray(out_w[-1][1].covariance), T_est)
    kept = _along_std(np.asarray(out_n[-1][1].covariance), T_est)
    assert widened == pytest.approx(tr_w.along_pipe_std_m)
    assert kept < 0.1 * widened  # the solver's own (3.5 cm here against 51 cm carried)
