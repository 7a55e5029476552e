"""URL parsing, autopilot profiles, timesync, send queue and state decoding (no sockets)."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import ConfigError, InputError
from companion.geometry import frames
from drivers.mavlink.profiles import ARDUPILOT_COPTER, PX4, profile_for_autopilot, profile_named
from drivers.mavlink.sendqueue import Priority, QueuedFrame, SendQueue
from drivers.mavlink.state import StateTracker, geodetic_from_ned, ned_from_geodetic
from drivers.mavlink.timesync import TimeSync
from drivers.mavlink.url import Endpoint, parse_url
from drivers.mavlink.wire import FrameParser


# ------------------------------------------------------------------ URLs
@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("serial:/dev/ttyAMA0:921600", Endpoint("serial", device="/dev/ttyAMA0", baud=921600)),
        ("udpin:0.0.0.0:14550", Endpoint("udpin", host="0.0.0.0", port=14550)),
        ("udpin://127.0.0.1:0", Endpoint("udpin", host="127.0.0.1", port=0)),
        ("udpout:192.168.1.10:14555", Endpoint("udpout", host="192.168.1.10", port=14555)),
        ("tcp:localhost:5760", Endpoint("tcp", host="localhost", port=5760)),
        ("tcpout:[::1]:5760", Endpoint("tcp", host="::1", port=5760)),
    ],
)
def test_parse_url(url: str, expected: Endpoint) -> None:
    assert parse_url(url) == expected


@pytest.mark.parametrize(
    "url",
    [
        "",
        "udpin",
        "bogus:1.2.3.4:5",
        "udpout:host",
        "udpout:host:0",
        "udpout:host:70000",
        "tcp::5760",
        "serial:/dev/ttyS0:fast",
        "serial::57600",
        "udpout:host:12x",
    ],
)
def test_parse_url_rejects(url: str) -> None:
    with pytest.raises(ConfigError):
        parse_url(url)


def test_endpoint_url_round_trip() -> None:
    for url in ("serial:/dev/ttyUSB0:57600", "udpin:0.0.0.0:14550", "tcp:10.0.0.2:5760"):
        assert parse_url(url).url == url


# ------------------------------------------------------------------ profiles
def test_ardupilot_modes() -> None:
    assert ARDUPILOT_COPTER.custom_mode("guided") == 4
    expected = {"LAND": 9, "BRAKE": 17, "LOITER": 5, "RTL": 6, "POSHOLD": 16}
    assert {k: ARDUPILOT_COPTER.custom_mode(k) for k in expected} == expected
    assert ARDUPILOT_COPTER.set_mode_params("LAND") == (1.0, 9.0, 0.0)
    assert ARDUPILOT_COPTER.mode_name(17) == "BRAKE"
    assert ARDUPILOT_COPTER.mode_name(99) == "UNKNOWN(99)"


def test_px4_modes_pack_main_and_sub() -> None:
    assert PX4.custom_mode("OFFBOARD") == 6 << 16
    assert PX4.custom_mode("AUTO.LAND") == (4 << 16) | (6 << 24)
    assert PX4.set_mode_params("AUTO.LOITER") == (1.0, 4.0, 3.0)
    assert PX4.set_mode_params("POSCTL") == (1.0, 3.0, 0.0)
    assert PX4.mode_name((4 << 16) | (2 << 24)) == "AUTO.TAKEOFF"
    # a non-AUTO main mode with a stray sub mode byte still reads by its main mode
    assert PX4.mode_name((3 << 16) | (1 << 24)) == "POSCTL"


def test_profile_lookup_and_errors() -> None:
    assert profile_for_autopilot(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA) is ARDUPILOT_COPTER
    assert profile_for_autopilot(mavlink.MAV_AUTOPILOT_PX4) is PX4
    assert profile_for_autopilot(mavlink.MAV_AUTOPILOT_GENERIC) is None
    assert profile_named("PX4") is PX4
    with pytest.raises(InputError):
        profile_named("betaflight")
    with pytest.raises(InputError, match="no mode"):
        ARDUPILOT_COPTER.custom_mode("OFFBOARD")


def test_takeoff_param7() -> None:
    assert ARDUPILOT_COPTER.takeoff_param7(2.5, 100.0) == 2.5
    assert PX4.takeoff_param7(2.5, 100.0) == 102.5
    assert math.isnan(PX4.takeoff_param7(2.5, None))
    with pytest.raises(InputError):
        ARDUPILOT_COPTER.takeoff_param7(-1.0, None)


# ------------------------------------------------------------------ timesync
def test_timesync_offset_from_fastest_round_trip() -> None:
    ts = TimeSync()
    offset = 4321.0
    assert ts.offset_s is None and not ts.converged
    for i, (out_delay, back_delay) in enumerate([(0.010, 0.030), (0.002, 0.002), (0.050, 0.001)]):
        t0 = 100.0 + i
        ts1 = ts.request_ns(t0)
        tc1 = round((t0 + out_delay + offset) * 1e9)
        assert ts.add_response(tc1, ts1, t0 + out_delay + back_delay)
    assert ts.converged
    assert ts.offset_s == pytest.approx(offset, abs=1e-6)  # the symmetric 4 ms round trip
    assert ts.to_peer_s(10.0) == pytest.approx(10.0 + offset, abs=1e-6)
    assert ts.to_local_s(offset + 3.0) == pytest.approx(3.0, abs=1e-6)


def test_timesync_ignores_foreign_answers_and_resets_on_jump() -> None:
    ts = TimeSync()
    assert not ts.add_response(5, 12345, 1.0)
    for i in range(3):
        ts1 = ts.request_ns(10.0 + i)
        ts.add_response(round((10.0 + i + 100.0) * 1e9), ts1, 10.0 + i)
    assert ts.offset_s == pytest.approx(100.0)
    ts1 = ts.request_ns(20.0)  # peer rebooted: its clock is now ~0
    ts.add_response(round(0.5 * 1e9), ts1, 20.0)
    assert ts.resets == 1 and not ts.converged and ts.offset_s == pytest.approx(-19.5)


# ------------------------------------------------------------------ send queue
def _qf(tag: bytes, prio: Priority) -> QueuedFrame:
    return QueuedFrame(tag, prio, 0.0)


def test_send_queue_priority_order_and_drop_oldest_pose() -> None:
    q = SendQueue({Priority.POSE: 2})
    q.put(_qf(b"p1", Priority.POSE))
    q.put(_qf(b"p2", Priority.POSE))
    q.put(_qf(b"p3", Priority.POSE))  # drops p1
    q.put(_qf(b"s1", Priority.SETPOINT))
    q.put(_qf(b"c1", Priority.CONTROL))
    out = []
    while (f := q.pop()) is not None:
        out.append(f.data)
    assert out == [b"c1", b"s1", b"p2", b"p3"]
    assert q.dropped[Priority.POSE] == 1 and len(q) == 0


async def test_send_queue_wait_wakes_on_put() -> None:
    q = SendQueue()
    waiter = asyncio.create_task(q.wait())
    await asyncio.sleep(0)
    assert not waiter.done()
    q.put(_qf(b"x", Priority.CONTROL))
    await asyncio.wait_for(waiter, 1.0)


# ------------------------------------------------------------------ state decoding
def _frames(mav: mavlink.MAVLink, *msgs: object) -> list[object]:
    parser = FrameParser()
    out = []
    for m in msgs:
        out += parser.feed(bytes(m.pack(mav)))  # type: ignore[attr-defined]
    return out


def test_state_tracker_units_and_identity() -> None:
    ap = mavlink.MAVLink(None, 7, 1)
    gcs = mavlink.MAVLink(None, 255, 190)
    tracker = StateTracker(origin_deg=(47.0, 8.0, 400.0))
    base = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    q = frames.quaternion_wxyz_from_rotation(frames.rotation_from_euler_zyx(0.1, 0.2, 0.3))
    lat, lon, alt = geodetic_from_ned([3.0, -4.0, -2.0], 47.0, 8.0, 400.0)
    msgs = (
        _frames(ap, ap.heartbeat_encode(2, 3, base, 4, 4))
        + _frames(gcs, gcs.heartbeat_encode(mavlink.MAV_TYPE_GCS, 8, 0, 0, 0))
        + _frames(
            ap,
            ap.attitude_encode(10, 0.1, 0.2, 0.3, 0.01, 0.02, 0.03),
            ap.local_position_ned_encode(10, 1.0, 2.0, -3.0, 0.1, 0.2, -0.3),
            ap.sys_status_encode(0, 0, 0, 0, 12600, 1550, 80, 0, 0, 0, 0, 0, 0),
            ap.distance_sensor_encode(10, 10, 4000, 250, 0, 0, 25, 0),
            ap.highres_imu_encode(123456789, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03, 0, 0, 0, 0, 0, 0, 0, 0),
            ap.scaled_imu_encode(1000, 0, 0, -1000, 10, 0, 0, 0, 0, 0),
            ap.sim_state_encode(
                *q,
                0.1,
                0.2,
                0.3,
                0,
                0,
                0,
                0,
                0,
                0,
                lat,
                lon,
                alt,
                0,
                0,
                0.5,
                0.6,
                0.7,
                round(lat * 1e7),
                round(lon * 1e7),
            ),
        )
    )
    imus = [tracker.apply(m, 50.0) for m in msgs]
    s = tracker.snapshot()
    assert s.autopilot == "ardupilot" and s.mode == "GUIDED" and s.armed
    assert s.autopilot_system_id == 7 and s.last_autopilot_heartbeat_s == 50.0
    assert s.gcs_system_id == 255 and s.last_gcs_heartbeat_s == 50.0
    assert s.attitude_rpy_rad is not None and s.position_ned_m is not None
    np.testing.assert_allclose(s.attitude_rpy_rad, np.array([0.1, 0.2, 0.3]), atol=1e-6)
    assert s.R_ned_body is not None
    np.testing.assert_allclose(s.R_ned_body, frames.rotation_from_euler_zyx(0.1, 0.2, 0.3), atol=1e-6)
    np.testing.assert_allclose(s.position_ned_m, np.array([1.0, 2.0, -3.0]), atol=1e-6)
    assert s.height_m == pytest.approx(3.0)
    assert s.battery_voltage_v == pytest.approx(12.6) and s.battery_current_a == pytest.approx(15.5)
    assert s.battery_remaining_pct == 80.0
    assert s.rangefinder_m == pytest.approx(2.5)
    highres, scaled = imus[-3], imus[-2]
    assert highres is not None and scaled is not None
    np.testing.assert_allclose(highres.accel_m_s2, [0.1, 0.2, -9.8], atol=1e-6)
    np.testing.assert_allclose(scaled.accel_m_s2, [0.0, 0.0, -9.80665], atol=1e-9)
    np.testing.assert_allclose(scaled.gyro_rad_s, [0.01, 0.0, 0.0], atol=1e-9)
    assert highres.stamp_s == 50.0  # no timesync yet: receive time
    assert s.sim_truth is not None
    np.testing.assert_allclose(s.sim_truth.T_ned_body[:3, 3], [3.0, -4.0, -2.0], atol=0.02)
    np.testing.assert_allclose(s.sim_truth.velocity_ned_m_s, [0.5, 0.6, 0.7], atol=1e-6)
    assert not s.ekf_origin_set
    with pytest.raises(ValueError):
        s.position_ned_m[0] = 5.0  # type: ignore[index]  # snapshots are read-only


def test_state_tracker_ignores_other_systems_and_px4_modes() -> None:
    ap = mavlink.MAVLink(None, 1, 1)
    other = mavlink.MAVLink(None, 2, 1)
    tracker = StateTracker()
    for m in _frames(ap, ap.heartbeat_encode(2, 12, 0, (4 << 16) | (6 << 24), 3)):
        tracker.apply(m, 1.0)
    for m in _frames(other, other.heartbeat_encode(2, 3, 128, 4, 3), other.attitude_encode(0, 1, 1, 1, 0, 0, 0)):
        tracker.apply(m, 2.0)
    s = tracker.snapshot()
    assert s.autopilot == "px4" and s.mode == "AUTO.LAND" and not s.armed
    assert s.autopilot_system_id == 1 and s.attitude_rpy_rad is None


def test_ned_geodetic_round_trip() -> None:
    lat, lon, alt = geodetic_from_ned([120.0, -80.0, -15.0], 45.0, 7.0, 300.0)
    np.testing.assert_allclose(ned_from_geodetic(lat, lon, alt, 45.0, 7.0, 300.0), [120.0, -80.0, -15.0], atol=1e-9)


def test_state_tracker_upward_and_downward_rangefinders_and_landed_state() -> None:
    ap = mavlink.MAVLink(None, 1, 1)
    tracker = StateTracker()
    msgs = _frames(
        ap,
        ap.heartbeat_encode(2, 3, 0, 0, 4),
        ap.distance_sensor_encode(10, 10, 4000, 180, 0, 0, 24, 0),  # PITCH_90: up
        ap.distance_sensor_encode(10, 10, 4000, 250, 0, 1, 25, 0),  # PITCH_270: down
        ap.distance_sensor_encode(10, 10, 4000, 90, 0, 2, 0, 0),  # forward: ignored
        ap.extended_sys_state_encode(0, mavlink.MAV_LANDED_STATE_IN_AIR),
    )
    for m in msgs:
        tracker.apply(m, 20.0)
    s = tracker.snapshot()
    assert s.rangefinder_up_m == pytest.approx(1.8) and s.rangefinder_up_stamp_s == 20.0
    assert s.rangefinder_m == pytest.approx(2.5) and s.rangefinder_stamp_s == 20.0
    assert s.landed_state == "in_air"
    tracker.apply(_frames(ap, ap.distance_sensor_encode(11, 10, 4000, 5000, 0, 0, 24, 0))[0], 21.0)  # out of range
    s = tracker.snapshot()
    assert s.rangefinder_up_m is None and s.rangefinder_up_stamp_s == 21.0
    assert s.rangefinder_m == pytest.approx(2.5)
