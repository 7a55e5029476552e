"""The along-pipe scan by a crossing pipe (`along_scan.py`) and its use by the tracker after a drift."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.data import data_path
from companion.errors import InputError
from companion.geometry import se3, so3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig
from companion.vision.rack.along_scan import crossing_pipes, scan_along

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
PAPER = RackModel.load(data_path("racks/paper_5pipe.toml"))  # crossing pipe along +x at y = 6 m


def _pose(y_m: float) -> np.ndarray:
    """Over pipe 3 of the paper's rack, 2 m above its support plane, looking down, slightly yawed."""
    return se3.make(so3.exp([0.0, 0.0, 0.03]) @ R_DOWN, [1.05, y_m, 2.0])


def test_only_pipes_across_the_parallel_ones_are_crossing() -> None:
    assert crossing_pipes(PAPER.pipe_arrays()).tolist() == [5]
    plain = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
    assert crossing_pipes(plain.pipe_arrays()).size == 0


@pytest.mark.parametrize("off_m", [-0.25, -0.12, 0.0, 0.09, 0.3])
def test_the_scan_finds_the_crossing_pipe_from_a_drifted_pose(off_m: float) -> None:
    scene = RackScene(PAPER, seed=3)
    T_true = _pose(5.92)
    img = scene.render(T_true, CAM, noise_std=4.0, rng=np.random.default_rng(2)).astype(np.float32)
    T_drift = T_true.copy()
    T_drift[1, 3] += off_m
    scan = scan_along(T_drift, CAM, PAPER.pipe_arrays(), img, 0.4)
    assert abs(scan.shift_m + off_m) <= 0.011, scan  # the camera moved back by the drift, to a step or two
    assert not scan.at_edge
    assert scan.runner_up < 0.5 * scan.score, scan  # one clear place
    if abs(off_m) > 0.05:
        assert scan.score > 1.5 * scan.score_at_zero, scan


def test_a_drift_beyond_the_range_is_not_taken_for_the_pipe() -> None:
    scene = RackScene(PAPER, seed=3)
    T_true = _pose(5.92)
    img = scene.render(T_true, CAM, noise_std=4.0, rng=np.random.default_rng(2)).astype(np.float32)
    T_drift = T_true.copy()
    T_drift[1, 3] += 0.6
    scan = scan_along(T_drift, CAM, PAPER.pipe_arrays(), img, 0.4)
    # The pipe lies outside the scanned range: either nothing scores, or the best sits at the range's end.
    assert scan.score < 3.0 or scan.at_edge or scan.runner_up > 0.5 * scan.score, scan


def test_nothing_is_scanned_without_a_crossing_pipe_in_view() -> None:
    scene = RackScene(PAPER, seed=3)
    T = _pose(2.0)  # 4 m from the crossing pipe
    img = scene.render(T, CAM, noise_std=4.0, rng=np.random.default_rng(2)).astype(np.float32)
    assert scan_along(T, CAM, PAPER.pipe_arrays(), img, 0.4).score == 0.0
    plain = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
    assert scan_along(T, CAM, plain.pipe_arrays(), img, 0.4).score == 0.0
    assert scan_along(T, CAM, PAPER.pipe_arrays(), img, 0.0).score == 0.0


