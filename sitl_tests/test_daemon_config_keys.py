"""Daemon settings that come from the config file: pose stamp time base per autopilot, vision and mission
options that used to be constructor-only, and the simulator's latency figure for either stamp base."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from companion.sim.report import SimRecord
from companion.sim.run import collect_frames
from sitl_tests.daemon_harness import VISUAL_GROUND_Z_NED_M, Rig, rig


async def _poses_and_latencies(r: Rig) -> tuple[list[Any], SimRecord]:
    """Two seconds of poses; the simulator's capture -> autopilot latency matching on what the fake received."""
    frames: list[Any] = []
    r.daemon.frame_observers.append(frames.append)
    await r.advance(2.0)
    record = SimRecord()
    vpe = r.ap.received_of("VISION_POSITION_ESTIMATE") or r.ap.received_of("ODOMETRY")
    assert r.daemon.link is not None
    base = r.daemon.link.pose_time_base
    assert base is not None
    collect_frames(frames, SimpleNamespace(done_clock_s=[]), vpe, r.start_s, record, stamp_base=base)
    return [f for f in frames if f.sent], record


async def test_px4_gets_local_pose_stamps_by_default_and_the_sim_latency_matches_them(tmp_path: Path) -> None:
    async with rig(tmp_path, profile="px4") as r:
        link = r.daemon.link
        assert link is not None and link.config.pose_stamp_base == "auto"
        assert link.pose_time_base == "local"  # PX4 converts usec with its own TIMESYNC estimate
        sent, record = await _poses_and_latencies(r)
        assert len(sent) >= 15
        captured_usec = {round(f.capture_s * 1e6) for f in sent}
        got = [int(m.fields["time_usec"]) for m in r.ap.received_of("ODOMETRY")[-10:]]  # odometry = auto
        assert set(got) <= captured_usec  # our clock's capture time, unconverted
        assert len(record.latencies_ms) >= len(sent) - 2
        assert all(0.0 <= lat < 100.0 for lat in record.latencies_ms)


async def test_ardupilot_gets_autopilot_stamps_by_default_and_the_config_can_force_local(tmp_path: Path) -> None:
    async with rig(tmp_path / "auto") as r:
        link = r.daemon.link
        assert link is not None and link.pose_time_base == "autopilot"
        sent, record = await _poses_and_latencies(r)
        boot_usec = {round((f.capture_s - r.start_s) * 1e6) for f in sent}
        got = [int(m.fields["usec"]) for m in r.ap.received_of("VISION_POSITION_ESTIMATE")[-10:]]
        assert all(min(abs(u - b) for b in boot_usec) < 2000 for u in got)  # the fake's boot time base
        assert len(record.latencies_ms) >= len(sent) - 2
    async with rig(tmp_path / "forced", overrides={"mavlink": {"pose_stamp_base": "local"}}) as r:
        link = r.daemon.link
        assert link is not None and link.pose_time_base == "local"
        sent, record = await _poses_and_latencies(r)
        assert len(record.latencies_ms) >= len(sent) - 2


async def test_daemon_options_come_from_the_config(tmp_path: Path) -> None:
    overrides = {
        "vision": {"rack_std_floor_m": 0.02, "rack_std_floor_deg": 1.0, "rack_along_pipe_std_m": 0.05,
                   "frame_gap_reset_s": 0.6},
        "mission": {"turn_first_deg": 30.0},
        "logging": {"record_frames": True},
    }
    async with rig(tmp_path, overrides=overrides) as r:
        d = r.daemon
        assert d.turn_first_rad == math.radians(30.0)
        assert d.frame_gap_reset_s == 0.6 and d.rack_along_pipe_std_m == 0.05
        assert d.visual_ground_z_ned_m == VISUAL_GROUND_Z_NED_M  # camera.sim_ground_z_ned_m of the harness
        assert d.pipeline is not None and d.pipeline.rack_along_pipe_std_m == 0.05
        np.testing.assert_allclose(np.diag(d.pipeline.rack_covariance_floor),
                                   [0.02**2] * 3 + [math.radians(1.0) ** 2] * 3)
        assert d.record_frames and d.flight is not None
        d.flight.flush()
        assert len(list((d.flight.path / "frames").glob("*.png"))) >= 10


async def test_the_daemons_rack_tracker_runs_without_ground_points_unless_configured(tmp_path: Path) -> None:
    async with rig(tmp_path / "default") as r:
        assert r.daemon.pipeline is not None and r.daemon.pipeline.rack_tracker is not None
        assert r.daemon.pipeline.rack_tracker.config.ground_points == 0  # the library default is 60
    async with rig(tmp_path / "asked", overrides={"vision": {"rack_tracker": {"ground_points": 40}}}) as r:
        assert r.daemon.pipeline is not None and r.daemon.pipeline.rack_tracker is not None
        assert r.daemon.pipeline.rack_tracker.config.ground_points == 40
