"""The daemon against the fake autopilot: start, fly, stop; SIGTERM mid-mission leaves the vehicle holding."""

from __future__ import annotations

import itertools
import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from companion.daemon.flight import read_tum
from companion.mission import State
from sitl_tests.daemon_harness import mission, rig

HOVER_MISSION = """
  <takeoff id="takeoff" height="1.0"/>
  <hover seconds="2"/>
  <land id="land"/>
"""


@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
async def test_daemon_flies_a_mission_and_stops_cleanly(tmp_path: Path, profile: str) -> None:
    async with rig(tmp_path, profile=profile) as r:
        await r.start_mission(mission(HOVER_MISSION, name="hover"))
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: ex.state in (State.COMPLETED, State.FAILED, State.ABORTED), max_s=40.0)
        assert ex.state is State.COMPLETED, [(a.action, a.result, a.message) for a in ex.results]
        await r.advance_until(lambda: not r.ap.armed, max_s=15.0)
        # what the autopilot actually received
        # PX4 gets ODOMETRY (odometry = "auto": it ignores VISION_SPEED_ESTIMATE), ArduPilot VISION_*
        pose_msg, stamp_field = ("ODOMETRY", "time_usec") if profile == "px4" else ("VISION_POSITION_ESTIMATE", "usec")
        vpe = r.received(pose_msg)
        assert len(vpe) > 50
        assert profile != "px4" or not r.received("VISION_SPEED_ESTIMATE")
        stamps = [m.fields[stamp_field] for m in vpe]
        assert all(b > a for a, b in itertools.pairwise(stamps)), "poses must never be re-sent"
        assert r.received("SET_POSITION_TARGET_LOCAL_NED"), "the hover was flown with velocity setpoints"
        assert any(int(m.fields["command"]) == 400 for m in r.received("COMMAND_LONG")), "armed by the daemon"
        flight = r.daemon.flight
        assert flight is not None
        folder = flight.path
    # after stop: flight folder complete and readable
    events = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
    names = [e["event"] for e in events]
    assert names[0] == "daemon-starting" and names[-1] == "daemon-stopped"
    assert "mission-start" in names
    tum = np.loadtxt(folder / "trajectory.tum")
    assert tum.shape[1] == 8 and tum.shape[0] > 50
    assert np.all(np.diff(tum[:, 0]) > 0)
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:8], axis=1), 1.0, atol=1e-6)
    assert (folder / "flight.tlog").stat().st_size > 1000


async def test_sigterm_mid_mission_leaves_the_vehicle_holding(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        sweep = mission("""
  <takeoff id="takeoff" height="1.0"/>
  <servo id="along" pipe="3" height="2.0" y="6.0" yaw="0" timeout="60"/>
  <land id="land"/>
""", name="long")
        await r.start_mission(sweep)
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: ex.results and ex.results[0].result == "succeeded", max_s=30.0)
        await r.advance(1.0)
        assert r.ap.armed and r.ap.truth.height_m > 0.8
        assert r.ap.mode == "GUIDED"
        t_signal = r.clock.now()
        r.daemon.install_signal_handlers()
        os.kill(os.getpid(), signal.SIGTERM)
        await r.advance_until(lambda: r.daemon.stopped, max_s=10.0)
        r.daemon.remove_signal_handlers()
        t_stop = r.clock.now()
        # the daemon put the autopilot in its hold mode (ArduPilot BRAKE = 17) and stopped commanding
        assert 17.0 in r.modes_commanded(since_s=t_signal)
        assert r.ap.mode == "BRAKE"
        assert r.ap.armed and r.ap.truth.height_m > 0.8
        assert ex.state is State.ABORTED
        await r.advance(0.5)
        assert not r.received("SET_POSITION_TARGET_LOCAL_NED", since_s=t_stop + 0.1)
        assert not r.received("VISION_POSITION_ESTIMATE", since_s=t_stop + 0.1)
        assert float(np.linalg.norm(r.ap.truth.velocity_ned_m_s)) < 0.3


async def test_replay_of_a_recorded_flight(tmp_path: Path) -> None:
    from companion.daemon.replay import replay_folder

    async with rig(tmp_path, record_frames=True) as r:
        await r.start_mission(mission('<takeoff id="takeoff" height="1.0"/><hover seconds="1"/>', name="rec"))
        await r.advance(4.0)
        assert r.daemon.flight is not None
        folder = r.daemon.flight.path
        config = r.config
    summary = replay_folder(folder, config, tmp_path / "replay", overlay=True)
    assert summary["frames"] >= 50
    assert summary["rack_ok"] >= 0.9 * summary["frames"]
    assert summary["vs_recorded_rms_m"] is not None and summary["vs_recorded_rms_m"] < 0.05
    stamps, _ = read_tum(tmp_path / "replay" / "trajectory.tum")
    assert stamps.size == summary["rack_ok"]
    assert (tmp_path / "replay" / "overlay.avi").stat().st_size > 10_000


async def test_startup_with_a_missing_piece_fails_clearly_and_commands_nothing(tmp_path: Path) -> None:
    import dataclasses

    from companion.clock import ManualClock
    from companion.daemon import Daemon, DaemonOptions
    from companion.errors import CompanionError
    from companion.sim.autopilot import FakeAutopilot, FakeAutopilotConfig
    from companion.sim.run import sim_config

    clock = ManualClock(1000.0)
    config = sim_config(tmp_path, {"rack": {"model": str(tmp_path / "missing-rack.toml")}})
    async with FakeAutopilot(FakeAutopilotConfig(listen="udpin:127.0.0.1:0"), clock=clock) as ap:
        config = dataclasses.replace(config, mavlink=dataclasses.replace(config.mavlink, url=ap.url_for_client))
        daemon = Daemon(config, clock=clock, options=DaemonOptions(vision_inline=True, api=False, sdnotify=False,
                                                                   flight_root=tmp_path / "flights"))
        with pytest.raises(CompanionError, match=r"missing-rack\.toml"):
            await daemon.start()
        await clock.advance(2.0, step_s=0.05)
        assert not ap.received_of("COMMAND_LONG", "SET_POSITION_TARGET_LOCAL_NED", "VISION_POSITION_ESTIMATE")
        assert not ap.armed
