"""The video task: frames with the tracking overlay to the ground station, and camera discovery over MAVLink.

`_open_video` (when ``video.enabled``) starts a `drivers.video.VideoStreamer` (its own thread) and adds a
frame observer: on the loop thread, between two frames of the vision worker, it snapshots what the overlay
needs (the frame, the rack estimate or the fused pose as a camera pose in the rack frame, the tracker's
texture points, text lines) and hands it to the streamer's one-slot mailbox. Nothing is drawn or encoded
on the vision path. It also writes the SDP file receivers such as VLC, ffplay and PyAV need.

Discovery (QGroundControl finds the stream by itself): the daemon sends a HEARTBEAT as a camera component
(``video.camera_component_id``, MAV_COMP_ID_CAMERA = 100, MAV_TYPE_CAMERA) at 1 Hz and answers
MAV_CMD_REQUEST_MESSAGE (512) for CAMERA_INFORMATION (259, with CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM) and
VIDEO_STREAM_INFORMATION (269: RTP/UDP, H.264, uri ``udp://0.0.0.0:PORT``), and the older
MAV_CMD_REQUEST_CAMERA_INFORMATION (521) / MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION (2504), with a
COMMAND_ACK first.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.clock import SystemClock
from companion.daemon.state import DaemonState, FrameRecord
from companion.errors import ConfigError
from companion.geometry import frames

__all__ = ["VideoTask"]

MSG_CAMERA_INFORMATION = 259
MSG_VIDEO_STREAM_INFORMATION = 269
CMD_REQUEST_MESSAGE = 512
CMD_REQUEST_CAMERA_INFORMATION = 521
CMD_REQUEST_VIDEO_STREAM_INFORMATION = 2504


class VideoTask(DaemonState):
    """The video streamer's feeding and the camera component's MAVLink side."""

    video_streamer: Any | None = None
    video_sdp_path: Path | None = None
    _video_size: tuple[int, int] = (0, 0)
    _video_model: Any | None = None
    _camera_heartbeat: asyncio.Task[None] | None = None

    if TYPE_CHECKING:
        def page_state(self) -> dict[str, Any]: ...  # page_state

    async def _open_video(self) -> None:
        cfg = self.config.video
        if not cfg.enabled:
            return
        from companion.config_checks import video_frame_size
        from drivers.video import VideoStreamer, sdp_text

        self._video_size = video_frame_size(cfg, self.config.camera)
        try:
            streamer = VideoStreamer(size=self._video_size, fps=cfg.fps, bitrate_kbps=cfg.bitrate_kbps,
                                     host=cfg.host, port=cfg.port, camera=self.camera_model,
                                     keyframe_interval_s=cfg.keyframe_interval_s, stamp=cfg.stamp,
                                     mjpeg_fps=cfg.mjpeg_fps, jpeg_quality=cfg.jpeg_quality)
        except (ImportError, OSError) as exc:
            raise ConfigError(f"video: cannot start the stream: {exc}") from exc
        streamer.start()
        self.video_streamer = streamer
        sdp_path = Path(cfg.sdp_path) if cfg.sdp_path else (
            self.flight.path / "stream.sdp" if self.flight is not None else Path("stream.sdp"))
        with contextlib.suppress(OSError):
            sdp_path.write_text(sdp_text(cfg.host, cfg.port), encoding="ascii")
            self.video_sdp_path = sdp_path
        self._video_model = self.pipeline.rack_tracker.model if (
            self.pipeline is not None and self.pipeline.rack_tracker is not None) else self._video_rack_model()
        self.frame_observers.append(self._video_on_frame)
        cam = self.camera
        if cam is not None and hasattr(cam, "on_lost"):
            cam.on_lost(self._video_camera_lost)
            cam.on_recovered(self._video_camera_recovered)
        if self.link is not None:
            self._unsubscribe.append(self.link.on_message(self._video_on_message))
            self._camera_heartbeat = asyncio.get_running_loop().create_task(self._camera_heartbeat_loop(),
                                                                            name="daemon-camera-heartbeat")
        self._event("video-streaming", destination=f"{cfg.host}:{cfg.port}", size=list(self._video_size),
                    fps=cfg.fps, sdp=str(self.video_sdp_path))

    def _status_page(self) -> Any:
        """The web status page for the control API: the page's state and the streamer's JPEGs."""
        from drivers.api.page import StatusPage

        return StatusPage(state_provider=self.page_state, streamer=self.video_streamer)

    def _video_camera_lost(self, reason: str) -> None:
        if self.video_streamer is not None:
            self.video_streamer.idle_alert = "CAMERA LOST"

    def _video_camera_recovered(self) -> None:
        if self.video_streamer is not None:
            self.video_streamer.idle_alert = "NO NEW FRAMES"

    def _video_rack_model(self) -> Any | None:
        path = self.config.rack.model
        if not path:
            return None
        from companion.vision.rack import RackModel

        return RackModel.load(path)

    def _close_video(self) -> None:
        task, self._camera_heartbeat = self._camera_heartbeat, None
        if task is not None:
            task.cancel()
        streamer, self.video_streamer = self.video_streamer, None
        if streamer is not None:
            with contextlib.suppress(ValueError):
                self.frame_observers.remove(self._video_on_frame)
            streamer.stop()

    # ------------------------------------------------------------------ per frame (loop thread)
    def _video_on_frame(self, record: FrameRecord) -> None:
        streamer = self.video_streamer
        frame = self._latest_frame
        if streamer is None or frame is None or int(frame.seq) != record.seq:
            return
        from drivers.video.streamer import FrameJob

        # glass time on CLOCK_MONOTONIC: the capture stamp with the real clock; a simulated clock's stamps
        # are not monotonic seconds, so the hand-over time stands in for them
        capture_mono_s = float(frame.stamp_s) if type(self.clock) is SystemClock else time.monotonic()
        streamer.submit(FrameJob(image=frame.image, capture_mono_s=capture_mono_s, overlay=self._overlay(record)))

    def _overlay(self, record: FrameRecord) -> Any:
        from drivers.video.overlay import Overlay

        m = record.measurement
        rack = m.rack
        model = self._video_model
        T_rack_cam = None
        pipes = None
        texture = None
        if model is not None and rack is not None:
            T_rack_cam = np.array(rack.T_rack_cam, dtype=np.float64)
            pipes = model.pipe_arrays(np.asarray(rack.gaps))
            texture = self._texture_points(pipes)
        elif model is not None and record.nav is not None and bool(record.nav.ok):
            T_rack_cam = frames.T_rack_cam_from_T_ned_body(np.asarray(record.nav.T_ned_body), self.T_ned_rack,
                                                           self.T_body_cam)
            pipes = model.pipe_arrays()
        return Overlay(T_rack_cam=T_rack_cam, pipes=pipes, rack_ok=bool(m.rack_ok), texture_rack=texture,
                       lines=self._overlay_lines(record))

    def _texture_points(self, pipes: Any) -> Any | None:
        """The rack tracker's texture points (rack frame, m), copied between two frames of the worker.

        The tracker does not publish its texture map; it is read (never written) while the worker is idle:
        frame observers run on the loop thread after `measure` returned and before the next one starts."""
        tracker = None if self.pipeline is None else self.pipeline.rack_tracker
        tex = getattr(tracker, "_texture", None)
        if tex is None or len(tex) == 0:
            return None
        with contextlib.suppress(IndexError, AttributeError, ValueError):
            return np.asarray(pipes.starts[np.asarray(tex.pipe)] + np.asarray(tex.offset_rack), dtype=np.float64)
        return None

    def _overlay_lines(self, record: FrameRecord) -> tuple[str, ...]:
        nav = record.nav
        lines: list[str] = []
        if nav is not None and bool(nav.ok):
            p = np.asarray(nav.position_ned_m)
            yaw = math.degrees(float(frames.yaw_from_rotation(np.asarray(nav.T_ned_body)[:3, :3])))
            lines.append(f"pose N {p[0]:+.2f} E {p[1]:+.2f} D {p[2]:+.2f} m  yaw {yaw:+.0f} deg  ({nav.source})")
        else:
            lines.append("pose: no estimate")
        m = record.measurement
        health = []
        if m.rack is not None:
            r = m.rack
            health.append(f"rack {'ok' if m.rack_ok else 'LOST'} edges {r.num_edge_points} tex {r.num_texture_points}"
                          f" res {float(r.residual_px):.2f}px")
        if m.ground is not None:
            inliers = int(getattr(m.ground, "num_inliers", 0))
            health.append(f"ground {'ok' if m.ground_ok else 'LOST'} inliers {inliers}")
        lines.append("  ".join(health) + f"  vision {1000.0 * m.process_s:.0f} ms")
        ex = self.executor
        if ex is not None:
            done, total = len(ex.results), len(ex.mission.actions)
            step = ""
            if done < total and self._mission_active():
                a = ex.mission.actions[done]
                step = f" {type(a).tag}:{a.id}"
            lines.append(f"mission {ex.mission.name} {ex.state} {done}/{total}{step}")
        state = self.link.state if self.link is not None else None
        veh = "" if state is None else (f"  {state.mode or '-'} {'ARMED' if state.armed else 'disarmed'}"
                                        + ("" if state.battery_voltage_v is None else
                                           f" {float(state.battery_voltage_v):.1f} V"))
        lines.append(f"safety {self._safety_view.last_action}{veh}")
        return tuple(lines)

    # ------------------------------------------------------------------ MAVLink camera component
    async def _camera_heartbeat_loop(self) -> None:
        comp = int(self.config.video.camera_component_id)
        while True:
            link = self.link
            if link is not None:
                with contextlib.suppress(Exception):
                    link.send_as(comp, lambda mav: mav.heartbeat_encode(30, 8, 0, 0, 4))  # CAMERA, INVALID, ACTIVE
            await self.clock.sleep(1.0)

    def _video_on_message(self, msg: Any) -> None:
        if msg.get_type() != "COMMAND_LONG" or self.link is None:
            return
        comp = int(self.config.video.camera_component_id)
        command = int(msg.command)
        if int(msg.target_component) not in (comp, 0):
            return
        if int(msg.target_system) not in (0, int(self.link.state.autopilot_system_id or 0), self._our_system_id()):
            return
        wanted = None
        if command == CMD_REQUEST_MESSAGE:
            wanted = round(float(msg.param1))
        elif command == CMD_REQUEST_CAMERA_INFORMATION:
            wanted = MSG_CAMERA_INFORMATION
        elif command == CMD_REQUEST_VIDEO_STREAM_INFORMATION:
            wanted = MSG_VIDEO_STREAM_INFORMATION
        if wanted not in (MSG_CAMERA_INFORMATION, MSG_VIDEO_STREAM_INFORMATION):
            return  # another message or command: the autopilot or another component answers it
        src = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
        self.link.send_as(comp, lambda mav: mav.command_ack_encode(command, 0, 0, 0, src[0], src[1]))
        self.link.send_as(comp, self._camera_information if wanted == MSG_CAMERA_INFORMATION
                          else self._video_stream_information)
        self._event("video-discovery", level=logging.DEBUG, message=wanted, requester=list(src))

    def _our_system_id(self) -> int:
        return int(self.config.mavlink.system_id or (self.link.state.autopilot_system_id if self.link else 0) or 1)

    def _camera_information(self, mav: Any) -> Any:
        w, h = self._video_size
        boot_ms = max(0, int((self.clock.now() - self._start_s) * 1000.0))
        vendor = list(b"companion".ljust(32, b"\0"))
        model = list(b"overlay stream".ljust(32, b"\0"))
        # CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM (256): QGroundControl then asks for VIDEO_STREAM_INFORMATION
        return mav.camera_information_encode(boot_ms, vendor, model, 0, 0.0, 0.0, 0.0, w, h, 0, 256, 0, b"")

    def _video_stream_information(self, mav: Any) -> Any:
        cfg = self.config.video
        w, h = self._video_size
        hfov = 0
        cam = self.camera_model
        if cam is not None:
            hfov = round(math.degrees(2.0 * math.atan(0.5 * float(cam.width) / float(cam.fx))))
        uri = f"udp://0.0.0.0:{cfg.port}".encode()
        # stream 1 of 1, VIDEO_STREAM_TYPE_RTPUDP (1), VIDEO_STREAM_STATUS_FLAGS_RUNNING (1), H.264 (encoding 1)
        return mav.video_stream_information_encode(1, 1, 1, 1, float(cfg.fps), w, h, cfg.bitrate_kbps * 1000, 0, hfov,
                                                   b"companion overlay", uri, 1)
