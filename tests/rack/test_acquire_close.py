"""Rack acquisition at close range (on the deck, 0.6 m over the pipes) and y from the rack's end."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import frames, se3
from companion.sim.rack_scene import RackScene, RackSceneConfig
from companion.vision.rack import AcquisitionConfig, AcquisitionPrior, RackModel, acquire_rack
from companion.vision.rack.acquire_decide import flanked_pipes, num_limbs_ok, pattern_seen
from companion.vision.rack.acquire_end import rack_end_fix
from companion.vision.rack.acquire_verify import EdgeCheck

# The simulator's camera (companion/data/sim_default.toml): 360x240, f = 315 px.
CAM = PinholeCamera(width=360, height=240, fx=315.0, fy=315.0, cx=180.0, cy=120.0)
PAPER = Path(__file__).resolve().parents[2] / "missions" / "racks" / "paper_5pipe.toml"
DECK_HEIGHT_M = 1.0  # camera above the support plane when resting on the simulator's deck


def view(yaw: float, xyz: tuple[float, float, float]) -> np.ndarray:
    """T_rack_cam of a level body at heading `yaw` (rad) with the default mount and rack alignment."""
    T_ned_body = se3.make(frames.rotation_from_euler_zyx(0.0, 0.0, yaw), np.zeros(3))
    T = frames.T_rack_cam_from_T_ned_body(T_ned_body, frames.default_T_ned_rack(), frames.default_T_body_cam())
    T[:3, 3] = xyz
    return T


def deck_prior(T: np.ndarray, y_error_m: float = 0.4) -> AcquisitionPrior:
    """What the daemon knows on the deck: level, the deck's height (3 cm), heading to 26 deg, y to 1 m."""
    return AcquisitionPrior(roll_rad=0.0, pitch_rad=0.0, height_m=DECK_HEIGHT_M, height_std_m=0.03,
                            y_m=float(T[1, 3]) + y_error_m, y_std_m=1.0, yaw_rad=0.0, yaw_std_rad=0.45)


def _check(limb_agree: list[int], samples: int = 24) -> EdgeCheck:
    la = np.asarray(limb_agree, dtype=np.float64)
    ls = np.where(la >= 0, float(samples), 0.0)
    la = np.maximum(la, 0.0)
    m = la.size // 2
    return EdgeCheck(T_rack_cam=np.eye(4), num_samples=int(ls.sum()), agree_fraction=float(la.sum() / max(ls.sum(), 1)),
                     pipe_samples=ls[0::2] + ls[1::2], pipe_agree=la[0::2] + la[1::2], limb_samples=ls, limb_agree=la,
                     limb_polarity=np.zeros(2 * m), limb_run=la.copy(), residual_px=0.3, H_data=np.eye(8), scale2=0.25)


def test_close_range_pattern_is_one_pipe_flanked_by_its_neighbours_limbs() -> None:
    cfg = AcquisitionConfig()
    # -1: limb out of view; 24 of 24 samples agree: a clean limb; 3: a limb in view without edges
    flanked = _check([-1, -1, -1, 24, 24, 24, 24, -1, -1, -1])  # pipe 3 (index 2) + pipes 2 and 4's facing limbs
    assert list(flanked_pipes(flanked, cfg, 5)) == [2]
    assert pattern_seen(flanked, cfg, 5) and num_limbs_ok(flanked, cfg, 5) == 4
    lone = _check([-1, -1, -1, -1, 24, 24, -1, -1, -1, -1])  # one pipe alone: any pipe of that width
    assert flanked_pipes(lone, cfg, 5).size == 0 and not pattern_seen(lone, cfg, 5)
    one_side = _check([-1, -1, -1, 24, 24, 24, 3, -1, -1, -1])  # the right neighbour's limb in view, no edge
    assert flanked_pipes(one_side, cfg, 5).size == 0
    # pipe 1 and pipe 2's facing limb: pipe 1 shows the ground on its other side, which an interior pipe of
    # its radius also shows when its neighbour's limb is lost (a rust spot): not a pattern
    outer = _check([24, 24, 24, -1, -1, -1, -1, -1, -1, -1])
    assert flanked_pipes(outer, cfg, 5).size == 0
    # Far away, where two pipes fit in the image, one flanked pipe is not enough.
    far = _check([-1, 24, 24, 24, 3, 3, -1, -1, -1, -1])
    assert not pattern_seen(far, cfg, 5)


