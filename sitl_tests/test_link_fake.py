"""The MAVLink link against the scripted fake autopilot over real loopback sockets (ManualClock).

Everything the link sends is checked by decoding what the fake received; everything it reports
is checked against the fake's truth.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
from collections.abc import AsyncIterator, Coroutine
from typing import Any, TypeVar

import numpy as np
import pytest

from companion.clock import ManualClock
from companion.control.types import VelocityCommand
from companion.sim.autopilot import FakeAutopilot, FakeAutopilotConfig, Fault, FlightParams
from drivers.mavlink import LinkConfig, LinkHealth, MavLink, PoseOut
from drivers.mavlink.wire import covariance_from_upper_triangle

T = TypeVar("T")
ORIGIN = (47.397742, 8.545594, 488.0)
POSE_COV = np.diag([0.01, 0.01, 0.02, 0.001, 0.001, 0.004])
POSE_COV[0, 1] = POSE_COV[1, 0] = 0.003
POSE_COV[2, 5] = POSE_COV[5, 2] = -0.002


async def drive(clock: ManualClock, coro: Coroutine[Any, Any, T], step_s: float = 0.02, max_s: float = 30.0) -> T:
    """Await ``coro`` while the manual clock moves on in ``step_s`` steps (at most ``max_s``)."""
    task = asyncio.ensure_future(coro)
    t_end = clock.now() + max_s
    while not task.done() and clock.now() < t_end:
        await clock.advance(step_s)
    if not task.done():
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        raise AssertionError(f"{coro!r} did not finish within {max_s} s of clock time")
    return await task


async def advance_until(clock: ManualClock, cond: Any, max_s: float, step_s: float = 0.05) -> None:
    t_end = clock.now() + max_s
    while not cond():
        if clock.now() >= t_end:
            raise AssertionError(f"condition not met within {max_s} s")
        await clock.advance(step_s)


def health(link: MavLink) -> LinkHealth:
    """The link's health now (a call, so the type checker does not carry narrowing across awaits)."""
    return link.health


class PoseFeeder:
    """Streams the fake's true pose as the 'vision' estimate at ``rate_hz`` (stamp = capture time = now)."""

    def __init__(self, link: MavLink, ap: FakeAutopilot, clock: ManualClock, rate_hz: float = 30.0) -> None:
        self.link, self.ap, self.clock, self.period_s = link, ap, clock, 1.0 / rate_hz
        self.reset_counter = 0
        self.sent: list[PoseOut] = []
        self._task: asyncio.Task[None] | None = None

    async def _run(self) -> None:
        while True:
            truth = self.ap.truth
            pose = PoseOut(
                stamp_s=self.clock.now(),
                T_ned_body=truth.T_ned_body,
                pose_covariance=POSE_COV,
                velocity_ned_m_s=truth.velocity_ned_m_s,
                velocity_covariance=np.eye(3) * 0.01,
                reset_counter=self.reset_counter,
            )
            if self.link.send_pose(pose):
                self.sent.append(pose)
            await self.clock.sleep(self.period_s)

    def __enter__(self) -> PoseFeeder:
        self._task = asyncio.ensure_future(self._run())
        return self

    def __exit__(self, *exc: object) -> None:
        if self._task is not None:
            self._task.cancel()


@contextlib.asynccontextmanager
async def fake_and_link(
    profile: str = "ardupilot", link_kwargs: dict[str, Any] | None = None, **fake_kwargs: Any
) -> AsyncIterator[tuple[ManualClock, FakeAutopilot, MavLink]]:
    clock = ManualClock(100.0)
    # The EKF's alignment (~12 s of vision on ArduCopter SITL) is shortened: these tests are about the link.
    fake_kwargs.setdefault("flight", FlightParams(ekf_alignment_s=0.5))
    cfg = FakeAutopilotConfig(profile=profile, listen="udpin:127.0.0.1:0", **fake_kwargs)
    async with FakeAutopilot(cfg, clock=clock) as ap:
        kwargs: dict[str, Any] = {
            "origin_lat_deg": ORIGIN[0],
            "origin_lon_deg": ORIGIN[1],
            "origin_alt_m": ORIGIN[2],
            "request_sim_state": True,
        }
        kwargs.update(link_kwargs or {})
        async with MavLink(LinkConfig(url=ap.url_for_client, **kwargs), clock=clock) as link:
            await drive(clock, link.wait_autopilot(5.0))
            yield clock, ap, link


