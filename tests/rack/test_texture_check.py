"""The texture check (`texture_check.py`): the edge + ground step about rack x, the mute's life cycle, and
its wiring in the tracker (muted points dropped and weightless, then new points on probation)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import se3, so3
from companion.vision.rack.texture_check import (
    AVERAGE_FRAMES,
    MUTE_FRAMES,
    PROBATION_FRAMES,
    SUSPICION_FRAMES,
    TextureCheck,
    valley_step_rad,
)

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def test_valley_step_is_the_rows_own_least_squares_rotation_about_rack_x(rng: np.random.Generator) -> None:
    # Rows that see every parameter strongly (the ridge is then negligible), residuals made by a known step:
    # the step's rotation about rack x comes back. Rows outside `rows` (a texture point pulling elsewhere)
    # do not count.
    R = so3.exp(rng.normal(0.0, 0.1, 3)) @ R_DOWN
    A = rng.normal(0.0, 300.0, (200, 9))
    x_true = rng.normal(0.0, 0.01, 9)
    r = A @ x_true
    r[190:] += 50.0  # ten rows with another opinion, left out below
    w = rng.uniform(0.5, 1.5, 200)
    got = valley_step_rad(A, w, r, np.arange(190), R)
    assert got == pytest.approx(float(R[0, :] @ x_true[3:6]), rel=1e-5, abs=1e-9)
    with_them = valley_step_rad(A, w, r, np.arange(200), R)
    assert abs(with_them - got) > 1e-4


def test_the_check_mutes_after_a_persistent_disagreement_and_holds_then_releases() -> None:
    thr = np.radians(0.3)
    check = TextureCheck()
    for frame in range(100):  # steps that average out: never muted, no probation
        assert not check.update(np.radians(0.5) * (-1) ** frame, frame, thr)
    assert not check.muted and check.probation_frames(100) == 0
    check = TextureCheck()
    check.update(float("nan"), 0, thr)  # left out, or the average would stay NaN and never fire
    assert check.mean_rad == 0.0
    fired = [check.update(np.radians(0.5), frame, thr) for frame in range(40)]
    # The average of a constant 0.5 deg step crosses 0.3 deg after n frames with 1 - (1 - 1/N)^n > 0.6.
    n = int(np.ceil(np.log(0.4) / np.log(1.0 - 1.0 / AVERAGE_FRAMES)))
    assert fired.index(True) == n - 1 and sum(fired) == 1
    start = check.mute_start
    assert start == n - 1 and check.muted
    ages = np.array([0, 3, 10])
    np.testing.assert_array_equal(check.point_weights(ages, start + 1), 0.0)  # muted: no texture weight
    frame = start + 1
    while check.muted:
        check.update(0.0, frame, thr)
        frame += 1
    # Released only after MUTE_FRAMES and once the average fell under half the threshold.
    assert frame - start >= MUTE_FRAMES and abs(check.mean_rad) <= 0.5 * thr
    assert check.probation_frames(frame) == PROBATION_FRAMES
    np.testing.assert_array_equal(check.point_weights(ages, frame), [0.0, 0.0, 1.0])
    assert check.probation_frames(start + SUSPICION_FRAMES) == 0
    np.testing.assert_array_equal(check.point_weights(ages, start + SUSPICION_FRAMES), 1.0)


def test_the_tracker_drops_and_mutes_its_texture_when_the_check_fires() -> None:
    """Wiring: a consistent sequence never fires the check (the same estimates as with it off); when it
    fires, the texture points are dropped, the new ones carry no weight while muted, and after the mute
    only points tracked for PROBATION_FRAMES count (`num_texture_points` reports the weighted ones)."""
    from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
    from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig

    model = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.1], length=10.0)
    scene = FieldRackScene(model, seed=7, config=FieldSceneConfig(ground="natural", num_spots=60, jpeg_quality=0))
    T = se3.make(so3.exp(np.radians([0.3, -0.2, 2.0])) @ R_DOWN, [0.55, 3.0, 2.2])
    rng = np.random.default_rng(7)
    frames = [(T @ se3.make(np.eye(3), [0.0, -0.006 * k, 0.0])) for k in range(12 + MUTE_FRAMES + 12)]
    images = [scene.render(T_k, CAM, noise_std=3.0, rng=rng) for T_k in frames]
    on, off = (RackTracker(model, CAM, RackTrackerConfig(texture_check_deg=d)) for d in (0.3, 0.0))
    for tr in (on, off):
        tr.reset(T)
    for k in range(12):
        e_on, e_off = (tr.track(images[k], k / 25.0) for tr in (on, off))
        np.testing.assert_array_equal(e_on.T_rack_cam, e_off.T_rack_cam)
    assert not on._texture_check.muted and abs(on._texture_check.mean_rad) < np.radians(0.3)
    assert e_on.num_texture_points >= 3
    # Make the next accepted frame fire the check: as if the edges had disagreed for a while.
    on._texture_check.mean_rad = np.radians(1.0)
    counts, muted = [], []
    for k in range(12, len(images)):
        est = on.track(images[k], k / 25.0)
        assert est.ok
        counts.append(est.num_texture_points)
        muted.append(on._texture_check.muted)
        if k == 12:
            assert len(on._texture) == 0 or int(on._texture.age.max()) == 0  # dropped; any left are new
    assert muted[0] and counts[1] == 0
    released = muted.index(False)
    assert released >= MUTE_FRAMES - 1
    assert all(c == 0 for c in counts[1:released])  # new points tracked, but without weight
    assert max(counts[released:]) >= 3  # texture counts again after the mute
    # A reset starts the check afresh (its frame count restarts): a mute does not outlive it.
    on._texture_check.mean_rad = np.radians(1.0)
    on.track(images[-1], len(images) / 25.0)
    assert on._texture_check.muted
    on.reset(frames[-1])
    assert not on._texture_check.muted and on._texture_check.mute_start is None
    assert on._texture_check.mean_rad == 0.0
    with pytest.raises(InputError, match="texture_check_deg"):
        RackTrackerConfig(texture_check_deg=-1.0)
