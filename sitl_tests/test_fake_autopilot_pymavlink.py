"""The fake autopilot against a raw pymavlink client over real loopback sockets (UDP and TCP), on a ManualClock.

The client is deliberately independent of `drivers.mavlink`: plain sockets plus pymavlink's
MAVLink 2 codec, so these tests check the fake's wire behaviour on its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.clock import ManualClock
from companion.errors import ConfigError, InputError
from companion.sim.autopilot import (
    BatteryParams,
    DrydenConfig,
    FakeAutopilot,
    FakeAutopilotConfig,
    Fault,
    FlightParams,
)

G = 9.80665
ORIGIN = (47.397742, 8.545594, 488.0)  # ArduPilot sets home (needed to arm) once the EKF has an origin
FLAG_CUSTOM = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)


class RawClient:
    """A minimal MAVLink 2 client on a non-blocking socket: `send(msg)`, `poll()`, `of(type)`."""

    def __init__(self, url: str, clock: ManualClock, system_id: int = 1, component_id: int = 197) -> None:
        scheme, host, port = url.split(":")
        if scheme == "udpout":
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.connect((host, int(port)))
        else:
            self.sock = socket.create_connection((host, int(port)))
        self.sock.setblocking(False)
        self.clock = clock
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.messages: list[tuple[float, Any]] = []  # (clock time of arrival, message)
        self.bad_frames = 0
        # Read as bytes arrive (the ManualClock lets loopback I/O flow between its wake-ups).
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self.sock.fileno(), self.poll)

    def send(self, msg: Any) -> None:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self.sock.send(buf)

    def send_bytes(self, data: bytes) -> None:
        self.sock.send(data)

    def poll(self) -> None:
        while True:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            if not data:
                return
            for msg in self.parser.parse_buffer(data) or []:
                if msg.get_type() == "BAD_DATA":
                    self.bad_frames += 1
                else:
                    self.messages.append((self.clock.now(), msg))

    def of(self, msg_type: str, since_s: float = -math.inf, src_system: int | None = 1) -> list[Any]:
        self.poll()
        return [
            m
            for t, m in self.messages
            if m.get_type() == msg_type and t >= since_s and (src_system is None or m.get_srcSystem() == src_system)
        ]

    def times_of(self, msg_type: str, src_system: int = 1) -> list[float]:
        self.poll()
        return [t for t, m in self.messages if m.get_type() == msg_type and m.get_srcSystem() == src_system]

    def heartbeat(self) -> None:
        self.send(
            self.mav.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
        )

    def command(self, command: int, *params: float) -> None:
        p = [*params, *([0.0] * (7 - len(params)))]
        self.send(self.mav.command_long_encode(1, 1, command, 0, *p))

    def acks(self, command: int) -> list[int]:
        return [m.result for m in self.of("COMMAND_ACK") if m.command == command]

    def vision(self, T_ned_body: np.ndarray, usec: int) -> None:
        from companion.geometry import frames

        roll, pitch, yaw = frames.euler_zyx_from_rotation(T_ned_body[:3, :3])
        x, y, z = T_ned_body[:3, 3]
        cov = [0.01] + [0.0] * 20
        self.send(self.mav.vision_position_estimate_encode(usec, x, y, z, roll, pitch, yaw, cov, 0))

    def velocity(self, vx: float, vy: float, vz: float, yaw_rate: float = 0.0, frame: int = 1) -> None:
        mask = 0b0000_0101_1100_0111  # ignore position, acceleration, yaw; use velocity + yaw rate
        self.send(
            self.mav.set_position_target_local_ned_encode(
                0, 1, 1, frame, mask, 0, 0, 0, vx, vy, vz, 0, 0, 0, 0, yaw_rate
            )
        )

    def close(self) -> None:
        self._loop.remove_reader(self.sock.fileno())
        self.sock.close()


@contextlib.asynccontextmanager
async def session(clock: ManualClock, **config: Any) -> AsyncIterator[tuple[FakeAutopilot, RawClient]]:
    config.setdefault("seed", 1)
    async with FakeAutopilot(FakeAutopilotConfig(**config), clock=clock) as ap:
        client = RawClient(ap.url_for_client, clock)
        try:
            client.heartbeat()
            await clock.advance(0.01)
            yield ap, client
        finally:
            client.close()


@contextlib.asynccontextmanager
async def streaming(clock: ManualClock, period_s: float, send: Any) -> AsyncIterator[None]:
    """Run `send()` every `period_s` of clock time while the block runs."""

    async def loop() -> None:
        while True:
            send()
            await clock.sleep(period_s)

    task = asyncio.create_task(loop())
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def vision_sender(ap: FakeAutopilot, client: RawClient) -> Any:
    return lambda: client.vision(ap.truth.T_ned_body, int(ap.clock.now() * 1e6))


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(start_s=500.0)


@pytest.mark.parametrize(
    ("profile", "autopilot", "custom_mode"),
    [("ardupilot", mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0), ("px4", mavlink.MAV_AUTOPILOT_PX4, 3 << 16)],
)
async def test_udp_telemetry_streams_at_their_rates(
    clock: ManualClock, profile: str, autopilot: int, custom_mode: int
) -> None:
    async with session(clock, profile=profile) as (ap, client):
        start = clock.now()
        await clock.advance(2.0)
        hb = client.of("HEARTBEAT")
        assert 2 <= len(hb) <= 3
        assert hb[-1].autopilot == autopilot and hb[-1].type == mavlink.MAV_TYPE_QUADROTOR
        assert hb[-1].custom_mode == custom_mode
        assert hb[-1].base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert not hb[-1].base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        for name in ("SYS_STATUS", "BATTERY_STATUS", "EKF_STATUS_REPORT", "EXTENDED_SYS_STATE"):
            assert len(client.of(name, since_s=start + 0.5)) >= 1, name
        assert 19 <= len(client.of("ATTITUDE", since_s=start + 0.01)) <= 21
        assert 19 <= len(client.of("SIM_STATE", since_s=start + 0.01)) <= 21
        rng = client.of("DISTANCE_SENSOR")[-1]
        assert rng.orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_270 and rng.current_distance == rng.min_distance
        assert client.of("EXTENDED_SYS_STATE")[-1].landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
        battery = client.of("SYS_STATUS")[-1]
        assert battery.voltage_battery == pytest.approx(16800, abs=60)
        # No position source yet (non-GPS configuration): no LOCAL_POSITION_NED, EKF in constant-position mode.
        assert client.of("LOCAL_POSITION_NED") == []
        assert client.of("EKF_STATUS_REPORT")[-1].flags & mavlink.EKF_CONST_POS_MODE
        sim = client.of("SIM_STATE")[-1]
        assert (sim.q1, sim.q2, sim.q3, sim.q4) == pytest.approx((1.0, 0.0, 0.0, 0.0), abs=1e-9)
        assert sim.lat_int == round(ap.config.reference_lla[0] * 1e7)


async def test_message_interval_drives_highres_imu_at_200_hz(clock: ManualClock) -> None:
    async with session(clock) as (_, client):
        client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 5000.0)
        await clock.advance(0.02)
        assert client.acks(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL) == [mavlink.MAV_RESULT_ACCEPTED]
        start = clock.now()
        await clock.advance(1.0)
        imu = client.of("HIGHRES_IMU", since_s=start + 1e-6)
        assert 199 <= len(imu) <= 201
        acc = np.array([[m.xacc, m.yacc, m.zacc] for m in imu])
        gyro = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in imu])
        # At rest: specific force -g on body z plus bias, gyro = bias; noise present but small.
        assert acc.mean(axis=0) == pytest.approx([0.0, 0.0, -G], abs=0.2)
        assert np.all(acc.std(axis=0) > 0.005) and np.all(acc.std(axis=0) < 0.1)
        assert np.all(np.abs(gyro.mean(axis=0)) < 0.02)
        stamps = np.diff([m.time_usec for m in imu])
        assert np.all(stamps == 5000)
        # GET_MESSAGE_INTERVAL reports it; -1 turns it off; unknown ids fail.
        client.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU)
        client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, -1.0)
        client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 9999.0, 1000.0)
        await clock.advance(0.05)
        assert client.of("MESSAGE_INTERVAL")[-1].interval_us == 5000
        assert client.acks(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL)[-2:] == [
            mavlink.MAV_RESULT_ACCEPTED,
            mavlink.MAV_RESULT_DENIED,  # ArduCopter SITL: DENIED for an id it cannot stream
        ]
        off = clock.now()
        await clock.advance(0.5)
        assert client.of("HIGHRES_IMU", since_s=off + 0.01) == []
        # Unknown commands are UNSUPPORTED; REQUEST_MESSAGE sends the message once.
        client.command(mavlink.MAV_CMD_DO_DIGICAM_CONTROL)
        client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        await clock.advance(0.05)
        assert client.acks(mavlink.MAV_CMD_DO_DIGICAM_CONTROL) == [mavlink.MAV_RESULT_UNSUPPORTED]
        assert client.acks(mavlink.MAV_CMD_REQUEST_MESSAGE) == [mavlink.MAV_RESULT_ACCEPTED]
        assert len(client.of("AUTOPILOT_VERSION")) == 1


async def test_arming_is_denied_without_a_fresh_vision_pose(clock: ManualClock) -> None:
    # The EKF's alignment (~12 s, as on ArduCopter SITL) is shortened: this test is about vision freshness.
    async with session(clock, origin_lla=ORIGIN, flight=FlightParams(ekf_alignment_s=0.1)) as (ap, client):
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        await clock.advance(0.1)
        assert client.acks(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == [mavlink.MAV_RESULT_FAILED]
        assert any(m.text == "Arm: VisOdom: not healthy" for m in client.of("STATUSTEXT"))  # ArduCopter SITL
        assert not ap.armed and not ap.ready_to_arm
        await clock.advance(1.0)  # SYS_STATUS at 1 Hz
        assert not client.of("SYS_STATUS")[-1].onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
        async with streaming(clock, 1 / 30, vision_sender(ap, client)):
            await clock.advance(0.2)
            assert ap.ekf_healthy and ap.ready_to_arm
            client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
            await clock.advance(1.1)
            assert client.acks(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)[-1] == mavlink.MAV_RESULT_ACCEPTED
            assert ap.armed
            assert client.of("HEARTBEAT")[-1].base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            assert not client.of("EKF_STATUS_REPORT")[-1].flags & mavlink.EKF_CONST_POS_MODE
            assert len(client.of("LOCAL_POSITION_NED")) >= 5
            assert len(ap.received_of("VISION_POSITION_ESTIMATE")) >= 30
            client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
            await clock.advance(0.05)
            assert not ap.armed
        # ArduCopter: the EKF dead-reckons on (still healthy) but VisOdom fails 300 ms after the last pose.
        await clock.advance(0.35)
        assert ap.ekf_healthy
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        await clock.advance(0.05)
        assert client.acks(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)[-1] == mavlink.MAV_RESULT_FAILED


async def test_guided_takeoff_velocity_and_the_3_s_timeout_in_body_frame(clock: ManualClock) -> None:
    # Heading east: a BODY_NED forward velocity flies east.
    async with session(  # noqa: SIM117 - the sender needs ap
        clock, start_yaw_rad=math.pi / 2, origin_lla=ORIGIN, flight=FlightParams(ekf_alignment_s=0.05)
    ) as (ap, client):
        async with streaming(clock, 1 / 30, vision_sender(ap, client)):
            await clock.advance(0.1)
            client.command(mavlink.MAV_CMD_DO_SET_MODE, FLAG_CUSTOM, 4.0)
            client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
            client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0)
            await clock.advance(0.05)
            assert ap.mode == "GUIDED" and ap.armed
            assert client.acks(mavlink.MAV_CMD_NAV_TAKEOFF) == [mavlink.MAV_RESULT_ACCEPTED]
            await clock.advance(1.0)
            assert client.of("EXTENDED_SYS_STATE")[-1].landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF
            await clock.advance(6.5)  # ArduCopter SITL: the climb starts ~3.2 s after NAV_TAKEOFF
            assert ap.truth.height_m == pytest.approx(2.0, abs=0.1)
            assert client.of("EXTENDED_SYS_STATE")[-1].landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
            assert client.of("DISTANCE_SENSOR")[-1].current_distance == pytest.approx(200, abs=5)
            east0 = ap.truth.position_ned_m[1]
            client.velocity(1.0, 0.0, 0.0, frame=mavlink.MAV_FRAME_BODY_NED)
            await clock.advance(2.5)
            truth = ap.truth
            assert truth.velocity_ned_m_s == pytest.approx([0.0, 1.0, 0.0], abs=0.05)
            assert truth.T_ned_body[:3, 0] == pytest.approx([0.0, 1.0, 0.0], abs=0.05)  # nose east
            lpn = client.of("LOCAL_POSITION_NED")[-1]
            assert lpn.vy == pytest.approx(1.0, abs=0.05)
            await clock.advance(1.0)  # 3.5 s after the only setpoint: stopping
            await clock.advance(1.5)
            assert np.linalg.norm(ap.truth.velocity_ned_m_s) < 0.05
            # 3 s at 1 m/s: the ramp-up lag and the braking distance cancel.
            assert ap.truth.position_ned_m[1] - east0 == pytest.approx(3.0, abs=0.2)
            assert ap.mode == "GUIDED"
            # Landing: LAND descends, disarms on the ground.
            client.command(mavlink.MAV_CMD_NAV_LAND)
            await clock.advance(7.0)  # ArduCopter SITL: 0.53 m/s, disarmed 2.2 s after touchdown
            assert ap.mode == "LAND" and not ap.armed and ap.truth.on_ground
            hb = client.of("HEARTBEAT")[-1]
            assert hb.custom_mode == 9 and not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED


async def test_px4_offboard_stream_rules_over_tcp(clock: ManualClock) -> None:
    async with session(clock, profile="px4", listen="tcpin:127.0.0.1:0") as (ap, client):
        assert ap.url_for_client.startswith("tcp:127.0.0.1:")
        async with streaming(clock, 1 / 30, vision_sender(ap, client)):
            await clock.advance(0.1)
            client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
            client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, math.nan)
            await clock.advance(0.05)
            assert ap.mode == "AUTO.TAKEOFF"
            await clock.advance(5.0)
            assert ap.mode == "AUTO.LOITER"
            assert client.of("HEARTBEAT")[-1].custom_mode == (4 << 16) | (3 << 24)
            assert ap.truth.height_m == pytest.approx(2.5, abs=0.1)
            # OFFBOARD without a setpoint stream: refused.
            client.command(mavlink.MAV_CMD_DO_SET_MODE, FLAG_CUSTOM, 6.0)
            await clock.advance(0.05)
            assert client.acks(mavlink.MAV_CMD_DO_SET_MODE) == [mavlink.MAV_RESULT_TEMPORARILY_REJECTED]
            async with streaming(clock, 0.1, lambda: client.velocity(0.0, -1.0, 0.0)):
                await clock.advance(0.5)
                client.command(mavlink.MAV_CMD_DO_SET_MODE, FLAG_CUSTOM, 6.0)
                await clock.advance(3.0)
                assert client.acks(mavlink.MAV_CMD_DO_SET_MODE)[-1] == mavlink.MAV_RESULT_ACCEPTED
                assert ap.mode == "OFFBOARD"
                assert client.of("HEARTBEAT")[-1].custom_mode == 6 << 16
                assert ap.truth.velocity_ned_m_s == pytest.approx([0.0, -1.0, 0.0], abs=0.05)
            stopped = clock.now()
            await clock.advance(0.4)
            assert ap.mode == "OFFBOARD"
            await clock.advance(0.3)
            assert ap.mode == "AUTO.LOITER"
            assert any("offboard" in m.text for m in client.of("STATUSTEXT", since_s=stopped))
            await clock.advance(3.0)
            assert np.linalg.norm(ap.truth.velocity_ned_m_s) < 0.1


async def test_timesync_origin_set_once_and_recorded_messages(clock: ManualClock) -> None:
    async with session(clock) as (ap, client):
        await clock.advance(1.0)
        client.send(client.mav.timesync_encode(0, 123456789))
        await clock.advance(0.01)
        reply = client.of("TIMESYNC")[-1]
        assert reply.ts1 == 123456789
        assert reply.tc1 == pytest.approx(ap.elapsed_s * 1e9, abs=2e7)
        client.send(client.mav.set_gps_global_origin_encode(1, 473977420, 85455940, 488000, 0))
        await clock.advance(0.01)
        client.send(client.mav.set_gps_global_origin_encode(1, 100000000, 100000000, 0, 0))
        await clock.advance(0.01)
        origins = client.of("GPS_GLOBAL_ORIGIN")
        assert len(origins) == 2
        assert all((o.latitude, o.longitude, o.altitude) == (473977420, 85455940, 488000) for o in origins)
        assert ap.origin_lla == pytest.approx((47.397742, 8.545594, 488.0))
        # A recorded message carries its decoded fields and the exact bytes on the wire.
        client.send(
            client.mav.vision_position_estimate_encode(42_000_000, 1.0, 2.0, -3.0, 0.1, 0.2, 0.3, [0.5] * 21, 7)
        )
        await clock.advance(0.01)
        rec = ap.received_of("VISION_POSITION_ESTIMATE")[-1]
        assert rec.fields["usec"] == 42_000_000 and rec.fields["reset_counter"] == 7
        assert rec.fields["covariance"] == pytest.approx([0.5] * 21)
        assert (rec.src_system, rec.src_component) == (1, 197)
        decoded = mavlink.MAVLink(None).decode(bytearray(rec.raw))
        assert decoded.x == 1.0 and decoded.usec == 42_000_000
        assert rec.time_s == pytest.approx(clock.now(), abs=0.02)
        assert [r.type for r in ap.received][:1] == ["HEARTBEAT"]


async def test_received_records_are_capped_keeping_the_newest(clock: ManualClock) -> None:
    async with session(clock, max_records=32) as (ap, client):
        for i in range(100):
            client.send(client.mav.timesync_encode(0, 1000 + i))
            if i % 10 == 9:
                await clock.advance(0.01)
        await clock.advance(0.02)
        assert ap.stats["received"] == 101  # the session's heartbeat and 100 TIMESYNC
        kept = [r.fields["ts1"] for r in ap.received_of("TIMESYNC")]
        assert 30 <= len(ap.received) <= 32
        assert kept == list(range(1100 - len(kept), 1100))  # oldest dropped, order kept
    with pytest.raises(ConfigError):
        FakeAutopilotConfig(max_records=0)


async def test_link_loss_silences_both_directions(clock: ManualClock) -> None:
    async with session(clock) as (ap, client):
        ap.schedule(Fault("link-loss", at_s=ap.elapsed_s + 1.0, duration_s=1.0))
        start = clock.now()
        await clock.advance(0.5)
        async with streaming(clock, 0.1, client.heartbeat):
            await clock.advance(3.0)
        times = np.array(client.times_of("ATTITUDE")) - start
        assert not np.any((times > 1.0 + 1e-6) & (times < 2.0 - 1e-6))
        assert np.sum(times < 1.0) >= 9 and np.sum(times > 2.0) >= 14
        heard = np.array([r.time_s for r in ap.received_of("HEARTBEAT")]) - start
        assert not np.any((heard > 1.0 + 1e-6) & (heard < 2.0 - 1e-6))
        assert np.sum(heard > 2.0) >= 10
        assert ap.stats["dropped_in"] >= 9


async def test_message_loss_latency_and_corruption(clock: ManualClock) -> None:
    async with session(clock) as (ap, client):
        t0 = ap.elapsed_s
        ap.schedule(Fault("message-loss", at_s=t0, duration_s=10.0, percent=50.0))
        start = clock.now()
        async with streaming(clock, 0.05, client.heartbeat):
            await clock.advance(10.0)
        got = len(client.of("ATTITUDE", since_s=start + 0.01))
        assert 30 <= got <= 70  # 100 sent at 10 Hz, half lost
        heard = len([r for r in ap.received_of("HEARTBEAT") if r.time_s > start])
        assert 70 <= heard <= 130  # 200 sent, half lost of each direction
        # Latency (outgoing only): a TIMESYNC reply needs 200 ms.
        ap.schedule(Fault("latency", at_s=ap.elapsed_s, duration_s=2.0, ms=200.0, direction="out"))
        client.send(client.mav.timesync_encode(0, 1))
        await clock.advance(0.15)
        assert [m for m in client.of("TIMESYNC") if m.ts1 == 1] == []
        await clock.advance(0.1)
        assert len([m for m in client.of("TIMESYNC") if m.ts1 == 1]) == 1
        await clock.advance(2.0)
        # Corruption: every outgoing frame fails its CRC at the client.
        ap.schedule(Fault("corrupt", at_s=ap.elapsed_s, duration_s=1.0, percent=100.0))
        before_bad = client.bad_frames
        mark = clock.now()
        await clock.advance(0.99)
        assert client.of("ATTITUDE", since_s=mark + 0.001) == []
        assert client.bad_frames - before_bad >= 9
        await clock.advance(0.5)
        assert len(client.of("ATTITUDE", since_s=mark + 1.0)) >= 4


async def test_garbage_bytes_never_stop_the_autopilot(clock: ManualClock) -> None:
    rng = np.random.default_rng(5)
    async with session(clock) as (ap, client):
        for _ in range(300):
            client.send_bytes(rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8).tobytes())
        client.send_bytes(b"\xfd\x09\x00")  # a truncated frame start: may swallow the next frame
        # asyncio reads one datagram per loop iteration: small clock steps let the backlog drain.
        await clock.advance(0.5, step_s=0.002)
        assert ap.stats["parse_errors"] >= 100
        # A garbage length byte can make the parser wait for up to 280 bytes: it resyncs within ~13 frames.
        for ts1 in range(100, 120):
            client.send(client.mav.timesync_encode(0, ts1))
            await clock.advance(0.02)
        assert [m.ts1 for m in client.of("TIMESYNC")][-5:] == [115, 116, 117, 118, 119]
        assert ap.stats["parse_errors"] > 0
        assert len(client.of("ATTITUDE")) >= 3


async def test_command_rejection_fault(clock: ManualClock) -> None:
    async with session(clock, require_vision=False) as (ap, client):
        ap.schedule(Fault("command-reject", at_s=ap.elapsed_s, duration_s=1.0, commands=[400]))
        ap.schedule(Fault("command-reject", at_s=ap.elapsed_s + 1.0, duration_s=1.0, result="timeout"))
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        client.command(mavlink.MAV_CMD_DO_SET_MODE, FLAG_CUSTOM, 4.0)
        await clock.advance(1.05)
        assert client.acks(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == [mavlink.MAV_RESULT_DENIED]
        assert client.acks(mavlink.MAV_CMD_DO_SET_MODE) == [mavlink.MAV_RESULT_ACCEPTED]
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        await clock.advance(0.5)
        assert client.acks(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == [mavlink.MAV_RESULT_DENIED]  # no answer at all
        assert not ap.armed
        await clock.advance(0.5)
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        await clock.advance(0.05)
        assert client.acks(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)[-1] == mavlink.MAV_RESULT_ACCEPTED
        assert ap.armed


async def test_battery_faults_and_battery_failsafe(clock: ManualClock) -> None:
    async with session(clock, require_vision=False) as (ap, client):
        t = ap.elapsed_s
        ap.schedule(Fault("battery-sag", at_s=t + 1.5, duration_s=1.0, voltage_v=14.2))
        await clock.advance(1.2)
        assert client.of("SYS_STATUS")[-1].voltage_battery > 16000
        await clock.advance(1.0)
        assert client.of("SYS_STATUS")[-1].voltage_battery == 14200
        await clock.advance(1.0)
        assert client.of("SYS_STATUS")[-1].voltage_battery > 16000
        # Fly, then the battery turns critical: charge state CRITICAL and the vehicle lands.
        client.command(mavlink.MAV_CMD_DO_SET_MODE, FLAG_CUSTOM, 4.0)
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0)
        await clock.advance(5.0)
        hover_current = client.of("BATTERY_STATUS")[-1].current_battery
        assert hover_current > 1500  # > 15 A in hover (cA)
        ap.schedule(Fault("battery-critical", at_s=ap.elapsed_s))
        await clock.advance(1.0)
        status = client.of("BATTERY_STATUS")[-1]
        assert status.charge_state == mavlink.MAV_BATTERY_CHARGE_STATE_CRITICAL and status.battery_remaining == 5
        assert ap.mode == "LAND"
        assert client.of("HEARTBEAT")[-1].system_status == mavlink.MAV_STATE_CRITICAL
        await clock.advance(8.0)
        assert ap.truth.on_ground and not ap.armed


async def test_battery_status_carries_more_than_ten_cells_in_the_extension(clock: ManualClock) -> None:
    """A 12S pack: cells 1..10 in `voltages`, 11..12 in `voltages_ext` (0 = no cell); the sum is the pack."""
    async with session(clock, battery=BatteryParams(cells=12)) as (ap, client):
        await clock.advance(1.1)
        status = client.of("BATTERY_STATUS")[-1]
        assert len(set(status.voltages)) == 1 and status.voltages[0] == pytest.approx(4200, abs=5)
        assert list(status.voltages_ext) == [status.voltages[0]] * 2 + [0, 0]
        total_mv = sum(status.voltages) + sum(status.voltages_ext)
        assert total_mv == pytest.approx(client.of("SYS_STATUS")[-1].voltage_battery, abs=12)
        assert total_mv / 1000.0 == pytest.approx(ap.truth.battery_voltage_v, abs=0.02)
    with pytest.raises(InputError):
        BatteryParams(cells=15)


async def test_gcs_heartbeats_stop_on_gcs_loss(clock: ManualClock) -> None:
    async with session(clock, gcs_heartbeat=True) as (ap, client):
        ap.schedule(Fault("gcs-loss", at_s=ap.elapsed_s + 2.5))
        start = clock.now()
        await clock.advance(5.0)
        gcs = [t - start for t in client.times_of("HEARTBEAT", src_system=255)]
        assert len(gcs) >= 2 and max(gcs) < 2.5
        hb = client.of("HEARTBEAT", src_system=255)[-1]
        assert hb.type == mavlink.MAV_TYPE_GCS and hb.get_srcComponent() == 190
        assert max(client.times_of("HEARTBEAT")) - start > 4.0  # the autopilot's own continue


async def test_ceiling_fault_reports_and_stops_the_climb(clock: ManualClock) -> None:
    async with session(clock, require_vision=False, faults=(Fault("ceiling", at_s=0.0, height_m=1.5),)) as (ap, client):
        client.command(mavlink.MAV_CMD_DO_SET_MODE, FLAG_CUSTOM, 4.0)
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0)
        await clock.advance(5.0)
        assert ap.truth.height_m == pytest.approx(1.4, abs=0.01)
        up = [m for m in client.of("DISTANCE_SENSOR") if m.orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_90]
        assert up and up[-1].current_distance == pytest.approx(20, abs=2)


async def test_same_seed_same_flight_in_gusty_wind() -> None:
    async def fly(seed: int) -> np.ndarray:
        c = ManualClock(start_s=500.0)
        wind = DrydenConfig(w20_m_s=6.0, from_rad=1.0)
        async with session(c, seed=seed, require_vision=False, wind=wind, rates_hz={"SIM_STATE": 50.0}) as (_, client):
            client.command(mavlink.MAV_CMD_DO_SET_MODE, FLAG_CUSTOM, 4.0)
            client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
            client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0)
            await c.advance(6.0)
            return np.array([[m.vn, m.ve, m.vd, m.roll, m.pitch] for m in client.of("SIM_STATE")])

    a, b, c = await fly(3), await fly(3), await fly(4)
    assert a.shape == b.shape and np.array_equal(a, b)
    assert a.shape == c.shape and not np.array_equal(a, c)
    # The gusts move and tilt the hovering vehicle.
    assert np.abs(a[-100:, :2]).max() > 0.05 and np.abs(a[-100:, 3:]).max() > 0.01


async def test_set_mode_message_and_vision_reject_failsafe(clock: ManualClock) -> None:
    fast_align = FlightParams(ekf_alignment_s=0.05)
    async with (
        session(clock, origin_lla=ORIGIN, flight=fast_align) as (ap, client),
        streaming(clock, 1 / 30, vision_sender(ap, client)),
    ):
        await clock.advance(0.1)
        client.send(client.mav.set_mode_encode(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4))
        client.send(client.mav.set_mode_encode(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 42))
        await clock.advance(0.05)
        # ArduPilot answers SET_MODE with a COMMAND_ACK whose command is the message id (11).
        assert client.acks(mavlink.MAVLINK_MSG_ID_SET_MODE) == [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED]
        assert ap.mode == "GUIDED"
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0)
        await clock.advance(7.0)
        # The autopilot stops accepting vision. ArduCopter SITL: the EKF dead-reckons for 7.1 s, then
        # FS_EKF says "EKF variance" and switches to LAND at 7.95 s.
        ap.schedule(Fault("vision-reject", at_s=ap.elapsed_s))
        await clock.advance(7.8)
        assert ap.mode == "GUIDED" and ap.armed
        await clock.advance(0.3)
        assert ap.mode == "LAND"
        assert any(m.text == "EKF Failsafe: changed to LAND Mode" for m in client.of("STATUSTEXT"))
        assert not client.of("EKF_STATUS_REPORT")[-1].flags & mavlink.EKF_POS_HORIZ_REL


async def test_sim_state_and_highres_imu_are_consistent_with_the_truth(clock: ManualClock) -> None:
    from companion.geometry import frames
    from companion.sim.autopilot import ImuNoise

    quiet = ImuNoise(0.0, 0.0, 0.0, 0.0)
    async with session(clock, require_vision=False, imu_noise=quiet, origin_lla=(45.0, 9.0, 100.0)) as (ap, client):
        client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 5000.0)
        client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_SIM_STATE, 5000.0)
        client.command(mavlink.MAV_CMD_DO_SET_MODE, FLAG_CUSTOM, 4.0)
        client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0)
        await clock.advance(7.0)  # ArduCopter SITL: the climb starts ~3.2 s after NAV_TAKEOFF
        v0 = ap.truth.velocity_ned_m_s
        mark = clock.now()
        async with streaming(clock, 0.1, lambda: client.velocity(1.5, -1.0, -0.3, yaw_rate=0.4)):
            await clock.advance(1.5)
        truth = ap.truth
        # SIM_STATE is the true pose: quaternion, Euler angles and position agree.
        sim = client.of("SIM_STATE")[-1]
        R_quat = frames.rotation_from_quaternion_wxyz(np.array([sim.q1, sim.q2, sim.q3, sim.q4]))
        R_euler = frames.rotation_from_euler_zyx(sim.roll, sim.pitch, sim.yaw)
        assert np.allclose(R_quat, R_euler, atol=1e-5)
        assert np.allclose(R_quat, truth.T_ned_body[:3, :3], atol=1e-4)
        north_m = (sim.lat_int / 1e7 - 45.0) * math.pi / 180.0 * 6378137.0
        assert north_m == pytest.approx(truth.position_ned_m[0], abs=0.02)
        assert sim.alt == pytest.approx(100.0 + truth.height_m, abs=0.01)
        assert [sim.vn, sim.ve, sim.vd] == pytest.approx(list(truth.velocity_ned_m_s), abs=1e-4)
        # Noise-free HIGHRES_IMU integrated with the true attitude gives the true velocity change.
        imu = [m for t, m in client.messages if m.get_type() == "HIGHRES_IMU" and t > mark + 1e-6]
        att = [m for t, m in client.messages if m.get_type() == "SIM_STATE" and t > mark + 1e-6]
        assert len(imu) == len(att) == 300
        dv = np.zeros(3)
        for m_imu, m_att in zip(imu, att, strict=True):
            R = frames.rotation_from_quaternion_wxyz(np.array([m_att.q1, m_att.q2, m_att.q3, m_att.q4]))
            dv += (R @ np.array([m_imu.xacc, m_imu.yacc, m_imu.zacc]) + np.array([0.0, 0.0, G])) * 0.005
        assert dv == pytest.approx(truth.velocity_ned_m_s - v0, abs=0.03)
        assert np.linalg.norm(truth.velocity_ned_m_s - v0) > 1.0
