"""Safety behaviours through the daemon, each fault injected at the fake autopilot (or the camera).

Every assertion is on what the fake autopilot actually received (commands, setpoints, poses) or
on its true state. ArduPilot custom modes: BRAKE = 17 (the daemon's hold mode), LAND = 9.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.mission import State
from sitl_tests.daemon_harness import Rig, mission, rig

BRAKE = 17.0
LAND = 9.0
HOVER_LONG = """
  <takeoff id="takeoff" height="1.0"/>
  <hover seconds="60" timeout="90"/>
  <land id="land"/>
"""


async def airborne(r: Rig) -> None:
    """Start the long-hover mission and wait until the take-off action succeeded."""
    await r.start_mission(mission(HOVER_LONG, name="hover-long", timeout_s=90.0))
    ex = r.daemon.executor
    assert ex is not None
    await r.advance_until(lambda: bool(ex.results) and ex.results[0].result == "succeeded", max_s=20.0)
    assert r.ap.armed and r.ap.truth.height_m > 0.8


def first_mode_command(r: Rig, mode: float, since_s: float) -> float | None:
    for m in r.received("COMMAND_LONG", since_s):
        if int(m.fields["command"]) == 176 and float(m.fields["param2"]) == mode:
            return float(m.time_s)
    return None


async def test_battery_sag_lands_within_2s_of_the_debounce(tmp_path: Path) -> None:
    async with rig(tmp_path, overrides={"safety": {"battery_debounce_s": 1.0}}) as r:
        await airborne(r)
        t_fault = r.clock.now()
        r.schedule("battery-sag", in_s=0.0, voltage_v=13.6)  # below battery_low_v = 14.0
        await r.advance_until(lambda: first_mode_command(r, LAND, t_fault) is not None, max_s=6.0)
        t_land = first_mode_command(r, LAND, t_fault)
        assert t_land is not None
        assert t_land - (t_fault + 1.0) <= 2.0
        assert r.daemon.executor is not None and r.daemon.executor.state is State.ABORTED
        await r.advance(1.0)
        assert r.ap.mode == "LAND"
        assert not r.received("SET_POSITION_TARGET_LOCAL_NED", since_s=t_land + 0.2)
        await r.advance_until(lambda: r.ap.truth.on_ground, max_s=10.0)


async def test_gcs_loss_hovers_then_lands_after_the_timeout(tmp_path: Path) -> None:
    safety = {"gcs_loss_hover_s": 1.0, "gcs_loss_land_s": 3.0}
    async with rig(tmp_path, overrides={"safety": safety}) as r:
        await airborne(r)
        assert r.daemon.link is not None and r.daemon.link.state.last_gcs_heartbeat_s is not None
        r.schedule("gcs-loss", in_s=0.0)
        t_fault = r.clock.now()
        await r.advance_until(lambda: first_mode_command(r, BRAKE, t_fault) is not None, max_s=4.0)
        t_hover = first_mode_command(r, BRAKE, t_fault)
        link = r.daemon.link
        assert link is not None
        last_hb = link.state.last_gcs_heartbeat_s  # the last GCS heartbeat before the loss
        assert t_hover is not None and last_hb is not None and last_hb <= t_fault + 1e-6
        assert 1.0 <= t_hover - last_hb <= 1.5
        await r.advance(0.5)
        assert r.ap.mode == "BRAKE" and r.ap.truth.height_m > 0.8
        assert first_mode_command(r, LAND, t_fault) is None
        assert not r.received("SET_POSITION_TARGET_LOCAL_NED", since_s=t_hover + 0.2)
        await r.advance_until(lambda: first_mode_command(r, LAND, t_fault) is not None, max_s=5.0)
        t_land = first_mode_command(r, LAND, t_fault)
        assert t_land is not None and 3.0 <= t_land - last_hb <= 3.5
        await r.advance(0.5)
        assert r.ap.mode == "LAND"


async def test_vision_loss_stops_the_pose_stream_and_holds(tmp_path: Path) -> None:
    async with rig(tmp_path, overrides={"safety": {"vision_loss_hover_ms": 200}}) as r:
        await airborne(r)
        t_fault = r.clock.now()
        r.camera.featureless = True  # the camera works, the tracker sees nothing
        await r.advance_until(lambda: first_mode_command(r, BRAKE, t_fault) is not None, max_s=2.0)
        t_hover = first_mode_command(r, BRAKE, t_fault)
        assert t_hover is not None and t_hover - t_fault <= 0.5
        # the last pose stamp sent is from before the loss; nothing after
        vpe_after = r.received("VISION_POSITION_ESTIMATE", since_s=t_fault + 0.15)
        assert vpe_after == []
        await r.advance(0.2)
        assert r.ap.mode == "BRAKE"
        assert float(np.linalg.norm(r.ap.truth.velocity_ned_m_s[:2])) < 0.3
        assert not r.received("SET_POSITION_TARGET_LOCAL_NED", since_s=t_hover + 0.2)
        # a hold pauses the mission (it resumes when vision is back); it does not end it
        assert r.daemon.executor is not None and r.daemon.executor.state is State.PAUSED


async def test_short_vision_loss_holds_then_resumes_in_guided(tmp_path: Path) -> None:
    # issue #13 item 4: a 1-2 s vision fault must not end the flight; the mission resumes, and the
    # daemon (who resumes motion) switches the autopilot back to GUIDED before it streams setpoints
    async with rig(tmp_path, overrides={"safety": {"vision_loss_hover_ms": 200}}) as r:
        await airborne(r)
        ex = r.daemon.executor
        assert ex is not None
        t_fault = r.clock.now()
        r.camera.featureless = True
        await r.advance_until(lambda: first_mode_command(r, BRAKE, t_fault) is not None, max_s=2.0)
        await r.advance(0.2)
        assert r.ap.mode == "BRAKE" and ex.state is State.PAUSED
        t_back = r.clock.now()
        r.camera.featureless = False
        await r.advance_until(lambda: ex.state is State.RUNNING, max_s=3.0)
        await r.advance_until(lambda: r.ap.mode == "GUIDED", max_s=3.0)
        assert first_mode_command(r, 4.0, t_back) is not None  # MAV_CMD_DO_SET_MODE GUIDED sent by the daemon
        assert r.ap.armed and r.ap.truth.height_m > 0.8
        await r.advance(1.0)
        assert r.received("SET_POSITION_TARGET_LOCAL_NED", since_s=r.clock.now() - 0.5)
        assert first_mode_command(r, LAND, t_fault) is None


async def test_ceiling_no_climb_above_the_limit(tmp_path: Path) -> None:
    # an overhead structure 2.6 m above the deck (upward rangefinder); clearance limit 1.0 m
    async with rig(tmp_path, overrides={"safety": {"ceiling_clearance_m": 1.0}}) as r:
        r.schedule("ceiling", in_s=0.0, height_m=2.6)
        climb = mission("""
  <takeoff id="takeoff" height="1.0"/>
  <gotoz id="up" z="3.5" speed="0.5" timeout="8"/>
