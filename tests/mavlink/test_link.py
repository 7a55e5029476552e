"""The link against a tiny scripted peer over real loopback sockets, on a ManualClock."""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Awaitable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.clock import ManualClock
from companion.control.types import VelocityCommand
from companion.errors import CommandDenied, CommandTimeout, ConfigError, LinkError
from drivers.mavlink import LinkConfig, LinkHealth, MavLink, PoseOut
from drivers.mavlink.tlog import read_tlog
from drivers.mavlink.wire import Encoder, FrameParser, covariance_from_upper_triangle
from tests.mavlink.peer import Peer

T = TypeVar("T")


async def run(clock: ManualClock, coro: Awaitable[T], step_s: float = 0.01, max_s: float = 30.0) -> T:
    """Drive ``coro`` to completion while moving the manual clock forward."""
    task = asyncio.ensure_future(coro)
    waited = 0.0
    while not task.done() and waited < max_s:
        await clock.advance(step_s)
        waited += step_s
    return await task


def health(link: MavLink) -> LinkHealth:
    """The link's health now (a call, so the type checker does not carry narrowing across awaits)."""
    return link.health


async def _connected(clock: ManualClock, peer: Peer, link: MavLink) -> None:
    await clock.advance(0.02)  # our first heartbeat tells the peer where we are
    peer.heartbeat()
    await run(clock, link.wait_autopilot(2.0))
    peer.start_heartbeats(clock)


def _pose(stamp_s: float, reset_counter: int = 0) -> PoseOut:
    T_ned_body = np.eye(4)
    T_ned_body[:3, 3] = [1.0, 2.0, -1.5]
    cov = np.diag([0.01, 0.02, 0.03, 0.001, 0.002, 0.003])
    cov[0, 1] = cov[1, 0] = 0.005
    return PoseOut(stamp_s, T_ned_body, cov, np.array([0.1, 0.0, 0.0]), np.eye(3) * 0.01, reset_counter)


@pytest.fixture
async def clock_peer() -> Any:
    clock = ManualClock(1000.0)
    peer = Peer(now_s=clock.now)
    await peer.start()
    yield clock, peer
    peer.close()


async def test_heartbeat_identity_and_detection(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        assert health(link) is LinkHealth.CONNECTED
        peer.system_id = 1
        await _connected(clock, peer, link)
        await clock.advance(3.0, step_s=0.05)
        hbs = [r for r in peer.of_type("HEARTBEAT")]
        assert 3 <= len(hbs) <= 5  # 1 Hz
        hb = hbs[-1].msg
        assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 197)
        s = link.state
        assert s.autopilot == "ardupilot" and s.mode == "STABILIZE" and health(link) is LinkHealth.AUTOPILOT_OK
        requested = {int(r.msg.param1) for r in peer.of_type("COMMAND_LONG") if r.msg.command == 511}
        assert {mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU} <= requested


async def test_scaled_imu_requested_when_highres_imu_is_refused(clock_peer: Any) -> None:
    clock, peer = clock_peer
    peer.ack_result[mavlink.MAV_CMD_SET_MESSAGE_INTERVAL] = mavlink.MAV_RESULT_UNSUPPORTED
    async with MavLink(LinkConfig(url=peer.url, message_rates_hz={"HIGHRES_IMU": 100.0}), clock=clock) as link:
        await _connected(clock, peer, link)
        await clock.advance(0.5, step_s=0.02)
        asked = [int(r.msg.param1) for r in peer.of_type("COMMAND_LONG") if r.msg.command == 511]
        assert asked == [mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, mavlink.MAVLINK_MSG_ID_SCALED_IMU]
        assert link.stats.interval_requests_failed == 2


async def test_follows_autopilot_system_id(clock_peer: Any) -> None:
    clock, _ = clock_peer
    peer = Peer(now_s=clock.now, system_id=42)
    await peer.start()
    try:
        async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
            await _connected(clock, peer, link)
            await clock.advance(1.1, step_s=0.1)
            assert peer.of_type("HEARTBEAT")[-1].msg.get_srcSystem() == 42
            assert link.state.autopilot_system_id == 42
    finally:
        peer.close()


