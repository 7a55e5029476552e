"""`RackTracker.reset(keep_appearance=True)`: a re-seed of a locked tracker keeps the limb polarity it learnt and
solves its first frame once, where a plain reset tries the four polarity hypotheses."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.geometry import se3, so3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import RackModel, RackTracker
from companion.vision.rack.tracker_solve import TrackerSolve

CAM = PinholeCamera(width=360, height=240, fx=315.0, fy=315.0, cx=180.0, cy=120.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MODEL = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175], gaps=[0.1] * 3, length=10.0)


def _pose(y_m: float) -> np.ndarray:
    return se3.make(so3.exp([0.02, -0.01, 0.1]) @ R_DOWN, [0.35, y_m, 2.2])


def _solves(monkeypatch: pytest.MonkeyPatch) -> list[bool]:
    """Replace `TrackerSolve._solve` by a wrapper recording each call's `first` flag."""
    calls: list[bool] = []
    real = TrackerSolve._solve

    def spy(self: TrackerSolve, *args: object) -> dict[str, object]:
        calls.append(bool(args[5]))
        return real(self, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(TrackerSolve, "_solve", spy)
    return calls


def test_a_reseed_keeping_the_appearance_solves_once_and_lands_where_a_full_reset_does(
        monkeypatch: pytest.MonkeyPatch) -> None:
    scene = RackScene(MODEL, seed=3)
    rng = np.random.default_rng(7)
    tr = RackTracker(MODEL, CAM)
    tr.reset(_pose(4.0))
    for k in range(4):  # locked: the polarity of every limb is learnt
        est = tr.track(scene.render(_pose(4.0 + 0.02 * k), CAM, noise_std=3.0, rng=rng), 0.1 * k)
        assert est.ok, est.status
    T_true = _pose(4.3)  # a gap in the frames: 0.3 m further along
    img = scene.render(T_true, CAM, noise_std=3.0, rng=rng)
    seed = T_true @ se3.exp(np.array([0.015, 0.0, 0.01, 0.0, 0.0, np.radians(0.5)]))  # the filter's pose
    poses = {}
    for keep in (False, True):
        t = copy.deepcopy(tr)
        calls = _solves(monkeypatch)
        t.reset(seed, keep_appearance=keep)
        est = t.track(img, 1.0)
        monkeypatch.undo()
        assert est.ok, est.status
        assert calls == ([True] if keep else [True] * 4)
        poses[keep] = est.T_rack_cam
        # across the pipes and in height the edges fix it (along them it stays the seed's: no texture yet)
        d_cam = T_true[:3, :3].T @ (est.T_rack_cam[:3, 3] - T_true[:3, 3])
        assert abs(d_cam[0]) < 0.005 and abs(d_cam[2]) < 0.005, (keep, d_cam)
    np.testing.assert_allclose(poses[True], poses[False], atol=1e-3)


def test_keep_appearance_on_a_tracker_that_never_locked_tries_the_four_hypotheses(
        monkeypatch: pytest.MonkeyPatch) -> None:
    scene = RackScene(MODEL, seed=3)
    img = scene.render(_pose(4.0), CAM, noise_std=3.0, rng=np.random.default_rng(1))
    tr = RackTracker(MODEL, CAM)
    calls = _solves(monkeypatch)
    tr.reset(_pose(4.0), keep_appearance=True)  # nothing learnt yet: nothing to keep
    assert tr.track(img, 0.0).ok
    assert calls == [True] * 4
