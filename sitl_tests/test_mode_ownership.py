"""Issue #13 item 1: whoever starts or resumes motion puts the autopilot in its guided mode first.

Pause then resume, and a new mission started while airborne after an abort, must switch the
autopilot back from its hold mode (ArduPilot BRAKE, PX4 AUTO.LOITER) to GUIDED / OFFBOARD and fly
to the goal; a mode change made by someone else under a moving mission pauses it. Asserted on the
MAV_CMD_DO_SET_MODE commands the fake autopilot received and on its true position.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from companion.mission import State
from sitl_tests.daemon_harness import Rig, mission, rig

GUIDED = {"ardupilot": ("GUIDED", 4.0), "px4": ("OFFBOARD", 6.0)}  # mode name, DO_SET_MODE param2
HOLD = {"ardupilot": "BRAKE", "px4": "AUTO.LOITER"}
GO_FAR = """
  <takeoff id="takeoff" height="1.0"/>
  <gotoxy id="far" x="1.05" y="3.0" speed="0.4" timeout="60"/>
  <hover seconds="30" timeout="60"/>
"""


def set_mode_commands(r: Rig, param2: float, since_s: float) -> list[float]:
    return [m.time_s for m in r.received("COMMAND_LONG", since_s)
            if int(m.fields["command"]) == 176 and float(m.fields["param2"]) == param2]


def pilot_switches_to_loiter(r: Rig) -> None:
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    mavutil.set_dialect("ardupilotmega")
    gcs = mavutil.mavlink_connection(r.ap.url_for_client, source_system=255, source_component=190)
    try:
        gcs.mav.command_long_send(1, 1, 176, 0, 1.0, 5.0, 0, 0, 0, 0, 0)  # DO_SET_MODE custom LOITER
    finally:
        gcs.close()


def goal_ned(r: Rig, action_id: str) -> np.ndarray:
    ex = r.daemon.executor
    assert ex is not None
    for res in ex.results:
        if res.action_id == action_id and res.T_ned_body_goal is not None:
            return np.asarray(res.T_ned_body_goal)[:3, 3]
    raise AssertionError(f"no goal for {action_id}")


@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
async def test_pause_then_resume_switches_back_to_guided_and_flies_on(tmp_path: Path, profile: str) -> None:
    mode_name, mode_param = GUIDED[profile]
    async with rig(tmp_path, profile=profile) as r:
        await r.start_mission(mission(GO_FAR, name="far", timeout_s=120.0))
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: bool(ex.results) and ex.results[0].result == "succeeded", max_s=25.0)
        await r.advance(2.0)  # on its way to the far point
        r.daemon.pause_mission()
        await r.advance_until(lambda: r.ap.mode == HOLD[profile], max_s=3.0)
        p_paused = r.ap.truth.position_ned_m.copy()
        await r.advance(2.0)
        assert np.linalg.norm(r.ap.truth.position_ned_m[:2] - p_paused[:2]) < 0.3  # holding
        t_resume = r.clock.now()
        r.daemon.resume_mission()
        await r.advance_until(lambda: r.ap.mode == mode_name, max_s=3.0)
        assert set_mode_commands(r, mode_param, t_resume), f"no DO_SET_MODE {mode_name} after resume"
        await r.advance_until(lambda: len(ex.results) >= 2, max_s=40.0)
        assert ex.results[1].result == "succeeded", ex.results[1]
        assert np.linalg.norm(r.ap.truth.position_ned_m - goal_ned(r, "far")) < 0.15


@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
async def test_new_mission_while_airborne_after_an_abort_flies(tmp_path: Path, profile: str) -> None:
    mode_name, mode_param = GUIDED[profile]
    async with rig(tmp_path, profile=profile) as r:
        await r.start_mission(mission('<takeoff id="takeoff" height="1.0"/><hover seconds="60"/>', timeout_s=90.0))
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: bool(ex.results) and ex.results[0].result == "succeeded", max_s=25.0)
        r.daemon.abort_mission()
        await r.advance_until(lambda: r.ap.mode == HOLD[profile], max_s=3.0)
        assert ex.state is State.ABORTED and r.ap.armed
        await r.advance(1.0)
        t_start = r.clock.now()
        await r.start_mission(mission('<gotoxy id="next" x="1.05" y="2.0" speed="0.4" timeout="40"/>',
                                      name="next", timeout_s=60.0))
        ex2 = r.daemon.executor
        assert ex2 is not None and ex2 is not ex
        await r.advance_until(lambda: r.ap.mode == mode_name, max_s=3.0)
        assert set_mode_commands(r, mode_param, t_start)
        await r.advance_until(lambda: ex2.state is State.COMPLETED, max_s=40.0)
        assert np.linalg.norm(r.ap.truth.position_ned_m - goal_ned(r, "next")) < 0.15


async def test_a_foreign_mode_change_pauses_the_mission_instead_of_being_fought(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        await r.start_mission(mission(GO_FAR, name="far", timeout_s=120.0))
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: bool(ex.results) and ex.results[0].result == "succeeded", max_s=25.0)
        await r.advance(2.0)
        pilot_switches_to_loiter(r)  # a pilot flips the mode switch (a second MAVLink client on the link)
        await r.advance_until(lambda: ex.state is State.PAUSED, max_s=3.0)
        t_paused = r.clock.now()
        await r.advance(3.0)
        assert r.ap.mode == "LOITER"
        assert not set_mode_commands(r, 4.0, t_paused)  # the daemon did not switch back to GUIDED by itself