@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
async def test_finds_the_fake_sets_origin_and_reads_telemetry(profile: str) -> None:
    async with fake_and_link(profile) as (clock, ap, link):
        imus: list[Any] = []
        link.on_imu(imus.append)
        with PoseFeeder(link, ap, clock):  # the fake reports a local position only with vision
            await clock.advance(3.0, step_s=0.02)
        s = link.state
        assert s.autopilot == profile and s.mode == ap.mode and not s.armed
        assert health(link) is LinkHealth.AUTOPILOT_OK
        # origin set once and confirmed
        assert ap.origin_lla == pytest.approx(ORIGIN, abs=1e-6)
        assert s.ekf_origin_set and len(ap.received_of("SET_GPS_GLOBAL_ORIGIN")) <= 2
        # requested streams arrive at (about) the requested rates
        intervals = {
            int(r.fields["param1"]): r.fields["param2"]
            for r in ap.received_of("COMMAND_LONG")
            if r.fields["command"] == 511
        }
        assert len(intervals) >= 7 and link.stats.interval_requests_failed == 0
        assert 150 <= len(imus) <= 320  # HIGHRES_IMU at 100 Hz for ~2.5 s after the request
        # decoded state matches the truth
        truth = ap.truth
        assert s.position_ned_m is not None and s.attitude_rpy_rad is not None
        np.testing.assert_allclose(s.position_ned_m, truth.position_ned_m, atol=0.1)
        assert s.battery_voltage_v is not None
        assert s.battery_voltage_v == pytest.approx(truth.battery_voltage_v, abs=0.2)
        assert s.sim_truth is not None
        np.testing.assert_allclose(s.sim_truth.T_ned_body, truth.T_ned_body, atol=0.02)
        # TIMESYNC converged on the fake's boot-time clock
        assert link.time_offset_s is not None
        assert link.time_offset_s == pytest.approx(-(clock.now() - ap.elapsed_s), abs=0.005)
        # our heartbeat: onboard controller, autopilot's system id, component 197
        hb = [r for r in ap.received_of("HEARTBEAT") if r.src_component == 197]
        assert len(hb) >= 3 and hb[-1].fields["type"] == 18 and hb[-1].src_system == 1


async def test_ardupilot_arm_takeoff_velocity_and_pose_stamps() -> None:
    async with fake_and_link("ardupilot") as (clock, ap, link):
        with PoseFeeder(link, ap, clock) as feeder:
            await clock.advance(1.5, step_s=0.02)  # origin, timesync, fresh vision
            await drive(clock, link.set_mode("GUIDED"))
            await drive(clock, link.arm())
            await drive(clock, link.takeoff(2.0))
            await advance_until(clock, lambda: ap.truth.height_m > 1.9, max_s=10.0)
            assert link.state.armed and link.state.mode == "GUIDED"
            link.set_velocity_command(VelocityCommand(1.0, 0.0, 0.0, 0.0))
            start = ap.truth.position_ned_m
            t0 = clock.now()
            await clock.advance(4.0, step_s=0.02)
            moved = ap.truth.position_ned_m - start
            assert moved[0] > 2.5 and abs(moved[1]) < 0.5
            sps = [r for r in ap.received_of("SET_POSITION_TARGET_LOCAL_NED") if r.time_s >= t0]
            assert len(sps) >= 10 * 4.0 * 0.95  # >= 10 Hz
            assert all(r.fields["type_mask"] == 0x05C7 and r.fields["coordinate_frame"] == 1 for r in sps)
            await drive(clock, link.hold())
            await clock.advance(3.0, step_s=0.02)
            assert ap.mode == "BRAKE" and link.velocity_command is None
            assert np.linalg.norm(ap.truth.velocity_ned_m_s) < 0.2
            await drive(clock, link.land())
            await advance_until(clock, lambda: ap.truth.on_ground, max_s=20.0)
            assert link.state.mode == "LAND"
        check_pose_messages(ap, link, feeder.sent)


