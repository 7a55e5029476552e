"""Issue #15: QGroundControl finds the video by itself (MAVLink camera protocol).

The daemon forwards to a ground station on UDP (``mavlink.gcs_forward``); the "GCS" here is a pymavlink
encoder/parser on a socket, like QGroundControl: it hears the camera component's HEARTBEAT
(MAV_COMP_ID_CAMERA, MAV_TYPE_CAMERA), asks it with MAV_CMD_REQUEST_MESSAGE for CAMERA_INFORMATION and
VIDEO_STREAM_INFORMATION, and gets a COMMAND_ACK and each message: H.264 over RTP/UDP on udp://0.0.0.0:5600.
"""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sitl_tests.daemon_harness import rig
from sitl_tests.video_harness import free_udp_port


def _drain(sock: socket.socket, parser: Any) -> tuple[list[Any], tuple[str, int] | None]:
    msgs: list[Any] = []
    source = None
    while True:
        try:
            data, source = sock.recvfrom(65536)
        except BlockingIOError:
            return msgs, source
        msgs.extend(parser.parse_buffer(data) or [])


async def test_camera_component_answers_request_message(tmp_path: Path) -> None:
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    gcs.setblocking(False)
    gcs_port = gcs.getsockname()[1]
    parser = mavlink.MAVLink(None, 255, 190)
    parser.robust_parsing = True
    overrides = {"mavlink": {"gcs_forward": [f"udpout:127.0.0.1:{gcs_port}"]},
                 "video": {"enabled": True, "port": free_udp_port(), "fps": 10.0}}
    try:
        async with rig(tmp_path, overrides=overrides, start_flight=False) as r:
            await r.advance(2.5)
            msgs, daemon_addr = _drain(gcs, parser)
            cams = [m for m in msgs if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 100]
            assert len(cams) >= 2 and all(m.type == mavlink.MAV_TYPE_CAMERA for m in cams)
            assert daemon_addr is not None
            sysid = cams[0].get_srcSystem()
            replies: dict[int, list[Any]] = {}
            for wanted in (259, 269):
                cmd = mavlink.MAVLink_command_long_message(sysid, 100, 512, 0, float(wanted), 0, 0, 0, 0, 0, 0)
                gcs.sendto(cmd.pack(parser), daemon_addr)
                await r.advance(0.3)
                replies[wanted], _ = _drain(gcs, parser)
            # a request for another component is not ours to answer
            other = mavlink.MAVLink_command_long_message(sysid, 154, 512, 0, 269.0, 0, 0, 0, 0, 0, 0)
            gcs.sendto(other.pack(parser), daemon_addr)
            await r.advance(0.3)
            stray, _ = _drain(gcs, parser)
    finally:
        gcs.close()
    info = [m for m in replies[259] if m.get_type() == "CAMERA_INFORMATION"]
    acks = [m for m in replies[259] if m.get_type() == "COMMAND_ACK" and m.get_srcComponent() == 100]
    assert acks and acks[0].command == 512 and acks[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert acks[0].target_system == 255 and acks[0].target_component == 190
    assert info and info[0].flags & mavlink.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM
    assert info[0].get_srcComponent() == 100 and info[0].get_srcSystem() == sysid
    vsi = [m for m in replies[269] if m.get_type() == "VIDEO_STREAM_INFORMATION"]
    assert vsi, [m.get_type() for m in replies[269]]
    v = vsi[0]
    assert v.type == mavlink.VIDEO_STREAM_TYPE_RTPUDP and v.encoding == mavlink.VIDEO_STREAM_ENCODING_H264
    assert v.uri == f"udp://0.0.0.0:{overrides['video']['port']}"
    assert (v.resolution_h, v.resolution_v) == (240, 160)  # the harness camera's size, scale 1
    assert v.flags & mavlink.VIDEO_STREAM_STATUS_FLAGS_RUNNING
    assert not [m for m in stray if m.get_type() in ("VIDEO_STREAM_INFORMATION", "COMMAND_ACK")
                and m.get_srcComponent() == 100]
