"""`companion.daemon.hint_check`: the decision on a rack lock from the start hint (agree / disagree twice / none)."""

from __future__ import annotations

import math

import numpy as np

from companion.daemon.hint_check import HintChecker, lock_difference

COV_TIGHT = np.diag([1e-6] * 3 + [1e-6] * 3)  # 1 mm, 1 mrad: the limits are the floors


def _pose(x_m: float, z_m: float, yaw_rad: float, y_m: float = 0.5) -> np.ndarray:
    """A downward camera over the rack (optical axis along rack -z) at (x, y, z), turned by yaw about rack z."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R_down = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    T = np.eye(4)
    T[:3, :3] = Rz @ R_down
    T[:3, 3] = (x_m, y_m, z_m)
    return T


def test_lock_difference_is_across_height_and_heading_only() -> None:
    a = _pose(1.48, 1.0, math.radians(2.0), y_m=3.0)
    b = _pose(1.05, 1.08, math.radians(-1.0), y_m=0.5)
    dx, dz, dyaw = lock_difference(a, b)
    assert math.isclose(dx, 0.43, abs_tol=1e-12) and math.isclose(dz, -0.08, abs_tol=1e-12)
    assert math.isclose(dyaw, math.radians(3.0), abs_tol=1e-12)
    # heading wraps: 179 deg against -179 deg is 2 deg apart
    _, _, dyaw = lock_difference(_pose(0, 1, math.radians(179.0)), _pose(0, 1, math.radians(-179.0)))
    assert math.isclose(dyaw, math.radians(-2.0), abs_tol=1e-9)


def test_an_agreeing_check_verifies_and_stops() -> None:
    checker = HintChecker(every_frames=8)
    assert checker.due  # the first locked frame is checked at once
    T = _pose(1.05, 1.0, 0.0)
    check = checker.check(T, COV_TIGHT, _pose(1.07, 0.99, math.radians(1.0)), COV_TIGHT)
    assert check.outcome == "agrees" and checker.verdict == "verified"
    assert not checker.pending and not checker.due
    for _ in range(20):
        checker.tick()
    assert not checker.due


def test_one_pipe_off_needs_two_consistent_disagreements() -> None:
    checker = HintChecker(every_frames=3)
    tracked, acquired = _pose(1.05, 1.08, 0.0), _pose(1.48, 1.0, 0.0)
    first = checker.check(tracked, COV_TIGHT, acquired, COV_TIGHT)
    assert first.outcome == "disagrees" and checker.pending and not checker.due
    # `due` is read for the next frame before that frame's tick: checks on frames 0, 3, 6, ...
    checker.tick()  # frame 1
    assert not checker.due  # frame 2 gets none
    checker.tick()  # frame 2
    assert checker.due  # frame 3 gets one
    # a confident answer elsewhere (not consistent with the first) does not move the lock: it replaces it
    other = checker.check(tracked, COV_TIGHT, _pose(0.62, 1.0, 0.0), COV_TIGHT)
    assert other.outcome == "disagrees" and checker.pending
    # the vehicle moved 0.2 m across between attempts: the tracker and the acquisition moved alike
    step = np.eye(4)
    step[0, 3] = 0.2
    second = checker.check(step @ tracked, COV_TIGHT, step @ _pose(0.62, 1.0, 0.0), COV_TIGHT)
    assert second.outcome == "re-acquire" and checker.verdict == "re-acquired" and not checker.pending


def test_no_confident_pose_keeps_it_pending_and_limits_follow_the_covariance() -> None:
    checker = HintChecker()
    check = checker.check(_pose(1.05, 1.0, 0.0), COV_TIGHT, None, None, "ambiguous")
    assert check.outcome == "no-confident-pose" and check.status == "ambiguous" and checker.pending
    # a loose covariance (8 cm across) widens the limit to 3 std but never past the cap (15 cm)
    loose = np.diag([0.08**2, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6])
    check = checker.check(_pose(1.05, 1.0, 0.0), loose, _pose(1.17, 1.0, 0.0), COV_TIGHT)
    assert check.outcome == "agrees" and math.isclose(check.limit_x_m, 0.15)
    checker = HintChecker()
    check = checker.check(_pose(1.05, 1.0, 0.0), loose, _pose(1.48, 1.0, 0.0), COV_TIGHT)
    assert check.outcome == "disagrees"