async def test_px4_offboard_flight() -> None:
    async with fake_and_link("px4") as (clock, ap, link):
        with PoseFeeder(link, ap, clock):
            await clock.advance(1.5, step_s=0.02)
            await drive(clock, link.arm())
            await drive(clock, link.takeoff(2.5))
            await advance_until(clock, lambda: ap.truth.height_m > 2.3, max_s=10.0)
            link.set_velocity_command(VelocityCommand(0.0, 1.0, 0.0, 0.0))  # stream first (PX4 rule)
            await clock.advance(0.5, step_s=0.02)
            await drive(clock, link.set_mode("OFFBOARD"))
            start = ap.truth.position_ned_m
            await clock.advance(3.0, step_s=0.02)
            assert link.state.mode == "OFFBOARD" and ap.mode == "OFFBOARD"
            assert ap.truth.position_ned_m[1] - start[1] > 2.0
            await drive(clock, link.hold())
            await clock.advance(0.5, step_s=0.05)
            assert ap.mode == "AUTO.LOITER" and link.velocity_command is None
            await drive(clock, link.land())
            await advance_until(clock, lambda: ap.truth.on_ground, max_s=20.0)


def check_pose_messages(ap: FakeAutopilot, link: MavLink, sent: list[PoseOut]) -> None:
    """Decode what the fake received: capture-time stamps, covariance layout, reset counters, no repeats."""
    vpe = ap.received_of("VISION_POSITION_ESTIMATE")
    vse = ap.received_of("VISION_SPEED_ESTIMATE")
    assert len(vpe) >= 0.95 * len(sent) and len(vse) == len(vpe)
    usecs = [r.fields["usec"] for r in vpe]
    assert usecs == sorted(usecs) and len(set(usecs)) == len(usecs)  # each pose once, never re-sent
    for r in vpe[-20:]:
        cov = covariance_from_upper_triangle(r.fields["covariance"])
        np.testing.assert_allclose(cov, POSE_COV, rtol=1e-6, atol=1e-9)
        # Independently of our own helper: row-major upper triangle of (x, y, z, roll, pitch, yaw), so the
        # diagonal sits at 0, 6, 11, 15, 18, 20 (the indices ArduPilot and PX4 read the variances from).
        flat = np.asarray(r.fields["covariance"])
        np.testing.assert_allclose(flat[[0, 6, 11, 15, 18, 20]], np.diag(POSE_COV), rtol=1e-6)
        assert flat[1] == pytest.approx(POSE_COV[0, 1]) and flat[14] == pytest.approx(POSE_COV[2, 5])
        assert np.count_nonzero(flat) == 8  # six variances and the two covariances, nothing else
        assert r.fields["reset_counter"] == 0
        # the stamp is the capture time in the fake's boot-time base: it arrived within 30 ms of capture
        arrival_autopilot_s = r.time_s - (ap.clock.now() - ap.elapsed_s)
        delay_s = arrival_autopilot_s - r.fields["usec"] * 1e-6
        assert -1e-5 <= delay_s < 0.03, delay_s
    offset = link.time_offset_s
    assert offset is not None
    stamps_us = {round((p.stamp_s + offset) * 1e6) for p in sent}
    assert sum(1 for u in usecs[-20:] if any(abs(u - s) <= 2 for s in stamps_us)) == 20


