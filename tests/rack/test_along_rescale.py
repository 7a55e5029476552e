"""The ground-held along-pipe stretch rescaled to a better ground height (`along_rescale.py`) and its use by
the tracker."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import se3
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig
from companion.vision.rack.along_rescale import (
    FILTER_MAX_STD_M,
    MIN_DEPTH_M,
    MIN_HEIGHT_FRAMES,
    MIN_SHIFT_M,
    AlongLedger,
    after_shift,
    clear_correction_m,
    correction_m,
    filter_correction_m,
    record_height,
    record_step,
)
from companion.vision.rack.texture import TextureMap

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def _stretch(z_used_m: float, z_true_m: float, seed: int) -> tuple[AlongLedger, float]:
    """A ledger of 80 ground-held steps measured as if the ground were at `z_used_m` while it is at
    `z_true_m`, and the true travel (m). Camera heights wander 2.2-2.6 m; steps go back and forth."""
    rng = np.random.default_rng(seed)
    led = AlongLedger()
    travel = 0.0
    for _ in range(80):
        c = 2.4 + 0.2 * rng.uniform(-1.0, 1.0)
        dy_true = rng.normal(0.01, 0.02)
        # the ground's image motion is dy_true / (c - z_true); the solve read it at depth c - z_used
        led = record_step(led, dy_true * (c - z_used_m) / (c - z_true_m), c, z_used_m)
        travel += dy_true
    return led, travel


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_correction_at_the_true_height_gives_the_true_travel(seed: int) -> None:
    led, travel = _stretch(-3.5, -2.0, seed)
    assert abs(led.applied_m - travel) > 0.05 * abs(travel)  # the wrong height got the travel wrong
    assert led.applied_m + correction_m(led, -2.0) == pytest.approx(travel, rel=1e-9, abs=1e-12)
    assert correction_m(led, -3.5) == pytest.approx(0.0, abs=1e-12)  # at the height it used: nothing to do


def test_after_a_shift_only_the_applied_travel_moves() -> None:
    led, travel = _stretch(-3.5, -2.0, 4)
    shift = correction_m(led, -2.0)
    moved = after_shift(led, shift)
    assert moved.applied_m == pytest.approx(travel)
    assert (moved.per_depth, moved.height_weighted_m, moved.frames) == (led.per_depth, led.height_weighted_m,
                                                                         led.frames)
    assert correction_m(moved, -2.0) == pytest.approx(0.0, abs=1e-12)
    # a later, better height corrects from there
    assert correction_m(moved, -2.1) == pytest.approx(correction_m(led, -2.1) - shift)


def test_a_camera_at_the_ground_books_no_step() -> None:
    led = record_step(AlongLedger(), 0.05, -1.9 + 0.5 * MIN_DEPTH_M, -1.9)
    assert led == AlongLedger()
    assert record_step(AlongLedger(), 0.05, 2.0, float("nan")) == AlongLedger()


def test_a_rescale_waits_for_enough_heights_and_for_a_clear_correction() -> None:
    led, _ = _stretch(-3.5, -2.0, 5)
    rng = np.random.default_rng(6)
    for _ in range(MIN_HEIGHT_FRAMES):
        assert clear_correction_m(led) == 0.0  # fewer than MIN_HEIGHT_FRAMES heights
        led = record_height(led, -2.0 + 0.05 * rng.standard_normal())
    shift = clear_correction_m(led)
    mean = led.height_sum_m / led.height_frames
    assert shift == pytest.approx(correction_m(led, mean)) and shift != 0.0
    # Heights that scatter as widely as they differ from the stretch's: no clear correction.
    wide, _ = _stretch(-2.2, -2.0, 5)
    for z in (-1.0, -3.0) * MIN_HEIGHT_FRAMES:
        wide = record_height(wide, z)
    assert clear_correction_m(wide) == 0.0


def test_no_rescale_below_the_minimum_or_beyond_a_fraction_of_the_net_travel() -> None:
    heights = [-2.0] * MIN_HEIGHT_FRAMES
    short = AlongLedger()
    for _ in range(10):  # 10 cm flown at -2.1 m: a 1 mm correction at -2.0
        short = record_step(short, 0.01, 2.4, -2.1)
    for z in heights:
        short = record_height(short, z)
    assert 0.0 < abs(correction_m(short, -2.0)) < MIN_SHIFT_M and clear_correction_m(short) == 0.0
    # Back and forth: +1 m booked at -3.5 m, -1 m at -1.0 m. The net is 0, the "correction" 0.7 m.
    swing = AlongLedger()
    for _ in range(50):
        swing = record_step(swing, 0.02, 2.4, -3.5)
        swing = record_step(swing, -0.02, 2.4, -1.0)
    for z in heights:
        swing = record_height(swing, z)
    assert abs(correction_m(swing, -2.0)) > 0.1 and abs(swing.applied_m) < 1e-9
    assert clear_correction_m(swing) == 0.0


def test_a_filtered_height_rescales_once_sure_and_only_before_texture_heights() -> None:
    led, travel = _stretch(-3.5, -2.0, 8)
    # not yet surer than FILTER_MAX_STD_M (nor a meaningless spread)
    for std in (2.0, 1.5 * FILTER_MAX_STD_M, 0.0, float("nan")):
        assert filter_correction_m(led, -2.0, std) == 0.0
    shift = filter_correction_m(led, -2.0, 0.3)
    assert shift == pytest.approx(correction_m(led, -2.0)) and led.applied_m + shift == pytest.approx(travel)
    # The same height again after the shift: nothing; a height one standard deviation off: a second shift.
    moved = after_shift(led, shift)
    assert filter_correction_m(moved, -2.0, 0.3) == 0.0
    assert filter_correction_m(moved, -2.0 + 0.5 * 0.3, 0.3) == 0.0
    assert filter_correction_m(moved, -2.0 + 1.2 * 0.3, 0.3) == pytest.approx(correction_m(moved, -2.0 + 0.36))
    # once a texture-measured height is in the stretch, the texture rule decides
    assert filter_correction_m(record_height(led, -2.0), -2.0, 0.3) == 0.0


def test_a_filtered_height_does_not_rescale_small_or_back_and_forth_stretches() -> None:
    short = AlongLedger()
    for _ in range(10):
        short = record_step(short, 0.01, 2.4, -2.1)
    assert 0.0 < abs(correction_m(short, -2.0)) < MIN_SHIFT_M and filter_correction_m(short, -2.0, 0.01) == 0.0
    swing = AlongLedger()
    for _ in range(50):
        swing = record_step(swing, 0.02, 2.4, -3.5)
        swing = record_step(swing, -0.02, 2.4, -1.0)
    assert abs(correction_m(swing, -2.0)) > 0.1 and filter_correction_m(swing, -2.0, 0.01) == 0.0


def _tracker() -> RackTracker:
    model = RackModel.parallel(radii=[0.1, 0.1, 0.1, 0.1], gaps=[0.3, 0.3, 0.3], length=10.0)
    tr = RackTracker(model, CAM, RackTrackerConfig())
    tr.reset(se3.make(R_DOWN, [0.6, 2.0, 2.4]))
    return tr


def _last(tr: RackTracker, rows_along: bool = False) -> dict[str, object]:
    R = tr.T_rack_cam[:3, :3]
    A = np.zeros((40, 6))
    A[:, :3] = R[0, :]  # limbs of parallel pipes: across only
    if rows_along:
        A[20:, :3] = R[1, :]  # a crossing pipe's limbs
    return {"n_edge": 40, "A": A, "w": np.ones(40), "z_g": -2.0, "i_z": 8, "ground_uv": np.zeros((30, 2))}


def test_the_tracker_moves_pose_texture_and_ground_rays_together() -> None:
    tr = _tracker()
    tr._texture = TextureMap.empty(tr._ref_patch_size())
    tr._texture.offset_rack = np.array([[0.0, 2.5, 0.1], [0.0, 3.0, 0.1]])
    tr._texture.ref_o = np.array([[0.6, 2.0, 2.4], [0.6, 2.1, 2.4]])
    tr._ground_o = np.array([0.6, 2.0, 2.4])
    tr._anchor_o = np.array([[0.6, 1.5, 2.4]])
    tr._z_g = -2.0
    led, travel = _stretch(-3.5, -2.0, 7)
    tr._along_ledger = led
    T0 = tr.T_rack_cam.copy()
    for _ in range(MIN_HEIGHT_FRAMES):
        tr._rescale_along(_last(tr), T0, 5)  # texture-measured frames at the fitted height -2.0
    shift = travel - led.applied_m
    assert tr.T_rack_cam[1, 3] - T0[1, 3] == pytest.approx(shift)
    assert np.allclose(tr.T_rack_cam[[0, 2], 3], T0[[0, 2], 3])
    assert np.allclose(tr._texture.offset_rack[:, 1], [2.5 + shift, 3.0 + shift])
    assert np.allclose(tr._texture.ref_o[:, 1], [2.0 + shift, 2.1 + shift])
    assert tr._ground_o[1] == pytest.approx(2.0 + shift) and tr._anchor_o[0, 1] == pytest.approx(1.5 + shift)
    tr._rescale_along(_last(tr), tr.T_rack_cam.copy(), 5)  # done: no second move
    assert tr.T_rack_cam[1, 3] - T0[1, 3] == pytest.approx(shift)


def test_ground_held_frames_book_steps_and_a_crossing_pipe_closes_the_stretch() -> None:
    tr = _tracker()
    T_old = tr.T_rack_cam.copy()
    T_new = T_old.copy()
    T_new[1, 3] += 0.02
    tr._T = T_new
    tr._rescale_along(_last(tr), T_old, 0)  # no texture: the ground held the step
    assert tr._along_ledger.frames == 1 and tr._along_ledger.applied_m == pytest.approx(0.02)
    assert tr._along_ledger.per_depth == pytest.approx(0.02 / (2.4 + 2.0))
    tr._rescale_along(_last(tr, rows_along=True), T_old, 0)
    assert tr._along_ledger == AlongLedger()


def test_ground_held_frames_rescale_to_the_filtered_height_unless_the_height_is_given() -> None:
    for given in (None, -2.0):
        tr = _tracker()
        if given is not None:
            tr.config = RackTrackerConfig(ground_height_m=given)
        led, travel = _stretch(-3.5, -2.0, 9)
        tr._along_ledger = led
        tr._zf, tr._zf_var = -2.0, (1.5 * FILTER_MAX_STD_M) ** 2  # not sure yet: no shift
        T_old = tr.T_rack_cam.copy()
        tr._rescale_along(_last(tr), T_old, 0)
        assert tr.T_rack_cam[1, 3] == T_old[1, 3]
        tr._zf_var = 0.2**2
        tr._rescale_along(_last(tr), T_old, 0)
        booked = tr._along_ledger
        if given is None:
            assert booked.applied_m == pytest.approx(travel, abs=1e-9)  # the last step is at -2.0: booked as is
            assert tr.T_rack_cam[1, 3] - T_old[1, 3] == pytest.approx(travel - led.applied_m, abs=1e-9)
        else:  # a surveyed height holds every frame's solve: nothing to rescale to
            assert tr.T_rack_cam[1, 3] == T_old[1, 3]


def test_the_config_switch_is_a_bool() -> None:
    assert RackTrackerConfig().along_rescale is True
    with pytest.raises(InputError):
        RackTrackerConfig(along_rescale="yes")  # type: ignore[arg-type]