async def test_commands_ack_deny_timeout_and_retry(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url, command_timeout_s=0.5, command_retries=2), clock=clock) as link:
        await _connected(clock, peer, link)
        await run(clock, link.arm())
        await run(clock, link.set_mode("GUIDED"))
        await clock.advance(1.1, step_s=0.1)
        assert link.state.armed and link.state.mode == "GUIDED"
        peer.ack_result[mavlink.MAV_CMD_NAV_TAKEOFF] = mavlink.MAV_RESULT_DENIED
        with pytest.raises(CommandDenied, match="DENIED"):
            await run(clock, link.takeoff(2.0))
        peer.ack_result[mavlink.MAV_CMD_COMPONENT_ARM_DISARM] = None
        start = clock.now()
        with pytest.raises(CommandTimeout):
            await run(clock, link.disarm())
        assert clock.now() - start == pytest.approx(1.5, abs=0.05)  # 3 attempts x 0.5 s
        tries = [r.msg for r in peer.of_type("COMMAND_LONG") if r.msg.command == 400 and r.msg.param1 == 0.0]
        assert [m.confirmation for m in tries] == [0, 1, 2]
        assert link.stats.command_timeouts == 1 and link.stats.commands_denied == 1
        takeoff = next(r.msg for r in peer.of_type("COMMAND_LONG") if r.msg.command == mavlink.MAV_CMD_NAV_TAKEOFF)
        assert takeoff.param7 == 2.0


async def test_command_ack_addressed_to_another_system_is_not_ours(clock_peer: Any) -> None:
    """With forwarding, a GCS's ARM gets an ACK addressed to the GCS; it must not complete our command."""
    clock, peer = clock_peer
    peer.ack_result[mavlink.MAV_CMD_COMPONENT_ARM_DISARM] = None  # the test answers by hand
    async with MavLink(LinkConfig(url=peer.url, command_timeout_s=5.0), clock=clock) as link:
        await _connected(clock, peer, link)
        task = asyncio.ensure_future(link.arm())
        await clock.advance(0.1, step_s=0.02)
        denied_for_gcs = mavlink.MAV_RESULT_DENIED
        peer.send(peer.mav.command_ack_encode(400, denied_for_gcs, 0, 0, 255, 190))
        await clock.advance(0.1, step_s=0.02)
        assert not task.done()
        peer.send(peer.mav.command_ack_encode(400, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 197))
        await run(clock, task)
        assert link.stats.commands_denied == 0 and link.stats.command_retries == 0


async def test_takeoff_denied_on_retry_but_already_flying_is_success(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url, command_timeout_s=0.5), clock=clock) as link:
        await _connected(clock, peer, link)
        await run(clock, link.set_mode("GUIDED"))
        await clock.advance(0.6, step_s=0.05)
        # first ACK lost; the resent command is refused because the vehicle is already climbing
        peer.ack_script[mavlink.MAV_CMD_NAV_TAKEOFF] = [None, mavlink.MAV_RESULT_FAILED, mavlink.MAV_RESULT_FAILED]
        task = asyncio.ensure_future(link.takeoff(2.0))
        await clock.advance(0.2, step_s=0.02)
        peer.send(peer.mav.extended_sys_state_encode(0, mavlink.MAV_LANDED_STATE_TAKEOFF))
        await run(clock, task)
        assert link.state.landed_state == "takeoff"
        # on the ground a refused retry stays an error
        peer.send(peer.mav.extended_sys_state_encode(0, mavlink.MAV_LANDED_STATE_ON_GROUND))
        peer.ack_script[mavlink.MAV_CMD_NAV_TAKEOFF] = [None, mavlink.MAV_RESULT_FAILED]
        with pytest.raises(CommandDenied):
            await run(clock, link.takeoff(2.0))