async def test_reset_counter_wraps_on_the_wire() -> None:
    async with fake_and_link("ardupilot") as (clock, ap, link):
        await clock.advance(0.5, step_s=0.02)  # TIMESYNC converges
        for counter in [254, 255, 256, 257, 600]:
            pose = PoseOut(clock.now(), ap.truth.T_ned_body, POSE_COV, reset_counter=counter)
            assert link.send_pose(pose)
            await clock.advance(0.05)
        got = [r.fields["reset_counter"] for r in ap.received_of("VISION_POSITION_ESTIMATE")]
        assert got == [254, 255, 0, 1, 600 % 256]
        assert not ap.received_of("VISION_SPEED_ESTIMATE")  # no velocity given: none sent


async def test_odometry_mode_received_by_fake() -> None:
    async with fake_and_link("px4", link_kwargs={"pose_message": "odometry"}) as (clock, ap, link):
        with PoseFeeder(link, ap, clock, rate_hz=20.0):
            await clock.advance(1.0, step_s=0.02)
        odo = ap.received_of("ODOMETRY")
        assert len(odo) >= 15 and not ap.received_of("VISION_POSITION_ESTIMATE")
        f = odo[-1].fields
        assert (f["frame_id"], f["child_frame_id"]) == (20, 12) and 1 <= f["quality"] <= 100
        assert ap.ekf_healthy


async def test_survives_ten_percent_loss() -> None:
    async with fake_and_link("ardupilot", seed=3) as (clock, ap, link):
        ap.schedule(Fault("message-loss", at_s=0.0, percent=10.0))
        with PoseFeeder(link, ap, clock):
            await clock.advance(1.5, step_s=0.02)
            for _ in range(3):  # commands get through thanks to retries
                await drive(clock, link.set_mode("GUIDED"))
                await drive(clock, link.set_mode("LOITER"))
            await drive(clock, link.set_mode("GUIDED"))
            await drive(clock, link.arm())
            await drive(clock, link.takeoff(1.5))
            await advance_until(clock, lambda: ap.truth.height_m > 1.4, max_s=10.0)
            await clock.advance(2.0, step_s=0.02)
        assert health(link) is LinkHealth.AUTOPILOT_OK
        assert ap.stats["dropped_in"] > 0 and ap.stats["dropped_out"] > 0
        assert link.stats.autopilot_lost == 0
        assert ap.ekf_healthy or len(ap.received_of("VISION_POSITION_ESTIMATE")) > 50


async def test_survives_one_second_of_silence_and_reconnects() -> None:
    async with fake_and_link("ardupilot", link_kwargs={"autopilot_timeout_s": 0.8}) as (clock, ap, link):
        with PoseFeeder(link, ap, clock):
            await clock.advance(1.0, step_s=0.02)
            ap.schedule(Fault("link-loss", at_s=ap.elapsed_s + 0.1, duration_s=1.0))
            await clock.advance(1.0, step_s=0.02)
            assert health(link) is not LinkHealth.AUTOPILOT_OK
            await advance_until(clock, lambda: health(link) is LinkHealth.AUTOPILOT_OK, max_s=5.0)
            assert link.stats.autopilot_lost == 1 and link.stats.reconnects >= 1
            n_before = len(ap.received_of("VISION_POSITION_ESTIMATE"))
            await drive(clock, link.set_mode("GUIDED"))
            await drive(clock, link.arm())
            await clock.advance(1.1, step_s=0.02)  # the next heartbeat reports it
            assert len(ap.received_of("VISION_POSITION_ESTIMATE")) > n_before + 10
            assert link.state.armed


