"""OpenCV-backed sources: a V4L2 device (`cv2.CAP_V4L2`) and a video file.

The capture object is created by an injectable `capture_factory(device, api_preference)`
(default `cv2.VideoCapture`), so tests drive the sources with fake captures.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import cv2

from companion.clock import Clock
from companion.errors import CameraError
from drivers.camera.base import CameraSource, Capture, EndOfStream

# V4L2 auto-exposure values as OpenCV's V4L2 backend passes them through
# (V4L2_EXPOSURE_MANUAL = 1, V4L2_EXPOSURE_APERTURE_PRIORITY = 3).
V4L2_EXPOSURE_MANUAL = 1.0
V4L2_EXPOSURE_AUTO = 3.0


class CaptureLike(Protocol):
    """The part of `cv2.VideoCapture` the sources use."""

    def isOpened(self) -> bool: ...

    def read(self) -> tuple[bool, Any]: ...

    def set(self, prop_id: int, value: float) -> bool: ...

    def get(self, prop_id: int) -> float: ...

    def release(self) -> None: ...


CaptureFactory = Callable[[Any, int], CaptureLike]


def opencv_capture(device: Any, api_preference: int) -> CaptureLike:
    """The default factory: `cv2.VideoCapture(device, api_preference)`."""
    cap: CaptureLike = cv2.VideoCapture(device, api_preference)
    return cap


def _device_arg(device: str) -> str | int:
    """"/dev/video2" stays a path; "2" becomes the index 2."""
    return int(device) if device.isdigit() else device


class V4L2Camera(CameraSource):
    """A V4L2 camera through OpenCV: resolution, fps, FOURCC (MJPG/YUYV), exposure and gain.

    A device that is missing or vanishes makes the source LOST and it reopens
    with backoff; a device that delivers another resolution than asked is a
    failed open (the calibration would not match).
    """

    def __init__(
        self,
        clock: Clock,
        device: str = "/dev/video0",
        *,
        width: int = 720,
        height: int = 480,
        fps: float = 30.0,
        pixel_format: str = "MJPG",
        exposure: str | float = "auto",
        gain: float | None = None,
        color: str = "gray",
        lost_after_s: float = 0.5,
        reopen_backoff_s: float = 0.2,
        reopen_backoff_max_s: float = 5.0,
        capture_factory: CaptureFactory | None = None,
    ) -> None:
        super().__init__(
            clock,
            name=f"v4l2:{device}",
            color=color,
            lost_after_s=lost_after_s,
            reopen_backoff_s=reopen_backoff_s,
            reopen_backoff_max_s=reopen_backoff_max_s,
            join_timeout_s=max(0.2, 3.0 / fps),
        )
        if pixel_format not in ("MJPG", "YUYV", ""):
            raise CameraError(f'pixel_format: must be "MJPG", "YUYV" or "", got {pixel_format!r}')
        self._device = device
        self._width = int(width)
        self._height = int(height)
        self._fps = float(fps)
        self._pixel_format = pixel_format
        self._exposure = exposure
        self._gain = gain
        self._factory = capture_factory or opencv_capture
        self._cap: CaptureLike | None = None

    def _configure(self, cap: CaptureLike) -> None:
        if self._pixel_format:
            cap.set(cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter.fourcc(*self._pixel_format)))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, float(self._width))
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, float(self._height))
        cap.set(cv2.CAP_PROP_FPS, self._fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1.0)  # keep the driver queue short: newest frame wins
        timeout_prop = getattr(cv2, "CAP_PROP_READ_TIMEOUT_MSEC", None)
        if timeout_prop is not None:  # a vanished device returns from read() instead of blocking
            cap.set(int(timeout_prop), 1000.0)
        if self._exposure == "auto":
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_AUTO)
        else:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_MANUAL)
            cap.set(cv2.CAP_PROP_EXPOSURE, float(self._exposure))
        if self._gain is not None:
            cap.set(cv2.CAP_PROP_GAIN, float(self._gain))
        got_w, got_h = cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)
        if got_w > 0 and got_h > 0 and (int(got_w), int(got_h)) != (self._width, self._height):
            raise CameraError(
                f"{self._device}: device delivers {int(got_w)}x{int(got_h)}, config asks {self._width}x{self._height}"
            )

    def _open(self) -> None:
        cap = self._factory(_device_arg(self._device), cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"{self._device}: cannot open")
        try:
            self._configure(cap)
        except CameraError:
            cap.release()
            raise
        self._cap = cap

    def _read(self) -> Capture | None:
        cap = self._cap
        if cap is None:
            raise CameraError(f"{self._device}: not open")
        ok, image = cap.read()
        if not ok or image is None:
            raise CameraError(f"{self._device}: read failed (device gone?)")
        return Capture(image)

    def _close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()


class VideoFileCamera(CameraSource):
    """A video file, paced at its own frame rate (`pacing="realtime"`) or as fast as consumed.

    `fps` is used when the file does not report one. With `loop=True` the
    video restarts at its end; otherwise the source ENDS. `Frame.source_stamp_s`
    is the frame's position in the video (s).
    """

    def __init__(
        self,
        clock: Clock,
        path: str | os.PathLike[str],
        *,
        fps: float = 30.0,
        pacing: str = "realtime",
        loop: bool = False,
        color: str = "gray",
        lost_after_s: float = 0.5,
        reopen_backoff_s: float = 0.2,
        reopen_backoff_max_s: float = 5.0,
        capture_factory: CaptureFactory | None = None,
    ) -> None:
        if pacing not in ("realtime", "consumer"):
            raise CameraError(f'pacing: must be "realtime" or "consumer", got {pacing!r}')
        super().__init__(
            clock,
            name=f"video:{Path(path).name}",
            color=color,
            lost_after_s=lost_after_s,
            reopen_backoff_s=reopen_backoff_s,
            reopen_backoff_max_s=reopen_backoff_max_s,
            drop_stale=pacing == "realtime",
        )
        self._path = Path(path)
        self._default_fps = float(fps)
        self._realtime = pacing == "realtime"
        self._loop_video = loop
        self._factory = capture_factory or opencv_capture
        self._cap: CaptureLike | None = None
        self._fps = self._default_fps
        self._index = 0
        self._origin_s: float | None = None

    async def _check_available(self) -> None:
        if not self._path.is_file():
            raise CameraError(f"{self._path}: no such video file")

    def _open(self) -> None:
        cap = self._factory(str(self._path), cv2.CAP_ANY)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"{self._path}: cannot open video")
        file_fps = cap.get(cv2.CAP_PROP_FPS)
        self._fps = file_fps if math.isfinite(file_fps) and 0 < file_fps <= 1000 else self._default_fps
        self._cap = cap

    def _read(self) -> Capture | None:
        cap = self._cap
        if cap is None:
            raise CameraError(f"{self._path}: not open")
        if self._realtime:
            if self._origin_s is None:
                self._origin_s = self._clock.now()
            self._pace(self._origin_s + self._index / self._fps)
        ok, image = cap.read()
        if (not ok or image is None) and self._loop_video:
            cap.set(cv2.CAP_PROP_POS_FRAMES, 0.0)
            ok, image = cap.read()
        if not ok or image is None:
            raise EndOfStream
        self._index += 1
        position_s = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        return Capture(image, source_stamp_s=position_s if math.isfinite(position_s) else None)

    def _close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()
