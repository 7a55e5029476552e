"""H.264 encoding (PyAV's libx264) and the RTP/UDP sender to the ground station.

`H264Encoder.encode(bgr)` turns one BGR frame into one Annex B access unit: libx264 with
``preset=ultrafast, tune=zerolatency`` (no B-frames, no look-ahead: each frame comes out at once, the
latency is the encoding time), constant bit rate capped by VBV, a key frame (with SPS and PPS in
band) every `keyframe_interval_s`. `RtpSender` packetizes and sends them over UDP (one socket, never
blocking: a full socket buffer drops the packet and counts it).
"""

from __future__ import annotations

import contextlib
import socket
from fractions import Fraction
from typing import Any

import cv2
import numpy as np

from companion.errors import CompanionError
from drivers.video.rtp import RtpH264Packetizer

__all__ = ["H264Encoder", "RtpSender", "VideoError"]


class VideoError(CompanionError):
    """The video encoder or sender failed (bad size, codec missing, socket)."""


class H264Encoder:
    """libx264 through PyAV: BGR (H, W, 3) uint8 frames of a fixed size in, Annex B access units out."""

    def __init__(self, width: int, height: int, fps: float, bitrate_kbps: int, keyframe_interval_s: float = 1.0,
                 threads: int = 1) -> None:
        import av

        if width % 2 or height % 2 or width < 16 or height < 16:
            raise VideoError(f"video size {width}x{height}: must be even and at least 16x16")
        self.width, self.height = int(width), int(height)
        try:
            ctx: Any = av.CodecContext.create("libx264", "w")
        except Exception as exc:  # an FFmpeg build without libx264
            raise VideoError(f"H.264 encoder libx264 unavailable in PyAV's FFmpeg: {exc}") from exc
        ctx.width, ctx.height = self.width, self.height
        ctx.pix_fmt = "yuv420p"
        rate = max(1, round(fps))
        ctx.time_base = Fraction(1, rate)
        ctx.framerate = Fraction(rate, 1)
        ctx.bit_rate = int(bitrate_kbps) * 1000
        gop = max(1, round(keyframe_interval_s * fps))
        ctx.gop_size = gop
        ctx.thread_count = int(threads)  # one thread: slices in parallel would add latency and compete with vision
        ctx.options = {
            "preset": "ultrafast",
            "tune": "zerolatency",
            "profile": "baseline",
            # VBV one frame deep: the bit rate holds per frame, so no burst waits in the socket
            "x264-params": f"keyint={gop}:min-keyint={gop}:scenecut=0:repeat-headers=1:"
                           f"vbv-maxrate={int(bitrate_kbps)}:vbv-bufsize={max(1, int(bitrate_kbps / rate * 2))}",
        }
        ctx.open()
        self._ctx = ctx
        self._pts = 0
        self._av = av

    def encode(self, bgr: np.ndarray[Any, Any]) -> bytes:
        """One frame in, its access unit out (b"" if the encoder held it back, which zerolatency does not)."""
        if bgr.shape[:2] != (self.height, self.width):
            raise VideoError(f"frame {bgr.shape[1]}x{bgr.shape[0]}: the encoder is {self.width}x{self.height}")
        # one pass, cheaper than FFmpeg's swscale from bgr24
        yuv = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420), dtype=np.uint8)
        frame = self._av.VideoFrame.from_ndarray(yuv, format="yuv420p")
        frame.pts = self._pts
        self._pts += 1
        return b"".join(bytes(p) for p in self._ctx.encode(frame))

    def close(self) -> None:
        ctx, self._ctx = self._ctx, None
        if ctx is not None:
            with contextlib.suppress(Exception):  # closing: nothing to report to
                ctx.encode(None)  # flush


class RtpSender:
    """Sends H.264 access units as RTP over UDP to (host, port); never blocks."""

    def __init__(self, host: str, port: int, mtu_bytes: int = 1200) -> None:
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except OSError as exc:
            raise VideoError(f"video.host: cannot resolve {host!r}: {exc}") from exc
        family, _, _, _, address = infos[0]
        self.address = address
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self.packetizer = RtpH264Packetizer(mtu_bytes=mtu_bytes)
        self.packets_sent = 0
        self.packets_dropped = 0
        self.bytes_sent = 0

    def send(self, access_unit: bytes, stamp_s: float) -> None:
        for pkt in self.packetizer.packetize(access_unit, stamp_s):
            try:
                self._sock.sendto(pkt, self.address)
                self.packets_sent += 1
                self.bytes_sent += len(pkt)
            except OSError:  # buffer full, network down, ICMP refusal: the stream goes on without this packet
                self.packets_dropped += 1

    def close(self) -> None:
        self._sock.close()