def test_the_tracker_takes_the_crossing_pipe_back_after_drifting_along_the_pipes() -> None:
    """A pose that drifted 15 cm along the pipes (the texture and ground points carried it so, as they do
    over a stretch without spots) meets the crossing pipe: with the scan it is pulled back to the pipe,
    without it the crossing pipe's limbs are matched 20-50 px off, to what lies there."""
    scene = RackScene(PAPER, seed=5)
    rng = np.random.default_rng(4)
    ys = np.linspace(4.6, 5.9, 33)  # flying along +y towards the crossing pipe at 6 m
    imgs = [scene.render(_pose(y), CAM, noise_std=3.0, rng=rng) for y in ys]
    final_err = {}
    for range_m in (0.0, 0.4):
        tr = RackTracker(PAPER, CAM, RackTrackerConfig(along_scan_range_m=range_m))
        tr.reset(_pose(ys[0]))
        for k in range(3):
            assert tr.track(imgs[k], 0.04 * k).ok
        # the drift: the last pose (and what was placed from it) 15 cm behind along the pipes
        tr._T = tr._T.copy()
        tr._T[1, 3] -= 0.15
        tr._along_std_m = 0.5  # as the tracker's own along-pipe std reads after metres without correction
        errs = []
        for k in range(3, len(ys)):
            est = tr.track(imgs[k], 0.04 * k)
            errs.append(abs(float(est.T_rack_cam[1, 3] - ys[k])))
        final_err[range_m] = float(np.mean(errs[-5:]))
    assert final_err[0.4] < 0.02, final_err
    assert final_err[0.0] > 0.08, final_err


def test_the_config_refuses_a_negative_range_or_a_gain_below_one() -> None:
    with pytest.raises(InputError, match="along_scan_range_m"):
        RackTrackerConfig(along_scan_range_m=-0.1)
    with pytest.raises(InputError, match="along_scan_min_gain"):
        RackTrackerConfig(along_scan_min_gain=0.5)


def test_no_move_while_frames_are_refused_or_within_the_edge_search() -> None:
    scene = RackScene(PAPER, seed=3)
    T_true = _pose(5.92)
    img = scene.render(T_true, CAM, noise_std=4.0, rng=np.random.default_rng(2)).astype(np.float32)
    pipes = PAPER.pipe_arrays()

    def moved(off_m: float, lost: int = 0, residual_px: float = 0.5) -> float:
        tr = RackTracker(PAPER, CAM, RackTrackerConfig())
        T = T_true.copy()
        T[1, 3] += off_m
        tr.reset(T)
        tr._along_std_m = 0.5
        tr._lost_frames, tr._residual_px = lost, residual_px
        return float(tr._scan_along(T, pipes, img)[1, 3] - T[1, 3])

    assert abs(moved(-0.2) - 0.2) <= 0.011  # 93 px off at the crossing pipe's depth: moved back
    assert moved(-0.2, lost=1) == 0.0  # the last frame was refused: the pose may be off in every direction
    assert moved(-0.2, residual_px=2.0) == 0.0  # it barely passed
    assert moved(-0.02) == 0.0  # 9 px: within the edge search, left to the solve


def test_a_velocity_error_is_moved_out_of_the_velocity_not_kept_alive() -> None:
    """The last pose on the pipe and the velocity 15 cm/frame too fast along the pipes (field loop seed 2: after
    refused frames). Moving the last pose back with each prediction kept the velocity's error, and the scan moved
    every later frame too; after a moved frame only the prediction moves, so the velocity takes the move back."""
    scene = RackScene(PAPER, seed=5)
    rng = np.random.default_rng(4)
    ys = np.linspace(5.5, 5.9, 21)  # 2 cm/frame along +y, the crossing pipe (6 m) in view
    imgs = [scene.render(_pose(y), CAM, noise_std=3.0, rng=rng) for y in ys]
    tr = RackTracker(PAPER, CAM, RackTrackerConfig())
    tr.reset(_pose(ys[0]))
    for k in range(3):
        assert tr.track(imgs[k], 0.04 * k).ok
    tr._velocity = tr._velocity.copy()
    tr._velocity[:3] += tr._T[:3, :3].T @ np.array([0.0, 0.15 / 0.04, 0.0])  # in the camera frame
    tr._along_std_m = 0.5
    moved, errs = [], []
    for k in range(3, len(ys)):
        est = tr.track(imgs[k], 0.04 * k)
        moved.append(tr._along_moved)
        errs.append(abs(float(est.T_rack_cam[1, 3] - ys[k])))
    assert 1 <= sum(moved) <= 2, moved
    assert max(errs[4:]) < 0.02, errs
