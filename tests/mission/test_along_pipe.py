"""The rack-end search leg (companion.mission.along_pipe): the reach against a brute-force projection, the
leg's length bounds, and the state machine's outcomes on a scripted vehicle (time injected)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import frames, se3
from companion.mission.along_pipe import AlongPipeSearch, SearchLimits, SearchState, end_reach_m, plan_leg

CAMERA = PinholeCamera(width=360, height=240, fx=315.0, fy=315.0, cx=180.0, cy=120.0)
T_NED_RACK = frames.default_T_ned_rack()
T_NED_RACK[:3, 3] = [-0.5, -1.1, 1.0]  # the simulator's rack: support plane 1 m below the deck (NED z = 0)
T_BODY_CAM = frames.default_T_body_cam()
LIMB_Z_M = 0.17


def body_at(y_rack_m: float, z_rack_m: float = 2.5, x_rack_m: float = 1.1, yaw_rad: float = 0.0) -> np.ndarray:
    """Body pose in NED at a rack position, heading `yaw_rad` from north (= rack +y)."""
    p_ned = se3.act(T_NED_RACK, np.array([x_rack_m, y_rack_m, z_rack_m]))
    return se3.make(frames.rotation_from_euler_zyx(0.0, 0.0, yaw_rad), p_ned)


def test_the_reach_is_where_the_limbs_leave_the_image() -> None:
    T_rack_cam = frames.T_rack_cam_from_T_ned_body(body_at(3.0), T_NED_RACK, T_BODY_CAM)
    reach = end_reach_m(CAMERA, T_rack_cam, LIMB_Z_M, min_side_m=0.15, margin_px=6.0)
    # looking straight down from 2.5 m - 0.17 m: the last row in (239 - 6 px) is 113 px from the centre row at
    # f = 315 px; less 15 cm (1 cm grid)
    depth_m = 2.5 - LIMB_Z_M
    assert reach == pytest.approx(depth_m * 113.0 / 315.0 - 0.15, abs=0.011)
    higher = end_reach_m(CAMERA, frames.T_rack_cam_from_T_ned_body(body_at(3.0, 4.5), T_NED_RACK, T_BODY_CAM),
                         LIMB_Z_M)
    assert higher > reach + 0.7  # 2 m higher: 2 m * 113 / 315 more


def test_the_leg_covers_two_std_but_never_goes_past_the_end_by_more_than_the_margin() -> None:
    limits = SearchLimits(speed_m_s=0.2, margin_m=0.5)
    T_rack_cam = frames.T_rack_cam_from_T_ned_body(body_at(0.5), T_NED_RACK, T_BODY_CAM)
    reach = end_reach_m(CAMERA, T_rack_cam, LIMB_Z_M)
    # y std 1 m: a + 2 std - reach = 0.5 + 2 - 0.69 > a + margin = 1.0: the margin bounds it
    leg = plan_leg(body_at(0.5), T_NED_RACK, T_BODY_CAM, CAMERA, 10.0, LIMB_Z_M, 1.0, limits)
    assert (leg.end_y_m, leg.direction) == (0.0, -1.0) and leg.length_m == pytest.approx(1.0)
    assert leg.reach_m == pytest.approx(reach)
    goal_rack = se3.act(se3.inverse(T_NED_RACK), leg.T_ned_body_goal[:3, 3])
    assert np.allclose(goal_rack, [1.1, -0.5, 2.5])  # only rack y changes
    assert np.allclose(leg.T_ned_body_goal[:3, :3], body_at(0.5)[:3, :3])
    # y std 0.3 m: the 2 std band ends at a + 0.6 - reach
    leg = plan_leg(body_at(0.5), T_NED_RACK, T_BODY_CAM, CAMERA, 10.0, LIMB_Z_M, 0.3, limits)
    assert leg.length_m == pytest.approx(0.5 + 0.6 - reach)
    # near the far end: toward rack +y
    leg = plan_leg(body_at(8.8, yaw_rad=math.pi), T_NED_RACK, T_BODY_CAM, CAMERA, 10.0, LIMB_Z_M, 1.0, limits)
    assert (leg.end_y_m, leg.direction) == (10.0, 1.0) and leg.length_m == pytest.approx(1.2 + 0.5, abs=0.02)
    with pytest.raises(InputError, match="y_std_m"):
        plan_leg(body_at(0.5), T_NED_RACK, T_BODY_CAM, CAMERA, 10.0, LIMB_Z_M, float("nan"), limits)
    with pytest.raises(InputError, match="speed_m_s"):
        SearchLimits(speed_m_s=0.0)


def _fly(search: AlongPipeSearch, T: np.ndarray, t0: float, t1: float, *, found_at_m: float | None = None,
         locked: bool = True, active: bool = True, dt: float = 0.05) -> tuple[np.ndarray, float, list[str]]:
    """A vehicle flying the leg's goal at the leg speed; `found_at_m`: y becomes known after that distance."""
    messages = []
    t = t0
    while t < t1 and search.state is SearchState.SEARCHING:
        known = found_at_m is not None and search.flown_m >= found_at_m
        step = search.step(t, T, y_known=known, tracker_locked=locked, active=active)
        if step.message:
            messages.append(step.message)
        if step.goal is not None and active:
            d = step.goal[:3, 3] - T[:3, 3]
            n = float(np.linalg.norm(d))
            T = T.copy()
            T[:3, 3] += d if n <= search.limits.speed_m_s * dt else d / n * search.limits.speed_m_s * dt
        t = round(t + dt, 9)
    return T, t, messages


