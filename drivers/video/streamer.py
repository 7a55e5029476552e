"""`VideoStreamer`: the thread that draws the overlay, encodes and sends the stream, off the vision thread.

The vision task hands each processed frame with its estimate to `submit` (a one-slot mailbox: a frame
the thread has not taken yet is replaced by the newer one and counted as dropped; nothing queues, so
a slow encoder lowers the frame rate, never raises the latency). The thread keeps at most `fps`
frames a second, draws the overlay (`drivers.video.overlay`), optionally the capture-time stamp
block, encodes H.264 and sends RTP. When frames stop (camera unplugged) it sends the last picture,
darkened, with `idle_alert` ("NO NEW FRAMES", or what the daemon sets: "CAMERA LOST") at `idle_fps`, so the
ground station sees why; when frames come
back the stream goes on with the same encoder (no new SPS needed by the receiver).

For the web page it also keeps the latest frame as JPEG, encoded only while someone asked for it in
the last two seconds, at most `mjpeg_fps` a second; `add_jpeg_listener` callbacks run on this thread.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from drivers.video.encoder import H264Encoder, RtpSender
from drivers.video.overlay import Overlay, draw_overlay, draw_stamp

__all__ = ["FrameJob", "StreamerStats", "VideoStreamer"]

_log = logging.getLogger(__name__)
_JPEG_INTEREST_S = 2.0


@dataclass(frozen=True)
class FrameJob:
    """One frame for the stream: the camera image, its capture time on CLOCK_MONOTONIC (s), the overlay."""

    image: np.ndarray[Any, Any]
    capture_mono_s: float
    overlay: Overlay


@dataclass(frozen=True)
class StreamerStats:
    """Counters since start; `encode_cpu_s` is the streamer thread's CPU time in encoding + sending,
    `overlay_cpu_s` in drawing, `thread_cpu_s` all of it (time.thread_time)."""

    submitted: int
    dropped: int
    rate_skipped: int
    encoded: int
    idle_frames: int
    jpegs: int
    errors: int
    encode_cpu_s: float
    overlay_cpu_s: float
    thread_cpu_s: float
    bytes_sent: int
    packets_dropped: int


class VideoStreamer:
    """The streamer thread (see the module docstring); `start()` / `stop()`, or a context manager."""

    def __init__(self, *, size: tuple[int, int], fps: float, bitrate_kbps: int, host: str, port: int,
                 camera: PinholeCamera | None, keyframe_interval_s: float = 1.0, stamp: bool = False,
                 mjpeg_fps: float = 10.0, jpeg_quality: int = 70, idle_after_s: float = 0.5, idle_fps: float = 2.0,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self.size = (int(size[0]), int(size[1]))
        self.fps = float(fps)
        self.camera = camera
        self.stamp = bool(stamp)
        self.mjpeg_period_s = 1.0 / float(mjpeg_fps)
        self.jpeg_quality = int(jpeg_quality)
        self.idle_after_s = float(idle_after_s)
        self.idle_period_s = 1.0 / float(idle_fps)
        self._monotonic = monotonic
        self._encoder = H264Encoder(self.size[0], self.size[1], fps, bitrate_kbps, keyframe_interval_s)
        self._sender = RtpSender(host, port)
        self._cond = threading.Condition()
        self._slot: FrameJob | None = None
        self._stop = False
        self._thread: threading.Thread | None = None
        self._counts = dict.fromkeys(("submitted", "dropped", "rate_skipped", "encoded", "idle_frames", "jpegs",
                                      "errors"), 0)
        self._encode_cpu_s = 0.0
        self._overlay_cpu_s = 0.0
        self._thread_cpu_s = 0.0
        self._jpeg: tuple[int, bytes] = (0, b"")
        self._jpeg_wanted_until = -1.0
        self._last_jpeg_s = -1e9
        self._jpeg_listeners: list[Callable[[int, bytes], None]] = []
        self._last_job: FrameJob | None = None
        self._last_frame_s = -1e9  # monotonic time the last real frame arrived
        self._next_due_s = -1e9
        # the warning on the repeated picture while no frames come; the daemon says "CAMERA LOST" when its camera
        # driver reports it (a slow vision worker also starves the stream, without the camera being gone)
        self.idle_alert = "NO NEW FRAMES"

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="video-streamer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._encoder.close()
        self._sender.close()

    def __enter__(self) -> VideoStreamer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def destination(self) -> tuple[str, int]:
        host, port = self._sender.address[:2]
        return str(host), int(port)

    # ------------------------------------------------------------------ producers and consumers
    def submit(self, job: FrameJob) -> None:
        """Hand over the newest frame (any thread); an untaken older one is dropped."""
        with self._cond:
            self._counts["submitted"] += 1
            if self._slot is not None:
                self._counts["dropped"] += 1
            self._slot = job
            self._cond.notify()

    def want_jpeg(self) -> None:
        """Someone watches the page: keep JPEGs coming for the next two seconds."""
        self._jpeg_wanted_until = self._monotonic() + _JPEG_INTEREST_S

    def latest_jpeg(self) -> tuple[int, bytes]:
        """(sequence number, JPEG bytes) of the newest page image; (0, b"") before the first."""
        return self._jpeg

    def add_jpeg_listener(self, callback: Callable[[int, bytes], None]) -> Callable[[], None]:
        """Call `callback(seq, jpeg)` (on the streamer thread) for each new JPEG; returns the remover."""
        self._jpeg_listeners.append(callback)
        return lambda: self._jpeg_listeners.remove(callback) if callback in self._jpeg_listeners else None

    def stats(self) -> StreamerStats:
        c = self._counts
        return StreamerStats(c["submitted"], c["dropped"], c["rate_skipped"], c["encoded"], c["idle_frames"],
                             c["jpegs"], c["errors"], self._encode_cpu_s, self._overlay_cpu_s, self._thread_cpu_s,
                             self._sender.bytes_sent, self._sender.packets_dropped)

    # ------------------------------------------------------------------ the thread
    def _take(self, timeout_s: float) -> FrameJob | None:
        with self._cond:
            if self._slot is None and not self._stop:
                self._cond.wait(timeout_s)
            job, self._slot = self._slot, None
            return job

    def _run(self) -> None:
        period = 1.0 / self.fps
        while not self._stop:
            job = self._take(self.idle_period_s)
            now = self._monotonic()
            if job is None:
                last = self._last_job
                if last is not None and now - self._last_frame_s >= self.idle_after_s:
                    idle = replace(last, capture_mono_s=now, overlay=replace(last.overlay, alert=self.idle_alert))
                    self._counts["idle_frames"] += 1
                    self._emit(idle, now, dim=True)
                continue
            self._last_frame_s = now
            self._last_job = job
            if now < self._next_due_s - 0.5 * period:
                self._counts["rate_skipped"] += 1  # over `fps`: this one is dropped, the next may go
                continue
            self._next_due_s = max(self._next_due_s + period, now)
            self._emit(job, now, dim=False)

    def _emit(self, job: FrameJob, now: float, dim: bool) -> None:
        t0 = time.thread_time()
        try:
            image = job.image // 3 if dim else job.image
            frame = draw_overlay(image, job.overlay, self.camera, self.size)
            if self.stamp:
                draw_stamp(frame, int(job.capture_mono_s * 1000.0))
            t1 = time.thread_time()
            self._sender.send(self._encoder.encode(frame), job.capture_mono_s)
            t2 = time.thread_time()
            self._counts["encoded"] += 1
            self._overlay_cpu_s += t1 - t0
            self._encode_cpu_s += t2 - t1
            if now <= self._jpeg_wanted_until and now - self._last_jpeg_s >= self.mjpeg_period_s * 0.9:
                self._last_jpeg_s = now
                ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
                if ok:
                    self._jpeg = (self._jpeg[0] + 1, buf.tobytes())
                    self._counts["jpegs"] += 1
                    for cb in list(self._jpeg_listeners):
                        with contextlib.suppress(Exception):
                            cb(*self._jpeg)
        except Exception:  # one bad frame must not end the stream
            self._counts["errors"] += 1
            if self._counts["errors"] <= 5:
                _log.exception("video: a frame failed")
        finally:
            self._thread_cpu_s += time.thread_time() - t0
