"""H.264 over RTP (RFC 6184) on bytes, no I/O: Annex B access units -> RTP packets, and the SDP that describes them.

`RtpH264Packetizer.packetize(access_unit, stamp_s)` splits an Annex B access unit (NAL units behind
start codes, as libx264 writes them) into RTP packets: a NAL unit that fits the MTU goes whole
(single NAL unit packet), a larger one in FU-A fragments; the marker bit ends the access unit. The
timestamp runs at 90 kHz from the capture time. `sdp_text` describes the stream for receivers that
need an SDP file (FFmpeg / PyAV, VLC, ffplay; QGroundControl does not: it listens on UDP 5600 for
H.264 with payload type 96). SPS and PPS travel in-band before every key frame, so a receiver that
joins late starts at the next key frame.
"""

from __future__ import annotations

import random
import struct

__all__ = ["PAYLOAD_TYPE", "RtpH264Packetizer", "sdp_text", "split_annexb"]

PAYLOAD_TYPE = 96  # dynamic; QGroundControl's and most receivers' default for H.264
_CLOCK_HZ = 90_000
_FU_A = 28


def split_annexb(data: bytes) -> list[bytes]:
    """The NAL units of an Annex B byte stream (start codes 00 00 01 / 00 00 00 01 removed)."""
    nals: list[bytes] = []
    n = len(data)
    i = data.find(b"\x00\x00\x01")
    while 0 <= i < n:
        start = i + 3
        j = data.find(b"\x00\x00\x01", start)
        end = n if j < 0 else j
        nal = data[start:end]
        if j >= 0 and nal.endswith(b"\x00"):  # the leading zero of the next 4-byte start code
            nal = nal.rstrip(b"\x00")
        if nal:
            nals.append(nal)
        i = j
    return nals


class RtpH264Packetizer:
    """RTP packets of H.264 access units (one SSRC, sequence numbers and 90 kHz timestamps of its own)."""

    def __init__(self, mtu_bytes: int = 1200, payload_type: int = PAYLOAD_TYPE, ssrc: int | None = None) -> None:
        if mtu_bytes < 100:
            raise ValueError(f"mtu_bytes: must be >= 100, got {mtu_bytes}")
        self.max_payload = mtu_bytes - 12
        self.payload_type = int(payload_type)
        self.ssrc = random.getrandbits(32) if ssrc is None else int(ssrc) & 0xFFFFFFFF
        self.seq = random.getrandbits(16)
        self._t0_s: float | None = None
        self._ts0 = random.getrandbits(32)

    def timestamp(self, stamp_s: float) -> int:
        """The 90 kHz RTP timestamp of a capture time (s, any monotonic clock)."""
        if self._t0_s is None:
            self._t0_s = stamp_s
        return (self._ts0 + round((stamp_s - self._t0_s) * _CLOCK_HZ)) & 0xFFFFFFFF

    def _header(self, marker: bool, ts: int) -> bytes:
        head = struct.pack("!BBHII", 0x80, (0x80 if marker else 0) | self.payload_type, self.seq, ts, self.ssrc)
        self.seq = (self.seq + 1) & 0xFFFF
        return head

    def packetize(self, access_unit: bytes, stamp_s: float) -> list[bytes]:
        """RTP packets (bytes) of one Annex B access unit captured at `stamp_s`."""
        ts = self.timestamp(stamp_s)
        nals = split_annexb(access_unit)
        packets: list[bytes] = []
        for k, nal in enumerate(nals):
            last_nal = k == len(nals) - 1
            if len(nal) <= self.max_payload:
                packets.append(self._header(last_nal, ts) + nal)
                continue
            indicator = (nal[0] & 0xE0) | _FU_A  # F and NRI of the NAL, type FU-A
            nal_type = nal[0] & 0x1F
            body = memoryview(nal)[1:]
            chunk = self.max_payload - 2
            for off in range(0, len(body), chunk):
                first, last = off == 0, off + chunk >= len(body)
                fu_header = (0x80 if first else 0) | (0x40 if last else 0) | nal_type
                packets.append(self._header(last_nal and last, ts) + bytes((indicator, fu_header))
                               + bytes(body[off:off + chunk]))
        return packets


def sdp_text(host: str, port: int, payload_type: int = PAYLOAD_TYPE, name: str = "companion") -> str:
    """An SDP session description of the H.264 RTP stream sent to `host`:`port` (for ffplay, VLC, PyAV)."""
    family = "IP6" if ":" in host else "IP4"
    return (
        "v=0\r\n"
        f"o=- 0 0 IN {family} {host}\r\n"
        f"s={name}\r\n"
        f"c=IN {family} {host}\r\n"
        "t=0 0\r\n"
        f"m=video {int(port)} RTP/AVP {int(payload_type)}\r\n"
        f"a=rtpmap:{int(payload_type)} H264/90000\r\n"
        f"a=fmtp:{int(payload_type)} packetization-mode=1\r\n"
        "a=recvonly\r\n"
    )
