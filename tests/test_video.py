"""Video to the ground station (issue #15): RTP packetization, SDP, the stamp block through H.264, the
overlay's drawing, and the [video] configuration's errors."""

from __future__ import annotations

import itertools
import re
import socket
import struct

import numpy as np
import pytest

from companion.config import parse_config
from companion.config_checks import video_frame_size
from companion.errors import ConfigError
from drivers.video.rtp import RtpH264Packetizer, sdp_text, split_annexb


def _depacketize(packets: list[bytes]) -> tuple[list[bytes], list[int], list[bool]]:
    """NAL units back from RTP packets (single NAL and FU-A), with timestamps and marker bits."""
    nals: list[bytes] = []
    stamps, markers = [], []
    fu = b""
    for p in packets:
        b0, b1, _seq, ts, _ssrc = struct.unpack("!BBHII", p[:12])
        assert b0 == 0x80 and b1 & 0x7F == 96
        stamps.append(ts)
        markers.append(bool(b1 & 0x80))
        payload = p[12:]
        if payload[0] & 0x1F == 28:
            start, end = payload[1] & 0x80, payload[1] & 0x40
            if start:
                fu = bytes(((payload[0] & 0xE0) | (payload[1] & 0x1F),))
            fu += payload[2:]
            if end:
                nals.append(fu)
        else:
            nals.append(payload)
    return nals, stamps, markers


def test_packetizer_round_trip_fragments_and_marker() -> None:
    rng = np.random.default_rng(3)
    big = bytes((0x65,)) + rng.integers(1, 255, 5000, dtype=np.uint8).tobytes()  # IDR slice, needs FU-A
    small = bytes((0x67, 0x42, 0xC0, 0x1E))  # SPS
    au = b"\x00\x00\x00\x01" + small + b"\x00\x00\x01" + big
    assert split_annexb(au) == [small, big]
    pk = RtpH264Packetizer(mtu_bytes=1200, ssrc=7)
    packets = pk.packetize(au, 10.0)
    assert all(len(p) <= 1200 for p in packets) and len(packets) == 1 + 5
    nals, stamps, markers = _depacketize(packets)
    assert nals == [small, big]
    assert len(set(stamps)) == 1 and markers == [False] * (len(packets) - 1) + [True]
    seqs = [struct.unpack("!H", p[2:4])[0] for p in packets]
    assert all((b - a) % 65536 == 1 for a, b in itertools.pairwise(seqs))
    later = pk.packetize(b"\x00\x00\x01" + small, 10.5)
    assert (struct.unpack("!I", later[0][4:8])[0] - stamps[0]) % 2**32 == 45000  # 90 kHz


def test_sdp_describes_h264_rtp() -> None:
    text = sdp_text("127.0.0.1", 5600)
    assert "m=video 5600 RTP/AVP 96" in text and "a=rtpmap:96 H264/90000" in text
    assert "packetization-mode=1" in text and "c=IN IP4 127.0.0.1" in text


def test_stamp_block_survives_h264() -> None:
    av = pytest.importorskip("av")
    from drivers.video import H264Encoder, draw_stamp, read_stamp

    rng = np.random.default_rng(5)
    enc = H264Encoder(320, 240, 15, 300)  # a low bit rate on a noisy picture: the cells must still read
    dec = av.CodecContext.create("h264", "r")
    sent = [int(v) for v in rng.integers(0, 2**32, 12)]
    got: list[int | None] = []
    for ms in sent:
        img = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
        draw_stamp(img, ms)
        for packet in dec.parse(enc.encode(img)):
            got += [read_stamp(f.to_ndarray(format="bgr24")) for f in dec.decode(packet)]
    for packet in dec.parse(None):
        got += [read_stamp(f.to_ndarray(format="bgr24")) for f in dec.decode(packet)]
    assert got == sent[: len(got)] and len(got) >= 11
    noisy = rng.integers(0, 255, (240, 320), dtype=np.uint8)
    assert read_stamp(noisy) is None  # the checksum rejects what is not a stamp