@pytest.mark.parametrize(("x_m", "yaw_deg"), [(1.1, 0.0), (1.2, -11.0), (0.72, 7.0), (0.94, 30.0)])
def test_deck_view_is_acquired_over_a_flanked_pipe(x_m: float, yaw_deg: float) -> None:
    model = RackModel.load(PAPER)
    T = view(np.deg2rad(yaw_deg), (x_m, 0.8, DECK_HEIGHT_M))
    scene = RackScene(model, seed=11)
    rng = np.random.default_rng(16)
    confident = []
    for _ in range(8):  # the daemon tries every frame: each has its own sensor noise
        res = acquire_rack(scene.render(T, CAM, noise_std=2.0, rng=rng), model, CAM, deck_prior(T))
        if res.confident:
            confident.append(res.best)
    assert confident, "no confident acquisition on the deck in 8 frames"
    for best in confident:  # never a confident wrong one
        assert best is not None and not best.reversed
        assert abs(best.T_rack_cam[0, 3] - x_m) < 0.02 and abs(best.T_rack_cam[2, 3] - DECK_HEIGHT_M) < 0.02
        assert not best.y_observed and best.T_rack_cam[1, 3] == pytest.approx(T[1, 3] + 0.4)


def test_deck_over_a_single_featureless_pipe_is_rejected() -> None:
    lone = RackModel.parallel(radii=[0.20], gaps=[], length=10.0)
    T = view(0.1, (0.2, 5.0, DECK_HEIGHT_M))
    rng = np.random.default_rng(17)
    img = RackScene(lone, seed=7, config=RackSceneConfig(spots_per_m2=0.0)).render(T, CAM, noise_std=2.0, rng=rng)
    res = acquire_rack(img, RackModel.load(PAPER), CAM, deck_prior(T))
    assert not res.confident


# ---------------------------------------------------------------------------------------------- rack end
@pytest.mark.parametrize(("height_m", "y_m", "y_error_m"),
                         list(itertools.product((1.6, 2.4), (0.1, 0.4), (-0.3, 0.25))))
def test_rack_end_in_view_gives_y(height_m: float, y_m: float, y_error_m: float) -> None:
    model = RackModel.load(PAPER)
    T = view(0.1, (1.1, y_m, height_m))
    img = RackScene(model, seed=12).render(T, CAM, noise_std=2.0, rng=np.random.default_rng(18))
    T_wrong = T.copy()
    T_wrong[1, 3] += y_error_m
    fix = rack_end_fix(img, model, CAM, T_wrong)
    assert fix.found and fix.end_y_m == 0.0 and fix.num_limbs >= 2
    assert abs(y_error_m + fix.dy_m) < 0.02


def test_no_rack_end_in_view_gives_nothing() -> None:
    model = RackModel.load(PAPER)
    T = view(0.0, (1.1, 3.0, 2.4))  # the view spans y = 2.2-3.8 m: no end, no crossing pipe
    rng = np.random.default_rng(19)
    img = RackScene(model, seed=13).render(T, CAM, noise_std=2.0, rng=rng)
    for dy in (-0.5, 0.0, 0.5):
        T_wrong = T.copy()
        T_wrong[1, 3] += dy
        assert not rack_end_fix(img, model, CAM, T_wrong).found
    flat = np.full((CAM.height, CAM.width), 120, dtype=np.uint8)
    assert not rack_end_fix(flat, model, CAM, view(0.0, (1.1, 0.2, 2.4))).found
    with pytest.raises(InputError, match="image"):
        rack_end_fix(flat[:, :10], model, CAM, T)
