"""Real-time rig for the video and status-page tests: fake autopilot + synthetic camera + daemon, real clock.

The video path is about wall-clock behaviour (frame rate, glass-to-decoded latency, a browser), so
unlike `daemon_harness` these tests run on the `SystemClock`: the synthetic camera renders the rack
scene from the fake autopilot's true pose in its capture thread, the daemon tracks in its vision
worker and streams with the video streamer thread. The vehicle rests on the deck unless a test flies
a mission, so the true camera pose is known for the overlay pixel check. `RtpReceiver` decodes the
stream with PyAV from the SDP file the daemon wrote, in a thread, and reads the stamp block.
"""

from __future__ import annotations

import contextlib
import dataclasses
import socket
import threading
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.clock import SystemClock
from companion.daemon.app import Daemon, DaemonOptions
from companion.sim.autopilot import DrydenConfig, FakeAutopilot, FakeAutopilotConfig, FlightParams
from companion.sim.render import FaultyRender, SceneRenderer
from companion.sim.run import sim_config
from drivers.camera import load_camera_model
from drivers.video import read_stamp

VISUAL_GROUND_Z_NED_M = 4.0  # as daemon_harness: the rendered ground 4 m below the deck


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class DecodedFrame:
    recv_mono_s: float
    stamp_ms: int | None
    image: np.ndarray[Any, Any] | None  # kept for the first `keep_images` frames only


@dataclass
class RtpReceiver:
    """Decodes the RTP stream described by `sdp_path` with PyAV in a thread until `stop()`."""

    sdp_path: Path
    keep_images: int = 0
    frames: list[DecodedFrame] = field(default_factory=list)
    error: BaseException | None = None
    decode_errors: int = 0
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None
    _opened: threading.Event = field(default_factory=threading.Event)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="rtp-receiver", daemon=True)
        self._thread.start()
        self._opened.wait(5.0)

    def _run(self) -> None:
        import av

        try:
            opts = {"protocol_whitelist": "file,udp,rtp", "fflags": "nobuffer", "reorder_queue_size": "0",
                    "max_delay": "0", "analyzeduration": "500000", "probesize": "65536"}
            self._opened.set()
            with av.open(str(self.sdp_path), format="sdp", options=opts, timeout=(10.0, 2.0)) as container:
                stream = container.streams.video[0]
                for packet in container.demux(stream):
                    try:
                        decoded = packet.decode()
                    except av.error.InvalidDataError:  # joined mid-stream: P-frames before the next key frame
                        self.decode_errors += 1
                        continue
                    for frame in decoded:
                        img = frame.to_ndarray(format="bgr24")
                        now = time.monotonic()
                        keep = img if len(self.frames) < self.keep_images else None
                        self.frames.append(DecodedFrame(now, read_stamp(img), keep))
                    if self._stop.is_set():
                        return
        except Exception as exc:  # reported by the test
            if not self._stop.is_set():
                self.error = exc
        finally:
            self._opened.set()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)

    def decoded_per_s(self, since_mono_s: float = 0.0) -> float:
        """Frames decoded per second (receive clock) after `since_mono_s`; 0 with fewer than two."""
        t = [f.recv_mono_s for f in self.frames if f.recv_mono_s >= since_mono_s]
        return (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0

    def latencies_ms(self, since_mono_s: float = 0.0) -> np.ndarray[Any, Any]:
        """Glass-to-decoded latency (ms) of every stamped frame decoded after `since_mono_s`."""
        out = [((int(f.recv_mono_s * 1000.0) - f.stamp_ms) & 0xFFFFFFFF) for f in self.frames
               if f.stamp_ms is not None and f.recv_mono_s >= since_mono_s]
        return np.asarray(out, dtype=np.float64)


@dataclass
class LiveRig:
    ap: FakeAutopilot
    daemon: Daemon
    render: FaultyRender
    config: Any
    camera_model: Any

    def unplug(self, seconds: float) -> None:
        """The camera fails every read for `seconds` from now (the driver reports it lost, then reopens)."""
        now = time.monotonic()
        self.render.windows.append(("camera-unplug", now, now + seconds))


@contextlib.asynccontextmanager
async def live_rig(tmp_path: Path, *, width: int = 640, height: int = 480, fps: float = 15.0, video: bool = True,
                   video_port: int | None = None, api: bool = False, token_file: Path | None = None,
                   overrides: dict[str, Any] | None = None) -> AsyncIterator[LiveRig]:
    """The real-time rig (see the module docstring); the daemon has started and the fake's EKF is aligned."""
    clock = SystemClock()
    ov: dict[str, Any] = {
        "camera": {"width": width, "height": height, "fps": fps, "sim_ground_z_ned_m": VISUAL_GROUND_Z_NED_M},
        "video": {"enabled": video, "host": "127.0.0.1", "port": video_port or free_udp_port(), "stamp": True,
                  "sdp_path": str(tmp_path / "stream.sdp")},
        "api": {"enabled": api, "port": 0, "bind": "127.0.0.1", "token_file": str(token_file or "")},
    }
    for k, v in (overrides or {}).items():
        ov.setdefault(k, {}).update(v)
    config = sim_config(tmp_path, ov)
    flight = FlightParams(takeoff_speed_m_s=0.5, ekf_alignment_s=0.5)
    ap_cfg = FakeAutopilotConfig(profile="ardupilot", listen="udpin:127.0.0.1:0", seed=3, gcs_heartbeat=True,
                                 wind=DrydenConfig(w20_m_s=0.0), physics_rate_hz=100.0, flight=flight)
    async with FakeAutopilot(ap_cfg, clock=clock) as ap:
        config = dataclasses.replace(config, mavlink=dataclasses.replace(config.mavlink, url=ap.url_for_client))
        camera_model = load_camera_model(config.camera)
        base = SceneRenderer.from_config(config, camera_model, seed=5)
        base(ap.truth.T_ned_body)  # warm the renderer's caches
        render = FaultyRender(base, time.monotonic)
        daemon = Daemon(config, clock=clock, options=DaemonOptions(
            render=render, api=api, sdnotify=False, initial_T_ned_body=ap.truth.T_ned_body,
            flight_root=tmp_path / "flights", visual_ground_z_ned_m=VISUAL_GROUND_Z_NED_M))
        async with daemon:
            yield LiveRig(ap=ap, daemon=daemon, render=render, config=config, camera_model=camera_model)