def test_overlay_draws_limbs_where_the_pose_projects_them() -> None:
    from companion.camera import PinholeCamera
    from companion.vision.rack import RackModel
    from companion.vision.rack.limbs import sample_limbs
    from drivers.video import Overlay, draw_overlay

    cam = PinholeCamera(width=320, height=240, fx=280.0, fy=280.0, cx=160.0, cy=120.0)
    model = RackModel.parallel(radii=[0.1, 0.15, 0.1], gaps=[0.2, 0.3], length=6.0)
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down at the rack
    T[:3, 3] = (0.5, 2.0, 2.0)
    image = np.full((240, 320), 90, np.uint8)
    out = draw_overlay(image, Overlay(T_rack_cam=T, pipes=model.pipe_arrays(), rack_ok=True, lines=("pose",)),
                       cam, (640, 480))
    assert out.shape == (480, 640, 3) and image.max() == 90  # a new image, the input untouched
    uv = sample_limbs(T, cam, model.pipe_arrays(), 20, margin_px=4.0).uv * 2.0
    green = (out[..., 1] == 255) & (out[..., 0] == 0)
    px = np.round(uv).astype(int)
    near = [green[v - 1:v + 2, u - 1:u + 2].any() for u, v in px if v < 440]
    assert np.mean(near) > 0.95
    assert green.mean() < 0.05


@pytest.mark.parametrize(("table", "message"), [
    ({"width": 641, "height": 480}, "video.width: must be even"),
    ({"width": 640}, "video.height: video.width and video.height go together"),
    ({"port": 0}, "video.port: must be in [1, 65535]"),
    ({"fps": 0}, "video.fps: must be > 0"),
    ({"bitrate_kbps": 10}, "video.bitrate_kbps: must be in [50, 50000]"),
    ({"camera_component_id": 1}, "video.camera_component_id"),
    ({"size": 3}, "video.size: unknown key"),
])
def test_video_config_errors_name_the_key(table: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match="^" + re.escape(message)):
        parse_config({"video": table})


def test_video_size_from_camera_and_scale() -> None:
    cfg = parse_config({"camera": {"width": 720, "height": 480}, "video": {"scale": 0.45}})
    assert video_frame_size(cfg.video, cfg.camera) == (324, 216)
    assert not cfg.video.enabled and cfg.video.port == 5600  # off for `companion run` unless configured
    tiny = parse_config({"camera": {"width": 100, "height": 60}, "video": {"scale": 0.1}})
    with pytest.raises(ConfigError, match=r"^video\.scale: the stream would be 10x6 px"):
        video_frame_size(tiny.video, tiny.camera)


def test_sim_command_line_turns_the_ground_station_on() -> None:
    from companion.cli import build_parser
    from companion.sim.ground_station import ground_station_overrides

    args = build_parser().parse_args(["sim", "--api-port", "0", "--video-port", "5602"])
    ov = ground_station_overrides(args)
    assert ov["video"]["enabled"] and ov["video"]["port"] == 5602 and ov["api"]["enabled"]
    assert ov["api"]["bind"] == "127.0.0.1" and ov["api"]["port"] == 0
    off = ground_station_overrides(build_parser().parse_args(["sim", "--no-video"]))
    assert not off["video"]["enabled"] and off["api"]["port"] == 8765
    parse_config(off)  # the overrides are a valid configuration


def test_streamer_mailbox_keeps_only_the_newest_frame() -> None:
    """Frames the encoder has not taken yet are replaced (dropped), never queued: the newest one is sent."""
    import threading

    import cv2

    pytest.importorskip("av")
    from drivers.video import Overlay
    from drivers.video.streamer import FrameJob, VideoStreamer

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sink:
        sink.bind(("127.0.0.1", 0))
        streamer = VideoStreamer(size=(160, 120), fps=30.0, bitrate_kbps=300, host="127.0.0.1",
                                 port=sink.getsockname()[1], camera=None)
        got: list[bytes] = []
        done = threading.Event()
        streamer.add_jpeg_listener(lambda seq, jpeg: (got.append(jpeg), done.set()))
        streamer.want_jpeg()
        for k in range(10):  # the thread is not running yet: each one replaces the one before
            streamer.submit(FrameJob(np.full((120, 160), 20 * k, np.uint8), float(k), Overlay()))
        streamer.start()
        try:
            assert done.wait(10.0)
        finally:
            streamer.stop()
    st = streamer.stats()
    assert (st.submitted, st.dropped, st.encoded - st.idle_frames) == (10, 9, 1)
    img = cv2.imdecode(np.frombuffer(got[0], np.uint8), cv2.IMREAD_GRAYSCALE)
    assert abs(float(img.mean()) - 180.0) < 3.0  # the 10th frame (20 * 9), not an older one
    assert st.bytes_sent > 0
