"""What `companion sim` adds for the ground station: the status page (control API) and the overlay video.

`add_ground_station_arguments` adds ``--no-video``, ``--video-port``, ``--api-port`` and ``--token-file``
to the `sim` parser; `ground_station_overrides` turns them into configuration overrides (the control API
on loopback, the video on unless ``--no-video``: H.264/RTP to 127.0.0.1:5600, QGroundControl's default,
at twice the simulated camera's 360x240); `announce` prints where the page, the stream and its SDP file are.
"""

from __future__ import annotations

import argparse
from typing import Any, TextIO

__all__ = ["add_ground_station_arguments", "announce", "ground_station_overrides"]


def add_ground_station_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-video", action="store_true", help="no overlay video stream to the ground station")
    p.add_argument("--video-port", type=int, default=5600, metavar="PORT",
                   help="UDP port of the H.264/RTP stream on 127.0.0.1 (default 5600, QGroundControl's)")
    p.add_argument("--api-port", type=int, default=8765, metavar="PORT",
                   help="port of the control API and the status page on 127.0.0.1 (default 8765; 0 = any free)")
    p.add_argument("--token-file", metavar="FILE", default="",
                   help="bearer token file for the control API and the page (default: none, loopback only)")


def ground_station_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """Configuration overrides (section -> values) for `SimOptions.config_overrides`."""
    return {
        "api": {"enabled": True, "bind": "127.0.0.1", "port": int(args.api_port), "token_file": str(args.token_file)},
        "video": {"enabled": not args.no_video, "host": "127.0.0.1", "port": int(args.video_port), "scale": 2.0},
    }


def announce(daemon: Any, out: TextIO) -> None:
    """Print the status page's address and the stream's destination and SDP file (when they run)."""
    server = getattr(daemon, "api_server", None)
    if server is not None:
        print(f"status page: {server.url}/page/" + (" (token required)" if server.token_required else ""),
              file=out, flush=True)
    streamer = getattr(daemon, "video_streamer", None)
    if streamer is not None:
        host, port = streamer.destination
        w, h = streamer.size
        print(f"video: H.264 RTP to udp://{host}:{port} ({w}x{h}; QGroundControl: UDP h.264 video on port {port}); "
              f"SDP for VLC/ffplay: {daemon.video_sdp_path}", file=out, flush=True)
