"""Wire-level encode/decode round trips and parser robustness (no sockets)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geometry import frames
from drivers.mavlink.state import PoseOut
from drivers.mavlink.tlog import TlogWriter, read_tlog
from drivers.mavlink.wire import (
    VELOCITY_YAWRATE_TYPE_MASK,
    Encoder,
    FrameParser,
    covariance_from_upper_triangle,
    covariance_upper_triangle,
    statustext_chunks,
)


def _pose(rng: np.random.Generator, reset_counter: int = 0, with_velocity: bool = True) -> PoseOut:
    R = frames.rotation_from_euler_zyx(0.1, -0.2, 2.5)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [1.5, -2.25, -3.0]
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 0.01
    B = rng.normal(size=(3, 3))
    return PoseOut(
        stamp_s=1234.5678,
        T_ned_body=T,
        pose_covariance=cov,
        velocity_ned_m_s=np.array([0.5, -0.25, 0.1]) if with_velocity else None,
        velocity_covariance=B @ B.T * 0.01 if with_velocity else None,
        reset_counter=reset_counter,
    )


def _decode_one(data: bytes) -> Any:
    msgs = FrameParser().feed(data)
    assert len(msgs) == 1
    return msgs[0]


def test_covariance_upper_triangle_layout_is_row_major() -> None:
    cov = np.arange(36, dtype=float).reshape(6, 6)
    cov = cov + cov.T
    values = covariance_upper_triangle(cov)
    assert len(values) == 21
    # first row complete (6 values), then the second row from the diagonal (5 values), ...
    assert values[:6] == list(cov[0, :])
    assert values[6:11] == list(cov[1, 1:])
    assert values[11:15] == list(cov[2, 2:])
    assert values[-1] == cov[5, 5]
    np.testing.assert_array_equal(covariance_from_upper_triangle(values), cov)


def test_vision_position_estimate_round_trip(rng: np.random.Generator) -> None:
    pose = _pose(rng, reset_counter=7)
    enc = Encoder(1, 197)
    msg = _decode_one(enc.vision_position_estimate(pose, 987654321))
    assert msg.get_type() == "VISION_POSITION_ESTIMATE"
    assert (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 197)
    assert msg.usec == 987654321
    np.testing.assert_allclose(np.array([msg.x, msg.y, msg.z]), np.array([1.5, -2.25, -3.0]), atol=1e-6)
    R = frames.rotation_from_euler_zyx(msg.roll, msg.pitch, msg.yaw)
    np.testing.assert_allclose(R, pose.T_ned_body[:3, :3], atol=1e-6)
    cov = covariance_from_upper_triangle(msg.covariance)
    np.testing.assert_allclose(cov, pose.pose_covariance, rtol=1e-6, atol=1e-9)  # float32 on the wire
    assert msg.reset_counter == 7


def test_unknown_covariance_entries_stay_nan_and_only_there(rng: np.random.Generator) -> None:
    pose = _pose(rng)
    cov = np.array(pose.pose_covariance)
    cov[3:, 3:] = np.nan  # attitude unknown
    pose2 = PoseOut(pose.stamp_s, pose.T_ned_body, cov)
    msg = _decode_one(Encoder(1, 197).vision_position_estimate(pose2, 1))
    back = covariance_from_upper_triangle(msg.covariance)
    assert np.array_equal(np.isnan(back), np.isnan(cov))


@pytest.mark.parametrize(("counter", "wire"), [(0, 0), (255, 255), (256, 0), (257, 1), (1000, 1000 % 256)])
def test_reset_counter_wraps_to_uint8(rng: np.random.Generator, counter: int, wire: int) -> None:
    pose = _pose(rng, reset_counter=counter)
    enc = Encoder(1, 197)
    assert _decode_one(enc.vision_position_estimate(pose, 1)).reset_counter == wire
    assert _decode_one(enc.vision_speed_estimate(pose, 1)).reset_counter == wire
    assert _decode_one(enc.odometry(pose, 1)).reset_counter == wire


def test_reset_counter_must_be_non_negative(rng: np.random.Generator) -> None:
    pose = _pose(rng)
    with pytest.raises(ValueError, match="reset_counter"):
        PoseOut(pose.stamp_s, pose.T_ned_body, pose.pose_covariance, reset_counter=-1)


def test_vision_speed_estimate_round_trip(rng: np.random.Generator) -> None:
    pose = _pose(rng)
    msg = _decode_one(Encoder(1, 197).vision_speed_estimate(pose, 55))
    assert msg.usec == 55
    np.testing.assert_allclose(np.array([msg.x, msg.y, msg.z]), np.array([0.5, -0.25, 0.1]), atol=1e-6)
    assert pose.velocity_covariance is not None
    np.testing.assert_allclose(np.reshape(msg.covariance, (3, 3)), pose.velocity_covariance, rtol=1e-6)


def test_odometry_frames_body_velocity_and_nan_for_unknown(rng: np.random.Generator) -> None:
    pose = _pose(rng)
    msg = _decode_one(Encoder(1, 197).odometry(pose, 77))
    assert msg.frame_id == mavlink.MAV_FRAME_LOCAL_FRD
    assert msg.child_frame_id == mavlink.MAV_FRAME_BODY_FRD
    R = frames.rotation_from_quaternion_wxyz(np.array(msg.q))
    np.testing.assert_allclose(R, pose.T_ned_body[:3, :3], atol=1e-6)
    assert pose.velocity_ned_m_s is not None
    v_body = np.array([msg.vx, msg.vy, msg.vz])
    np.testing.assert_allclose(R @ v_body, pose.velocity_ned_m_s, atol=1e-6)
    assert all(math.isnan(x) for x in (msg.rollspeed, msg.pitchspeed, msg.yawspeed))
    vel_cov = covariance_from_upper_triangle(msg.velocity_covariance)
    assert np.all(np.isfinite(vel_cov[:3, :3])) and np.all(np.isnan(vel_cov[3:, 3:]))
    assert 1 <= msg.quality <= 100


def test_velocity_setpoint_type_mask_and_frames() -> None:
    enc = Encoder(1, 197)
    msg = _decode_one(enc.velocity_setpoint((1, 1), 1500, 1.0, -2.0, 0.5, 0.25))
    assert msg.type_mask == VELOCITY_YAWRATE_TYPE_MASK == 0x05C7
    assert msg.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED
    assert (msg.vx, msg.vy, msg.vz, msg.yaw_rate) == (1.0, -2.0, 0.5, 0.25)
    body = _decode_one(enc.velocity_setpoint((1, 1), 1500, 1.0, 0.0, 0.0, 0.0, body_frame=True))
    assert body.coordinate_frame == mavlink.MAV_FRAME_BODY_NED == 8


def test_sequence_numbers_advance_and_wrap() -> None:
    enc = Encoder(3, 197)
    seqs = [FrameParser().feed(enc.heartbeat())[0].get_seq() for _ in range(300)]
    assert seqs[:3] == [0, 1, 2] and seqs[256] == 0


def test_statustext_short_is_single_chunk_with_id_zero() -> None:
    assert statustext_chunks("hello", 9) == [(b"hello", 0, 0)]
    assert statustext_chunks("x" * 50, 9) == [(b"x" * 50, 0, 0)]


def test_statustext_long_text_is_chunked_and_reassembles() -> None:
    text = "".join(chr(ord("a") + i % 26) for i in range(123))
    chunks = statustext_chunks(text, 42)
    assert [c[2] for c in chunks] == [0, 1, 2]
    assert all(c[1] == 42 for c in chunks)
    enc = Encoder(1, 197)
    parser = FrameParser()
    msgs = [parser.feed(f)[0] for f in enc.statustext(text, mavlink.MAV_SEVERITY_WARNING, 42)]
    assert "".join(m.text for m in msgs) == text
    assert {m.id for m in msgs} == {42} and all(m.severity == mavlink.MAV_SEVERITY_WARNING for m in msgs)


def test_statustext_exact_multiple_gets_terminating_chunk() -> None:
    chunks = statustext_chunks("y" * 100, 1)
    assert [len(c[0]) for c in chunks] == [50, 50, 0]


def test_statustext_never_splits_a_utf8_character() -> None:
    text = "é" * 60  # 120 bytes
    chunks = statustext_chunks(text, 3)
    assert b"".join(c[0] for c in chunks).decode("utf-8") == text
    for data, _, _ in chunks:
        data.decode("utf-8")  # each chunk is valid on its own


def test_parser_survives_seeded_garbage_and_still_decodes(rng: np.random.Generator) -> None:
    enc = Encoder(1, 1)
    parser = FrameParser()
    good = 0
    for _ in range(2000):
        garbage = rng.integers(0, 256, size=int(rng.integers(1, 80)), dtype=np.uint8).tobytes()
        if rng.random() < 0.3:
            garbage = b"\xfd" + garbage  # looks like a frame start
        good += sum(1 for m in parser.feed(garbage) if m.get_type() == "HEARTBEAT")
        good += sum(1 for m in parser.feed(enc.heartbeat()) if m.get_type() == "HEARTBEAT")
    good += sum(1 for m in parser.feed(bytes(300)) if m.get_type() == "HEARTBEAT")  # flush a pending frame
    c = parser.counters
    assert c.parser_errors == 0
    assert c.garbage_bytes > 0 and c.bad_frames > 0
    # Resynchronisation inside rejected frames keeps nearly every valid frame of the stream.
    assert good >= 1990


def test_datagram_mode_recovers_frames_after_a_bogus_start(rng: np.random.Generator) -> None:
    enc = Encoder(1, 1)
    parser = FrameParser()
    good = 0
    for _ in range(1000):
        garbage = b"\xfd" + rng.integers(0, 256, size=int(rng.integers(1, 40)), dtype=np.uint8).tobytes()
        datagram = garbage + enc.heartbeat()
        good += sum(1 for m in parser.feed(datagram, datagram=True) if m.get_type() == "HEARTBEAT")
    assert good == 1000
    assert parser.counters.parser_errors == 0


def test_truncated_frame_does_not_swallow_the_next_one() -> None:
    enc = Encoder(1, 1)
    frame = enc.heartbeat()
    parser = FrameParser()
    msgs = parser.feed(frame[:7] + enc.heartbeat())
    assert [m.get_type() for m in msgs] == ["HEARTBEAT"]
    assert parser.counters.bad_frames + parser.counters.unknown_messages >= 1


def test_wrong_crc_is_counted_and_skipped() -> None:
    enc = Encoder(1, 1)
    frame = bytearray(enc.heartbeat())
    frame[-1] ^= 0xFF
    parser = FrameParser()
    assert parser.feed(bytes(frame)) == []
    assert parser.counters.bad_frames == 1
    assert len(parser.feed(enc.heartbeat())) == 1


def test_unknown_message_id_is_counted() -> None:
    enc = Encoder(1, 1)
    frame = bytearray(enc.heartbeat())
    frame[7:10] = (60001).to_bytes(3, "little")  # an id no dialect defines
    parser = FrameParser()
    assert parser.feed(bytes(frame)) == []
    assert parser.counters.unknown_messages == 1


def test_mavlink1_frames_rejected_unless_allowed() -> None:
    mav1 = mavlink.MAVLink(None, 1, 1)
    frame = bytes(mav1.heartbeat_encode(2, 3, 0, 0, 0).pack(mav1, force_mavlink1=True))
    strict = FrameParser()
    assert strict.feed(frame) == [] and strict.counters.mavlink1_rejected == 1
    assert len(FrameParser(accept_mavlink1=True).feed(frame)) == 1


def test_split_frames_across_reads() -> None:
    enc = Encoder(1, 1)
    data = b"".join(enc.heartbeat() for _ in range(5))
    parser = FrameParser()
    got = []
    for i in range(0, len(data), 3):
        got += parser.feed(data[i : i + 3])
    assert len(got) == 5


def test_byte_stream_split_anywhere_decodes_everything_with_bounded_memory(rng: np.random.Generator) -> None:
    """Serial/TCP reads end at arbitrary bytes; consumed bytes must not pile up in the parser."""
    enc = Encoder(1, 1)
    pose = _pose(rng)
    one_round = [enc.heartbeat(), enc.vision_position_estimate(pose, 1), enc.velocity_setpoint((1, 1), 0, 1, 2, 3, 4)]
    data = b"".join(f for _ in range(400) for f in one_round)
    parser = FrameParser()
    got, held_max, start = 0, 0, 0
    while start < len(data):
        end = start + int(rng.integers(1, 200))
        got += len(parser.feed(data[start:end]))
        held_max = max(held_max, parser.held_bytes)
        start = end
    assert got == 1200
    assert held_max < 280  # at most one partial MAVLink 2 frame


def test_tlog_records_are_mavproxy_format(tmp_path: object) -> None:
    from pathlib import Path

    path = Path(str(tmp_path)) / "flight.tlog"
    t = iter([1.0, 2.5])
    writer = TlogWriter(path, wall_time_s=lambda: next(t))
    enc = Encoder(1, 197)
    frames_out = [enc.heartbeat(), enc.statustext("hi", 6, 1)[0]]
    for f in frames_out:
        writer.write(f)
    writer.close()
    records = read_tlog(path)
    assert [r[0] for r in records] == [1_000_000, 2_500_000]
    assert [r[1] for r in records] == frames_out
    raw = path.read_bytes()
    assert raw[:8] == (1_000_000).to_bytes(8, "big")
    # pymavlink's own tlog reader agrees
    from pymavlink import mavutil

    mlog = mavutil.mavlink_connection(str(path))
    types = []
    while (m := mlog.recv_match()) is not None:
        types.append(m.get_type())
    mlog.close()
    assert types == ["HEARTBEAT", "STATUSTEXT"]


def test_tlog_write_error_stops_the_log_without_raising() -> None:
    """A full disk (here /dev/full) must not raise into the link's reader or writer."""
    from pathlib import Path

    if not Path("/dev/full").exists():
        pytest.skip("needs /dev/full")
    writer = TlogWriter("/dev/full", wall_time_s=lambda: 1.0)
    frame = Encoder(1, 197).heartbeat()
    for _ in range(2000):  # far more than one write buffer
        writer.write(frame)
    writer.close()
    assert writer.failed and isinstance(writer.error, OSError)
    assert writer.records < 2000
