"""RackTracker fed garbage between good frames: it never raises, its pose stays finite, blank frames are refused,
and after a reset it tracks again."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.daemon.wiring import DAEMON_RACK_TRACKER
from companion.geometry import se3, so3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import Pipe, RackModel, RackTracker, RackTrackerConfig

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
CROSS = Pipe(radius=0.12, start=(-0.5, 5.0, 0.52), direction=(1.0, 0.0, 0.0), length=3.5)
MODEL = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175], gaps=[0.1] * 3, length=10.0, extra=[CROSS])
N_GOOD = 12


@pytest.fixture(scope="module")
def frames() -> tuple[list[np.ndarray], list[np.ndarray]]:
    scene = RackScene(MODEL, seed=4)
    rng = np.random.default_rng(3)
    poses = [se3.make(so3.exp([0.0, 0.0, 0.01 * k]) @ R_DOWN, [0.8 + 0.01 * k, 4.4 + 0.02 * k, 2.4])
             for k in range(N_GOOD)]
    return poses, [scene.render(T, CAM, noise_std=3.0, rng=rng) for T in poses]


@pytest.mark.parametrize("settings", ["library", "daemon"])
def test_garbage_frames_never_raise_blank_ones_are_refused_and_a_reset_recovers(
    frames: tuple[list[np.ndarray], list[np.ndarray]], settings: str
) -> None:
    poses, images = frames
    cfg = RackTrackerConfig(**(DAEMON_RACK_TRACKER if settings == "daemon" else {}))
    tr = RackTracker(MODEL, CAM, cfg)
    tr.reset(poses[0])
    rng = np.random.default_rng(17)
    stamp_s = 0.0
    kinds = ["good", "black", "white", "noise", "other", "shifted", "reset_far", "stamp_back", "stamp_gap"]
    for step in range(60):
        kind = kinds[int(rng.integers(len(kinds)))] if step >= 2 else "good"
        k = step % N_GOOD
        img = images[k]
        stamp_s += 0.04
        if kind == "black":
            img = np.zeros_like(img)
        elif kind == "white":
            img = np.full_like(img, 255)
        elif kind == "noise":
            img = rng.integers(0, 256, img.shape, dtype=np.uint8)
        elif kind == "other":
            img = images[int(rng.integers(N_GOOD))]
        elif kind == "shifted":
            img = np.roll(img, int(rng.integers(-80, 80)), axis=int(rng.integers(2)))
        elif kind == "reset_far":
            tr.reset(poses[k] @ se3.exp(rng.normal(0.0, [0.3, 0.3, 0.3, 0.1, 0.1, 0.1])))
        elif kind == "stamp_back":
            stamp_s -= 0.2
        elif kind == "stamp_gap":
            stamp_s += 3.0
        est = tr.track(img, stamp_s)
        assert np.all(np.isfinite(est.T_rack_cam)), (step, kind)
        assert np.all(np.isfinite(est.covariance)), (step, kind)
        if kind in ("black", "white"):
            assert not est.ok and est.status, (step, kind)
    # nothing the garbage left behind (texture, ground points, velocity, gaps) stops it tracking from a reset
    tr.reset(poses[0])
    for k in range(6):
        stamp_s += 0.04
        est = tr.track(images[k], stamp_s)
        assert est.ok, (k, est.status)
        assert np.linalg.norm(est.T_rack_cam[:3, 3] - poses[k][:3, 3]) < 0.02