async def test_px4_mode_commands(clock_peer: Any) -> None:
    clock, _ = clock_peer
    peer = Peer(now_s=clock.now, autopilot=mavlink.MAV_AUTOPILOT_PX4)
    await peer.start()
    try:
        async with MavLink(
            LinkConfig(url=peer.url, origin_lat_deg=47.0, origin_lon_deg=8.0, origin_alt_m=400.0), clock=clock
        ) as link:
            await _connected(clock, peer, link)
            assert link.state.autopilot == "px4"
            await run(clock, link.land())
            await run(clock, link.hold())
            await run(clock, link.takeoff(3.0))
            cmds = [r.msg for r in peer.of_type("COMMAND_LONG") if r.msg.command in (176, 22)]
            assert [(m.command, m.param2, m.param3) for m in cmds[:2]] == [(176, 4.0, 6.0), (176, 4.0, 3.0)]
            assert cmds[2].command == 22 and cmds[2].param7 == pytest.approx(403.0)
            with pytest.raises(ValueError, match="no mode"):
                await link.set_mode("GUIDED")
    finally:
        peer.close()


async def test_no_autopilot_raises(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        with pytest.raises(LinkError, match="no autopilot"):
            await link.arm()
        with pytest.raises(LinkError, match="no autopilot heartbeat"):
            await run(clock, link.wait_autopilot(0.5))


async def test_velocity_stream_rate_frames_and_stop(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url, setpoint_rate_hz=20.0), clock=clock) as link:
        await _connected(clock, peer, link)
        link.set_velocity_command(VelocityCommand(1.0, -0.5, 0.2, 0.1))
        await clock.advance(1.0, step_s=0.01)
        sp = [r.msg for r in peer.of_type("SET_POSITION_TARGET_LOCAL_NED")]
        assert 19 <= len(sp) <= 22
        assert all(m.type_mask == 0x05C7 and m.coordinate_frame == 1 for m in sp)
        assert (sp[-1].vx, sp[-1].vy, sp[-1].yaw_rate) == (1.0, -0.5, pytest.approx(0.1))
        link.set_velocity_command(None)
        await clock.advance(0.1, step_s=0.01)
        n = len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED"))
        await clock.advance(1.0, step_s=0.05)
        assert len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED")) == n
        with pytest.raises(ValueError):
            link.set_velocity_command((1.0, 0.0, 0.0, 0.0))  # type: ignore[arg-type]


async def test_pose_stamps_timesync_covariance_and_stale(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        await _connected(clock, peer, link)
        assert link.time_offset_s is None and link.pose_time_base is None
        assert not link.send_pose(_pose(clock.now()))  # held until the time base is known
        await clock.advance(0.5, step_s=0.02)  # fast TIMESYNC requests until converged
        assert link.time_offset_s == pytest.approx(peer.time_offset_s, abs=0.02)
        stamp = clock.now() - 0.03
        assert link.send_pose(_pose(stamp, reset_counter=300))
        assert link.pose_time_base == "autopilot"
        assert not link.send_pose(_pose(stamp))  # not newer: never re-sent
        assert not link.send_pose(_pose(clock.now() - 5.0))  # too old
        await clock.advance(0.02)
        vpe = peer.of_type("VISION_POSITION_ESTIMATE")
        assert len(vpe) == 1
        m = vpe[0].msg
        assert m.usec / 1e6 == pytest.approx(stamp + peer.time_offset_s, abs=0.02)
        assert m.reset_counter == 300 % 256
        np.testing.assert_allclose(covariance_from_upper_triangle(m.covariance), _pose(0.0).pose_covariance, rtol=1e-6)
        vse = peer.of_type("VISION_SPEED_ESTIMATE")
        assert len(vse) == 1 and vse[0].msg.usec == m.usec and vse[0].msg.reset_counter == 300 % 256
        st = link.stats
        assert (st.poses_sent, st.poses_rejected_stale, st.poses_held_for_timesync) == (1, 2, 1)


async def test_pose_time_base_falls_back_to_local_without_timesync(clock_peer: Any) -> None:
    clock, peer = clock_peer
    peer.answer_timesync = False
    async with MavLink(LinkConfig(url=peer.url, timesync_fallback_s=2.0), clock=clock) as link:
        await _connected(clock, peer, link)
        await clock.advance(2.1, step_s=0.05)
        stamp = clock.now() - 0.01
        assert link.send_pose(_pose(stamp)) and link.pose_time_base == "local"
        await clock.advance(0.02)
        assert peer.of_type("VISION_POSITION_ESTIMATE")[0].msg.usec == round(stamp * 1e6)


async def test_pose_stamp_base_local_sends_capture_time_on_our_clock(clock_peer: Any) -> None:
    """PX4 converts ``usec`` itself with its own TIMESYNC estimate: with "local" the stamp is our clock's."""
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url, pose_stamp_base="local"), clock=clock) as link:
        await _connected(clock, peer, link)
        stamp = clock.now() - 0.02
        assert link.send_pose(_pose(stamp))  # no wait for TIMESYNC
        await clock.advance(0.5, step_s=0.02)
        assert link.time_offset_s == pytest.approx(peer.time_offset_s, abs=0.02)  # TIMESYNC still runs
        assert link.send_pose(_pose(clock.now()))
        await clock.advance(0.02)
        usecs = [r.msg.usec for r in peer.of_type("VISION_POSITION_ESTIMATE")]
        assert usecs[0] == round(stamp * 1e6) and usecs[1] == round((stamp + 0.02 + 0.5) * 1e6)
        assert link.pose_time_base == "local"
    with pytest.raises(ConfigError):
        LinkConfig(url=peer.url, pose_stamp_base="gps")