def test_the_search_ends_found_failed_or_timed_out() -> None:
    limits = SearchLimits(speed_m_s=0.2, margin_m=0.5)
    leg = plan_leg(body_at(0.5), T_NED_RACK, T_BODY_CAM, CAMERA, 10.0, LIMB_Z_M, 1.0, limits)
    # found after 0.8 m
    search = AlongPipeSearch(limits)
    assert search.start(0.0, leg, tracker_locked=True).message.startswith("along-pipe position not observed")
    _, t, messages = _fly(search, body_at(0.5), 0.0, 30.0, found_at_m=0.8)
    assert search.state is SearchState.FOUND and t == pytest.approx(4.05, abs=0.06)
    assert messages == ["rack end in view after 0.80 m of the search leg: along-pipe position observed, "
                        "mission goes on"]
    # never found: fails once the leg's end was held for the settle time
    search = AlongPipeSearch(limits)
    search.start(0.0, leg, tracker_locked=True)
    T_end, t, messages = _fly(search, body_at(0.5), 0.0, 30.0)
    assert search.state is SearchState.FAILED and "not in view at the end of the 1.00 m search leg" in messages[0]
    assert t == pytest.approx((1.0 - 0.05) / 0.2 + 1.0, abs=0.1)  # within 5 cm of the end, then 1 s
    assert np.allclose(T_end, leg.T_ned_body_goal)
    search.override()
    assert search.state is SearchState.OVERRIDDEN
    # tracker lost on the way
    search = AlongPipeSearch(limits)
    search.start(0.0, leg, tracker_locked=True)
    _, _, _ = _fly(search, body_at(0.5), 0.0, 1.0)
    _, _, messages = _fly(search, body_at(0.5), 1.0, 2.0, locked=False)
    assert search.state is SearchState.FAILED and messages[0].startswith("rack tracker not locked after")
    # a vehicle that does not move (e.g. held by the safety manager): inactive time does not count, active does
    search = AlongPipeSearch(limits)
    search.start(0.0, leg, tracker_locked=True)
    _fly(search, body_at(0.5), 0.0, 100.0, active=False)
    assert search.state is SearchState.SEARCHING
    for k in range(2001):
        step = search.step(100.0 + 0.01 * k, body_at(0.5), y_known=False, tracker_locked=True, active=True)
        if step.state is SearchState.FAILED:
            break
    assert step.message.startswith("search leg timed out after 20 s")  # 1.0 m / 0.2 m/s + 15 s spare
    # no tracker at the start, or a leg of no length: fails at once, no goal
    assert AlongPipeSearch(limits).start(0.0, leg, tracker_locked=False).state is SearchState.FAILED
    short = plan_leg(body_at(0.5), T_NED_RACK, T_BODY_CAM, CAMERA, 10.0, LIMB_Z_M, 0.0, limits)
    step = AlongPipeSearch(limits).start(0.0, short, tracker_locked=True)
    assert short.length_m == 0.0 and step.state is SearchState.FAILED and step.goal is None
