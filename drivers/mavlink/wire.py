"""MAVLink 2 encode/decode on bytes (pymavlink ``ardupilotmega`` dialect), no I/O.

`Encoder` turns typed values into complete frames (its sequence number advances per frame);
`FrameParser` turns a byte stream into decoded messages, counting and skipping garbage, bad
CRCs, truncated frames, MAVLink 1 frames (unless allowed) and unknown message ids. After a
frame that fails to decode, the parser re-synchronises on the next start marker *inside* the
rejected bytes, so a truncated frame does not swallow the valid frame that follows it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.checks import FloatArray
from companion.geometry import frames
from drivers.mavlink.state import PoseOut

__all__ = [
    "MAVLINK",
    "VELOCITY_YAWRATE_TYPE_MASK",
    "Encoder",
    "FrameParser",
    "ParserCounters",
    "covariance_from_upper_triangle",
    "covariance_upper_triangle",
    "statustext_chunks",
    "usec_from_s",
]

MAVLINK = mavlink
STATUSTEXT_LEN = 50
# SET_POSITION_TARGET_LOCAL_NED: ignore position (1|2|4), acceleration (64|128|256) and yaw (1024);
# use velocity and yaw rate.
VELOCITY_YAWRATE_TYPE_MASK = 1 | 2 | 4 | 64 | 128 | 256 | 1024
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8
_UPPER_ROWS, _UPPER_COLS = np.triu_indices(6)


def covariance_upper_triangle(cov: Any) -> list[float]:
    """The 21 upper-triangle entries of a 6x6 covariance, row-major (MAVLink pose covariance layout)."""
    c = np.asarray(cov, dtype=np.float64).reshape(6, 6)
    return [float(x) for x in c[_UPPER_ROWS, _UPPER_COLS]]


def covariance_from_upper_triangle(values: Any) -> FloatArray:
    """Symmetric 6x6 matrix from 21 row-major upper-triangle values (inverse of the above)."""
    v = np.asarray(values, dtype=np.float64).reshape(21)
    c = np.zeros((6, 6))
    c[_UPPER_ROWS, _UPPER_COLS] = v
    c[_UPPER_COLS, _UPPER_ROWS] = v
    return c


def usec_from_s(t_s: float) -> int:
    """Seconds to non-negative integer microseconds (uint64 field)."""
    return max(0, round(t_s * 1e6))


def statustext_chunks(text: str, chunk_id: int) -> list[tuple[bytes, int, int]]:
    """Split ``text`` into STATUSTEXT payloads (text bytes, id, chunk_seq).

    Up to 50 bytes: one chunk with id 0. Longer: chunks of 50 UTF-8 bytes (never splitting a
    character) sharing ``chunk_id`` (1..65535) with chunk_seq 0, 1, ...; a text that fills its
    last chunk exactly gets an empty terminating chunk, since receivers detect the end by a NUL.
    At most 256 chunks (the rest is cut).
    """
    data = text.encode("utf-8", errors="replace")
    if len(data) <= STATUSTEXT_LEN:
        return [(data, 0, 0)]
    if not 1 <= chunk_id <= 65535:
        raise ValueError(f"chunk_id must be in [1, 65535], got {chunk_id}")
    chunks: list[bytes] = []
    start = 0
    while start < len(data) and len(chunks) < 256:
        end = min(start + STATUSTEXT_LEN, len(data))
        while end < len(data) and end > start and (data[end] & 0xC0) == 0x80:
            end -= 1  # do not cut a UTF-8 continuation byte off its character
        chunks.append(data[start:end])
        start = end
    if len(chunks[-1]) == STATUSTEXT_LEN and len(chunks) < 256:
        chunks.append(b"")
    return [(c, chunk_id, seq) for seq, c in enumerate(chunks)]


class Encoder:
    """Builds MAVLink 2 frames as our component (``system_id``, ``component_id``)."""

    def __init__(self, system_id: int, component_id: int) -> None:
        self.mav = mavlink.MAVLink(None, system_id, component_id)
        self.mav.robust_parsing = True

    @property
    def system_id(self) -> int:
        return int(self.mav.srcSystem)

    @system_id.setter
    def system_id(self, value: int) -> None:
        self.mav.srcSystem = int(value)

    @property
    def component_id(self) -> int:
        return int(self.mav.srcComponent)

    def pack(self, msg: Any) -> bytes:
        """Serialize one message with our ids and the next sequence number."""
        buf = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    # -- housekeeping ---------------------------------------------------------------------
    def heartbeat(self, mav_type: int = mavlink.MAV_TYPE_ONBOARD_CONTROLLER) -> bytes:
        return self.pack(
            self.mav.heartbeat_encode(mav_type, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE)
        )

    def timesync(self, tc1_ns: int, ts1_ns: int) -> bytes:
        return self.pack(self.mav.timesync_encode(int(tc1_ns), int(ts1_ns)))

    def command_long(
        self, target: tuple[int, int], command: int, params: tuple[float, ...], confirmation: int = 0
    ) -> bytes:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        if len(p) != 7:
            raise ValueError(f"COMMAND_LONG takes at most 7 params, got {len(params)}")
        return self.pack(self.mav.command_long_encode(target[0], target[1], command, confirmation % 256, *p))

    def set_gps_global_origin(self, target_system: int, lat_deg: float, lon_deg: float, alt_m: float) -> bytes:
        return self.pack(
            self.mav.set_gps_global_origin_encode(
                target_system, round(lat_deg * 1e7), round(lon_deg * 1e7), round(alt_m * 1e3), 0
            )
        )

    # -- pose -----------------------------------------------------------------------------
    def vision_position_estimate(self, pose: PoseOut, usec: int) -> bytes:
        T = pose.T_ned_body
        roll, pitch, yaw = (float(a) for a in frames.euler_zyx_from_rotation(T[:3, :3]))
        return self.pack(
            self.mav.vision_position_estimate_encode(
                usec,
                float(T[0, 3]),
                float(T[1, 3]),
                float(T[2, 3]),
                roll,
                pitch,
                yaw,
                covariance_upper_triangle(pose.pose_covariance),
                pose.reset_counter % 256,
            )
        )

    def vision_speed_estimate(self, pose: PoseOut, usec: int) -> bytes:
        if pose.velocity_ned_m_s is None:
            raise ValueError("vision_speed_estimate needs a pose with velocity_ned_m_s")
        v = pose.velocity_ned_m_s
        if pose.velocity_covariance is None:
            cov = [math.nan] + [0.0] * 8
        else:
            cov = [float(x) for x in pose.velocity_covariance.reshape(9)]
        return self.pack(
            self.mav.vision_speed_estimate_encode(
                usec, float(v[0]), float(v[1]), float(v[2]), cov, pose.reset_counter % 256
            )
        )

    def odometry(self, pose: PoseOut, usec: int) -> bytes:
        """ODOMETRY, frame LOCAL_FRD (our NED), child BODY_FRD: body-frame velocity and rates."""
        T = pose.T_ned_body
        R_ned_body = T[:3, :3]
        q = [float(x) for x in frames.quaternion_wxyz_from_rotation(R_ned_body)]
        nan = math.nan
        vel_cov = np.full((6, 6), nan)
        if pose.velocity_ned_m_s is not None:
            v_body = R_ned_body.T @ pose.velocity_ned_m_s
            if pose.velocity_covariance is not None:
                vel_cov[:3, :3] = R_ned_body.T @ pose.velocity_covariance @ R_ned_body
        else:
            v_body = np.full(3, nan)
        w = pose.angular_rate_body_rad_s if pose.angular_rate_body_rad_s is not None else np.full(3, nan)
        return self.pack(
            self.mav.odometry_encode(
                usec,
                mavlink.MAV_FRAME_LOCAL_FRD,
                mavlink.MAV_FRAME_BODY_FRD,
                float(T[0, 3]),
                float(T[1, 3]),
                float(T[2, 3]),
                q,
                float(v_body[0]),
                float(v_body[1]),
                float(v_body[2]),
                float(w[0]),
                float(w[1]),
                float(w[2]),
                covariance_upper_triangle(pose.pose_covariance),
                covariance_upper_triangle(vel_cov),
                pose.reset_counter % 256,
                mavlink.MAV_ESTIMATOR_TYPE_VISION,
                odometry_quality(pose),
            )
        )

    # -- setpoints ------------------------------------------------------------------------
    def velocity_setpoint(
        self,
        target: tuple[int, int],
        time_boot_ms: int,
        vx_m_s: float,
        vy_m_s: float,
        vz_m_s: float,
        yaw_rate_rad_s: float,
        body_frame: bool = False,
    ) -> bytes:
        frame = MAV_FRAME_BODY_NED if body_frame else MAV_FRAME_LOCAL_NED
        return self.pack(
            self.mav.set_position_target_local_ned_encode(
                time_boot_ms % 2**32,
                target[0],
                target[1],
                frame,
                VELOCITY_YAWRATE_TYPE_MASK,
                0.0,
                0.0,
                0.0,
                vx_m_s,
                vy_m_s,
                vz_m_s,
                0.0,
                0.0,
                0.0,
                0.0,
                yaw_rate_rad_s,
            )
        )

    # -- ground station -------------------------------------------------------------------
    def statustext(self, text: str, severity: int, chunk_id: int) -> list[bytes]:
        return [
            self.pack(self.mav.statustext_encode(severity, chunk, cid, seq))
            for chunk, cid, seq in statustext_chunks(text, chunk_id)
        ]

    def named_value_float(self, time_boot_ms: int, name: str, value: float) -> bytes:
        return self.pack(
            self.mav.named_value_float_encode(time_boot_ms % 2**32, name.encode("ascii", "replace")[:10], float(value))
        )

    def camera_image_captured(
        self,
        time_boot_ms: int,
        time_utc_us: int,
        image_index: int,
        file_url: str,
        success: bool,
        q_wxyz: tuple[float, float, float, float],
        lat_e7: int,
        lon_e7: int,
        alt_mm: int,
        relative_alt_mm: int,
    ) -> bytes:
        return self.pack(
            self.mav.camera_image_captured_encode(
                time_boot_ms % 2**32,
                time_utc_us,
                0,
                lat_e7,
                lon_e7,
                alt_mm,
                relative_alt_mm,
                list(q_wxyz),
                image_index,
                1 if success else 0,
                file_url.encode("utf-8", "replace")[:205],
            )
        )


def odometry_quality(pose: PoseOut) -> int:
    """ODOMETRY quality 0..100 (0 = unknown): given, or 100 at 0 m position sigma falling to 1 at >= 1 m."""
    if pose.quality_pct is not None:
        return int(pose.quality_pct)
    var = np.diag(pose.pose_covariance)[:3]
    if not np.all(np.isfinite(var)) or np.any(var < 0.0):
        return 0
    sigma_m = math.sqrt(float(np.mean(var)))
    return int(min(100, max(1, round(100.0 * (1.0 - sigma_m)))))


@dataclass
class ParserCounters:
    """What a `FrameParser` has seen (cumulative)."""

    bytes_in: int = 0
    messages: int = 0
    garbage_bytes: int = 0
    bad_frames: int = 0
    unknown_messages: int = 0
    mavlink1_rejected: int = 0
    parser_errors: int = 0


class FrameParser:
    """Byte stream to decoded pymavlink messages; never raises on bad input.

    ``accept_mavlink1``: MAVLink 1 frames carry an 8-bit message id whose CRC is the only
    protection against random bytes; off by default (we speak MAVLink 2 only).
    """

    def __init__(self, accept_mavlink1: bool = False) -> None:
        self._mav = mavlink.MAVLink(None, 0, 0)
        self._mav.robust_parsing = True
        self._accept_v1 = accept_mavlink1
        self.counters = ParserCounters()

    @property
    def held_bytes(self) -> int:
        """Bytes the parser keeps in memory between calls (a pending partial frame, < 280)."""
        return len(self._mav.buf)

    def feed(self, data: bytes, datagram: bool = False) -> list[Any]:
        """Decoded, known messages in ``data`` (plus bytes held from earlier calls).

        ``datagram``: ``data`` is one whole UDP datagram, so a frame still incomplete at its end
        never completes; those bytes are re-scanned for frames and then dropped.
        """
        self.counters.bytes_in += len(data)
        out = self._parse(data)
        if datagram:
            mav = self._mav
            while mav.buf_len() > 0:
                pending = bytes(mav.buf[mav.buf_index :])
                self.counters.bad_frames += 1
                mav.buf = bytearray(pending[1:])
                mav.buf_index = 0
                mav.expected_length = mavlink.HEADER_LEN_V1 + 2
                out += self._parse(b"")
        mav = self._mav
        if mav.buf_index:
            # pymavlink only frees consumed bytes when a read ends exactly on a frame boundary; on a
            # byte stream (serial, TCP) that is rare, so drop them here: the buffer stays < 1 frame.
            del mav.buf[: mav.buf_index]
            mav.buf_index = 0
        return out

    def _parse(self, data: bytes) -> list[Any]:
        c = self.counters
        out: list[Any] = []
        mav = self._mav
        try:
            msg = mav.parse_char(data)
            while msg is not None:
                msg_id = msg.get_msgId()
                if msg_id == mavlink.MAVLINK_MSG_ID_BAD_DATA:
                    self._bad(msg)
                elif msg_id == mavlink.MAVLINK_MSG_ID_UNKNOWN:
                    # No CRC check is possible without the id's CRC_EXTRA: it may be noise that
                    # swallowed a real frame, so re-scan its bytes as well.
                    c.unknown_messages += 1
                    self._rescan(bytes(msg.data))
                elif msg.get_msgbuf()[0] != mavlink.PROTOCOL_MARKER_V2 and not self._accept_v1:
                    c.mavlink1_rejected += 1
                else:
                    c.messages += 1
                    out.append(msg)
                msg = mav.parse_char(b"")
        except Exception:  # pymavlink internals: never let a stream of bytes kill the reader
            c.parser_errors += 1
            mav.buf = bytearray()
            mav.buf_index = 0
            mav.expected_length = mavlink.HEADER_LEN_V1 + 2
        return out

    def _bad(self, msg: Any) -> None:
        data = bytes(msg.data)
        if msg.reason == "Bad prefix":
            self.counters.garbage_bytes += len(data)
            return
        self.counters.bad_frames += 1
        self._rescan(data)

    def _rescan(self, data: bytes) -> None:
        """Re-scan a rejected frame from its second byte: a valid frame may start inside it."""
        mav = self._mav
        mav.buf = bytearray(data[1:]) + mav.buf[mav.buf_index :]
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2
