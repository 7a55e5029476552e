"""Video to the ground station: the tracking overlay, H.264 encoding (PyAV), RTP over UDP, the streamer thread.

See `docs/video.md`."""

from drivers.video.encoder import H264Encoder, RtpSender, VideoError
from drivers.video.overlay import Overlay, draw_overlay, draw_stamp, read_stamp
from drivers.video.rtp import RtpH264Packetizer, sdp_text, split_annexb
from drivers.video.streamer import StreamerStats, VideoStreamer

__all__ = [
    "H264Encoder",
    "Overlay",
    "RtpH264Packetizer",
    "RtpSender",
    "StreamerStats",
    "VideoError",
    "VideoStreamer",
    "draw_overlay",
    "draw_stamp",
    "read_stamp",
    "sdp_text",
    "split_annexb",
]