async def test_pose_stamp_base_auto_is_local_for_px4(clock_peer: Any) -> None:
    """PX4's receiver runs ``usec`` through its own TIMESYNC offset (sync_stamp): "auto" sends our clock."""
    clock, peer = clock_peer
    peer.autopilot = mavlink.MAV_AUTOPILOT_PX4
    assert LinkConfig(url=peer.url).pose_stamp_base == "auto"
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        assert not link.send_pose(_pose(clock.now()))  # autopilot unknown: undecided
        await _connected(clock, peer, link)
        await clock.advance(0.5, step_s=0.02)
        assert link.time_offset_s == pytest.approx(peer.time_offset_s, abs=0.02)  # converged, yet not used
        stamp = clock.now() - 0.01
        assert link.send_pose(_pose(stamp)) and link.pose_time_base == "local"
        await clock.advance(0.02)
        assert peer.of_type("VISION_POSITION_ESTIMATE")[0].msg.usec == round(stamp * 1e6)


async def test_pose_stamp_base_auto_is_autopilot_for_ardupilot(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        await _connected(clock, peer, link)
        await clock.advance(0.5, step_s=0.02)
        stamp = clock.now() - 0.01
        assert link.send_pose(_pose(stamp)) and link.pose_time_base == "autopilot"
        await clock.advance(0.02)
        usec = peer.of_type("VISION_POSITION_ESTIMATE")[0].msg.usec
        assert usec / 1e6 == pytest.approx(stamp + peer.time_offset_s, abs=0.02)


async def test_pose_stamp_base_explicit_autopilot_overrides_px4_detection(clock_peer: Any) -> None:
    clock, peer = clock_peer
    peer.autopilot = mavlink.MAV_AUTOPILOT_PX4
    async with MavLink(LinkConfig(url=peer.url, pose_stamp_base="autopilot"), clock=clock) as link:
        await _connected(clock, peer, link)
        await clock.advance(0.5, step_s=0.02)
        assert link.send_pose(_pose(clock.now() - 0.01)) and link.pose_time_base == "autopilot"


async def test_landed_state_and_rangefinders_are_requested(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        await _connected(clock, peer, link)
        await clock.advance(1.0, step_s=0.05)
        requested = {int(r.msg.param1) for r in peer.of_type("COMMAND_LONG") if r.msg.command == 511}
        assert {mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR} <= requested


async def test_tlog_on_a_full_disk_does_not_stop_the_link(clock_peer: Any) -> None:
    if not Path("/dev/full").exists():
        pytest.skip("needs /dev/full")
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock, tlog_path="/dev/full") as link:
        imus: list[Any] = []
        link.on_imu(imus.append)
        await _connected(clock, peer, link)
        for i in range(300):  # ~20 kB of tlog: more than one write buffer
            peer.send(peer.mav.highres_imu_encode(i, 0, 0, -9.8, 0.1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
            if i % 50 == 0:
                await _drain(link)
        await _drain(link)
        assert len(imus) == 300  # the reader went on
        await run(clock, link.arm())  # and so did the writer
        assert link.state.armed or peer.armed


async def test_odometry_option(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url, pose_message="odometry"), clock=clock) as link:
        await _connected(clock, peer, link)
        await clock.advance(0.5, step_s=0.02)
        assert link.send_pose(_pose(clock.now()))
        await clock.advance(0.02)
        assert len(peer.of_type("ODOMETRY")) == 1 and not peer.of_type("VISION_POSITION_ESTIMATE")


async def test_answers_timesync_and_sets_origin(clock_peer: Any) -> None:
    clock, peer = clock_peer
    cfg = LinkConfig(url=peer.url, origin_lat_deg=47.1, origin_lon_deg=8.2, origin_alt_m=432.1)
    async with MavLink(cfg, clock=clock) as link:
        await _connected(clock, peer, link)
        peer.send(peer.mav.timesync_encode(0, 777))
        await clock.advance(0.05)
        answers = [r.msg for r in peer.of_type("TIMESYNC") if r.msg.ts1 == 777]
        assert len(answers) == 1 and answers[0].tc1 == pytest.approx(clock.now() * 1e9, abs=0.1e9)
        await clock.advance(3.0, step_s=0.05)
        origins = peer.of_type("SET_GPS_GLOBAL_ORIGIN")
        assert len(origins) == 1  # confirmed by GPS_GLOBAL_ORIGIN: not repeated
        m = origins[0].msg
        assert (m.latitude, m.longitude, m.altitude) == (471000000, 82000000, 432100)
        assert link.state.ekf_origin_set and link.state.ekf_origin_alt_m == pytest.approx(432.1)


async def test_origin_repeated_until_confirmed(clock_peer: Any) -> None:
    clock, peer = clock_peer
    peer.confirm_origin = False
    cfg = LinkConfig(url=peer.url, origin_lat_deg=1.0, origin_lon_deg=2.0, origin_alt_m=3.0)
    async with MavLink(cfg, clock=clock) as link:
        await _connected(clock, peer, link)
        await clock.advance(4.0, step_s=0.1)
        assert len(peer.of_type("SET_GPS_GLOBAL_ORIGIN")) >= 4
        assert not link.state.ekf_origin_set
        peer.confirm_origin = True
        await clock.advance(1.5, step_s=0.1)
        n = len(peer.of_type("SET_GPS_GLOBAL_ORIGIN"))
        assert link.state.ekf_origin_set
        await clock.advance(3.0, step_s=0.1)
        assert len(peer.of_type("SET_GPS_GLOBAL_ORIGIN")) == n  # confirmed: no more repeats


async def test_statustext_chunks_named_value_and_camera(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        await _connected(clock, peer, link)
        text = "vision lost over rack 3, hovering and waiting for re-localization (timeout 10 s)"
        link.statustext(text, "warning")
        link.named_value_float("trk_inl", 0.75)
        link.camera_image_captured(5, "file:///photos/5.jpg")
        await clock.advance(0.05)
        chunks = [r.msg for r in peer.of_type("STATUSTEXT")]
        assert len(chunks) == 2 and chunks[0].id == chunks[1].id != 0
        assert [c.chunk_seq for c in chunks] == [0, 1] and "".join(c.text for c in chunks) == text
        assert chunks[0].severity == mavlink.MAV_SEVERITY_WARNING
        nvf = peer.of_type("NAMED_VALUE_FLOAT")[0].msg
        assert nvf.name == "trk_inl" and nvf.value == pytest.approx(0.75)
        cam = peer.of_type("CAMERA_IMAGE_CAPTURED")[0].msg
        assert cam.image_index == 5 and cam.file_url == "file:///photos/5.jpg" and cam.capture_result == 1
        with pytest.raises(ValueError):
            link.statustext("x", "loud")


async def test_imu_and_message_callbacks_and_bad_callbacks(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        imus: list[Any] = []
        kinds: list[str] = []
        link.on_imu(imus.append)
        link.on_message(lambda m: kinds.append(m.get_type()))
        link.on_message(lambda m: 1 / 0)  # a broken consumer must not hurt the link
        await _connected(clock, peer, link)
        peer.send(peer.mav.highres_imu_encode(10_000_000, 0, 0, -9.8, 0.1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
        await clock.advance(0.05)
        assert len(imus) == 1 and imus[0].gyro_rad_s[0] == pytest.approx(0.1)
        assert "HIGHRES_IMU" in kinds and "HEARTBEAT" in kinds
        assert link.stats.callback_errors >= 2


async def test_garbage_datagrams_are_counted_and_survived(clock_peer: Any) -> None:
    clock, peer = clock_peer
    rng = np.random.default_rng(5)
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        await _connected(clock, peer, link)
        for i in range(500):
            junk = rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8).tobytes()
            if i % 3 == 0:
                junk = b"\xfd" + junk
            peer.send_bytes(junk)
            if i % 20 == 0:
                await _drain(link)
        await _drain(link)
        peer.heartbeat()
        await clock.advance(0.05)
        st = link.stats
        assert st.garbage_bytes + st.bad_frames + st.unknown_messages > 0 and st.parser_errors == 0
        assert link.state.last_autopilot_heartbeat_s == pytest.approx(clock.now(), abs=0.06)
        await run(clock, link.arm())


async def test_mavlink1_autopilot_is_ignored_with_one_warning(
    clock_peer: Any, caplog: pytest.LogCaptureFixture
) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url), clock=clock) as link:
        await clock.advance(0.02)  # our heartbeat tells the peer where we are
        v1 = peer.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 4, 3)
        for _ in range(3):
            peer.send_bytes(bytes(v1.pack(peer.mav, force_mavlink1=True)))
            await clock.advance(0.05)
        assert link.stats.mavlink1_rejected == 3 and link.state.autopilot is None
        warnings = [r for r in caplog.records if "MAVLink 1 frames" in r.getMessage()]
        assert len(warnings) == 1 and warnings[0].levelname == "WARNING"


async def test_silence_then_reconnect(clock_peer: Any) -> None:
    clock, peer = clock_peer
    async with MavLink(LinkConfig(url=peer.url, autopilot_timeout_s=1.0), clock=clock) as link:
        await _connected(clock, peer, link)
        link.set_velocity_command(VelocityCommand(0.5, 0.0, 0.0, 0.0))
        await clock.advance(0.2, step_s=0.02)
        peer.silent = True
        await clock.advance(1.2, step_s=0.05)  # the peer says nothing
        n_sp = len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED"))
        await clock.advance(0.8, step_s=0.05)
        assert len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED")) == n_sp  # no blind streaming
        assert health(link) in (LinkHealth.AUTOPILOT_LOST, LinkHealth.DISCONNECTED)
        assert link.stats.autopilot_lost == 1 and link.stats.reconnects >= 1
        peer.silent = False
        await clock.advance(1.0, step_s=0.05)  # new socket: our heartbeat re-teaches the peer our address
        await clock.advance(0.1, step_s=0.02)
        assert health(link) is LinkHealth.AUTOPILOT_OK
        await run(clock, link.arm())


async def test_tcp_client_reconnects(tmp_path: Path) -> None:
    clock = ManualClock(0.0)
    enc = Encoder(1, 1)
    conns: list[asyncio.StreamWriter] = []
    got = FrameParser()

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        conns.append(writer)
        writer.write(enc.pack(enc.mav.heartbeat_encode(2, 3, 0, 4, 3)))
        while data := await reader.read(4096):
            got.feed(data)

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with MavLink(LinkConfig(url=f"tcp:127.0.0.1:{port}"), clock=clock, tlog_path=tmp_path / "t.tlog") as link:
            await run(clock, link.wait_autopilot(2.0))
            assert link.state.mode == "GUIDED"
            conns[0].close()
            await run(clock, _until(lambda: len(conns) == 2), max_s=5.0)
            assert link.stats.reconnects == 1
            await run(clock, _until(lambda: got.counters.messages > 0), max_s=3.0)
        records = read_tlog(tmp_path / "t.tlog")
        assert len(records) >= 2  # what we sent and what we received
    finally:
        for w in conns:
            w.close()
            with contextlib.suppress(OSError):
                await w.wait_closed()
        server.close()
        await server.wait_closed()


async def _drain(link: MavLink) -> None:
    """Let the loop read every datagram already queued in the kernel (one per loop iteration)."""
    last, quiet = -1, 0
    while quiet < 5:
        await asyncio.sleep(0)
        n = link.stats.bytes_in
        quiet = quiet + 1 if n == last else 0
        last = n


async def _until(cond: Any) -> None:
    while not cond():
        await asyncio.sleep(0)


async def test_tcp_connect_refused_backs_off() -> None:
    clock = ManualClock(0.0)
    sock_server = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
    port = sock_server.sockets[0].getsockname()[1]
    sock_server.close()
    await sock_server.wait_closed()
    async with MavLink(LinkConfig(url=f"tcp:127.0.0.1:{port}", reconnect_max_s=0.4), clock=clock) as link:
        assert health(link) is LinkHealth.DISCONNECTED
        # the first attempt (on enter) and an immediate retry fail; then each retry waits 0.1, 0.2, 0.4, 0.4 s
        for k, backoff_s in enumerate([0.1, 0.2, 0.4, 0.4], start=2):
            await asyncio.wait_for(_until(lambda k=k: link.stats.connect_failures >= k), timeout=10.0)
            await clock.advance(backoff_s * 0.9)
            await asyncio.sleep(0)
            assert link.stats.connect_failures == k  # no retry before the backoff has passed
            await clock.advance(backoff_s * 0.11)
        assert health(link) is LinkHealth.DISCONNECTED


async def test_serial_over_pty() -> None:
    """A pseudo-terminal stands in for the UART; the kernel delivers pty bytes asynchronously, so the
    test waits on events (bounded by a real-time timeout) rather than on the manual clock."""
    clock = ManualClock(0.0)
    master, slave = os.openpty()
    os.set_blocking(master, False)
    loop = asyncio.get_running_loop()
    parser = FrameParser()
    got_frame: asyncio.Future[None] = loop.create_future()

    def readable() -> None:
        with contextlib.suppress(BlockingIOError):
            if parser.feed(os.read(master, 4096)) and not got_frame.done():
                got_frame.set_result(None)

    loop.add_reader(master, readable)
    try:
        async with MavLink(LinkConfig(url=f"serial:{os.ttyname(slave)}:115200"), clock=clock) as link:
            enc = Encoder(1, 1)
            os.write(master, enc.pack(enc.mav.heartbeat_encode(2, 3, 0, 9, 3)))
            await asyncio.wait_for(link.wait_autopilot(10.0), timeout=10.0)  # event-driven; the clock stands still
            assert link.state.mode == "LAND"
            await clock.advance(0.01)
            await asyncio.wait_for(got_frame, timeout=10.0)  # our heartbeat came out of the serial port
            assert link.stats.frames_out > 0
    finally:
        loop.remove_reader(master)
        os.close(master)
        os.close(slave)


async def test_forwarding_to_gcs_endpoint(clock_peer: Any) -> None:
    clock, peer = clock_peer
    gcs = Peer(now_s=clock.now, system_id=255, component_id=190)
    await gcs.start()
    try:
        async with MavLink(
            LinkConfig(url=peer.url, forward_urls=(f"udpout:127.0.0.1:{gcs.port}",)), clock=clock
        ) as link:
            await _connected(clock, peer, link)
            await clock.advance(0.05)
            assert gcs.of_type("HEARTBEAT")  # autopilot's heartbeat forwarded (and ours)
            assert {r.msg.get_srcSystem() for r in gcs.of_type("HEARTBEAT")} >= {1}
            gcs.send(gcs.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, 8, 0, 0, 0))
            await clock.advance(0.05)
            assert link.state.last_gcs_heartbeat_s is not None
            assert any(r.msg.get_srcSystem() == 255 for r in peer.of_type("HEARTBEAT"))  # reached the autopilot
            assert link.stats.forwarded_to_autopilot >= 1 and link.stats.forwarded_to_gcs >= 1
    finally:
        gcs.close()


def test_config_validation() -> None:
    with pytest.raises(ConfigError):
        LinkConfig(url="nope")
    with pytest.raises(ConfigError):
        LinkConfig(url="udpin:0.0.0.0:14550", setpoint_rate_hz=5.0)
    with pytest.raises(ConfigError):
        LinkConfig(url="udpin:0.0.0.0:14550", origin_lat_deg=1.0)
    with pytest.raises(ConfigError):
        LinkConfig(url="udpin:0.0.0.0:14550", message_rates_hz={"NOT_A_MESSAGE": 1.0})
    with pytest.raises(ConfigError):
        LinkConfig(url="udpin:0.0.0.0:14550", autopilot_profile="inav")