""", name="climb")
        await r.start_mission(climb)
        ex = r.daemon.executor
        assert ex is not None
        heights: list[float] = []
        t_end = r.clock.now() + 18.0
        while r.clock.now() < t_end and ex.state is not State.FAILED:
            await r.advance(0.1)
            heights.append(r.ap.truth.height_m)
        assert ex.results and ex.results[0].result == "succeeded"
        assert max(heights) <= 1.6 + 0.1, max(heights)
        # no setpoint the autopilot received asked to climb while within the clearance
        for m in r.received("SET_POSITION_TARGET_LOCAL_NED"):
            if m.time_s > r.clock.now() - 5.0:
                assert float(m.fields["vz"]) >= -0.05


async def test_gcs_back_ends_the_hold_and_the_mission_resumes(tmp_path: Path) -> None:
    # issue #13 item 4: after gcs-loss@T:10 the vehicle used to hover forever once the GCS was back
    safety = {"gcs_loss_hover_s": 1.0, "gcs_loss_land_s": 20.0, "gcs_resume_s": 2.0}
    async with rig(tmp_path, overrides={"safety": safety}) as r:
        await airborne(r)
        ex = r.daemon.executor
        assert ex is not None
        t_fault = r.clock.now()
        r.schedule("gcs-loss", in_s=0.0, duration_s=3.0)
        await r.advance_until(lambda: first_mode_command(r, BRAKE, t_fault) is not None, max_s=4.0)
        assert ex.state is State.PAUSED
        await r.advance_until(lambda: ex.state is State.RUNNING, max_s=8.0)  # GCS back for gcs_resume_s
        t_resumed = r.clock.now()
        assert t_resumed - t_fault >= 3.0 + 2.0 - 0.2
        await r.advance_until(lambda: r.ap.mode == "GUIDED", max_s=3.0)
        assert first_mode_command(r, 4.0, t_fault) is not None and first_mode_command(r, LAND, t_fault) is None
        assert r.ap.armed and r.ap.truth.height_m > 0.8


async def test_vision_loss_during_the_take_off_climb_holds_then_the_take_off_finishes(tmp_path: Path) -> None:
    # The brake cuts ArduCopter's NAV_TAKEOFF climb short and the daemon drops the take-off request it was
    # waiting on; resumed in the air, the take-off action climbs with the servo instead of waiting out its timeout.
    async with rig(tmp_path, overrides={"safety": {"vision_loss_hover_ms": 200}}) as r:
        await r.start_mission(mission(HOVER_LONG.replace('height="1.0"', 'height="1.5"'), name="climb-loss",
                                      timeout_s=90.0))
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: r.ap.truth.height_m > 0.4, max_s=20.0)
        assert not ex.results  # still climbing under NAV_TAKEOFF
        t_fault = r.clock.now()
        r.camera.featureless = True
        await r.advance_until(lambda: first_mode_command(r, BRAKE, t_fault) is not None, max_s=2.0)
        await r.advance(0.5)
        assert r.ap.mode == "BRAKE" and ex.state is State.PAUSED
        height_held_m = r.ap.truth.height_m
        assert height_held_m < 1.3
        r.camera.featureless = False
        await r.advance_until(lambda: bool(ex.results), max_s=20.0)
        assert ex.results[0].action_id == "takeoff" and ex.results[0].result == "succeeded", ex.results[0]
        assert r.ap.mode == "GUIDED" and abs(r.ap.truth.height_m - 1.5) < 0.15
        assert first_mode_command(r, LAND, t_fault) is None