async def test_ten_thousand_garbage_frames() -> None:
    """The link listens (udpin); the fake and a noise source both send to it."""
    clock = ManualClock(100.0)
    rng = np.random.default_rng(11)
    async with MavLink(LinkConfig(url="udpin:127.0.0.1:0"), clock=clock) as link:
        addr = link.local_address
        assert addr is not None
        cfg = FakeAutopilotConfig(listen=f"udpout:127.0.0.1:{addr[1]}", seed=1)
        async with FakeAutopilot(cfg, clock=clock) as ap:
            await drive(clock, link.wait_autopilot(5.0))
            feeder = PoseFeeder(link, ap, clock).__enter__()
            noise = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            noise.setblocking(False)
            try:
                for i in range(10_000):
                    n = int(rng.integers(1, 280))
                    frame = rng.integers(0, 256, size=n, dtype=np.uint8).tobytes()
                    if i % 2 == 0:  # half of them look like MAVLink 2 frames with a plausible header
                        frame = bytes([0xFD, min(n, 255), 0, 0, i % 256]) + frame
                    with contextlib.suppress(BlockingIOError):
                        noise.sendto(frame, addr)
                    if i % 25 == 0:
                        await clock.advance(0.005)
            finally:
                noise.close()
            await clock.advance(1.0, step_s=0.02)
            st = link.stats
            assert st.parser_errors == 0 and st.callback_errors == 0
            assert st.bad_frames + st.garbage_bytes + st.unknown_messages > 1000
            assert health(link) is LinkHealth.AUTOPILOT_OK
            assert link.state.autopilot_system_id == 1  # not confused by the noise
            # replies still go to the fake, not to the noise source
            await drive(clock, link.set_mode("GUIDED"))
            feeder.__exit__()
            assert ap.mode == "GUIDED"
            assert math.isfinite(link.state.last_autopilot_heartbeat_s or math.nan)


async def test_udpin_keeps_answering_the_autopilot_when_another_sender_speaks() -> None:
    """A GCS (valid MAVLink, other system id) sending to our udpin port must not take the link over."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    async def let_the_loop_run() -> None:
        """Let socket I/O flow with the manual clock standing still, until the link hears nothing more."""
        last, quiet = -1, 0
        while quiet < 10:
            await asyncio.sleep(0)
            n = link.stats.bytes_in
            quiet, last = (quiet + 1 if n == last else 0), n

    clock = ManualClock(100.0)
    async with MavLink(LinkConfig(url="udpin:127.0.0.1:0"), clock=clock) as link:
        addr = link.local_address
        assert addr is not None
        cfg = FakeAutopilotConfig(listen=f"udpout:127.0.0.1:{addr[1]}", require_vision=False, seed=1)
        async with FakeAutopilot(cfg, clock=clock) as ap:
            await drive(clock, link.wait_autopilot(5.0))
            gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            gcs.bind(("127.0.0.1", 0))
            gcs.setblocking(False)
            gcs_mav = mavlink.MAVLink(None, 255, 190)
            try:
                await let_the_loop_run()  # the fake's last datagrams are read: the GCS speaks last
                hb = gcs_mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4)
                gcs.sendto(bytes(hb.pack(gcs_mav)), addr)
                await let_the_loop_run()
                assert link.state.last_gcs_heartbeat_s is not None  # heard, and tracked as the GCS
                link.statustext("for the autopilot")  # sent before the autopilot speaks again
                await let_the_loop_run()
                with pytest.raises(BlockingIOError):
                    gcs.recv(65536)  # nothing of ours went to the GCS
                await clock.advance(0.05)
                assert [r.fields["text"] for r in ap.received_of("STATUSTEXT")] == ["for the autopilot"]
                await drive(clock, link.set_mode("GUIDED"))
                assert ap.mode == "GUIDED" and link.stats.command_retries == 0
            finally:
                gcs.close()


async def test_tcp_link_to_the_fake() -> None:
    clock = ManualClock(100.0)
    async with FakeAutopilot(FakeAutopilotConfig(profile="px4", listen="tcpin:127.0.0.1:0"), clock=clock) as ap:
        assert ap.url_for_client.startswith("tcp:")
        async with MavLink(LinkConfig(url=ap.url_for_client), clock=clock) as link:
            await drive(clock, link.wait_autopilot(5.0))
            await clock.advance(1.0, step_s=0.02)
            assert link.state.autopilot == "px4" and link.state.mode == ap.mode
            await drive(clock, link.set_mode("ALTCTL"))
            assert ap.mode == "ALTCTL"
            assert link.stats.interval_requests_failed == 0
