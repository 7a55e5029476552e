"""What a camera source hands out and reports: `Frame`, `Capture` (what `_read` returns), `CameraState`,
`CameraStats`, `EndOfStream`, and `convert_color`, which brings every image to gray or BGR uint8."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.errors import CameraError

__all__ = ["CameraState", "CameraStats", "Capture", "EndOfStream", "Frame", "Image", "convert_color"]

Image = np.ndarray[Any, np.dtype[Any]]  # uint8 (H, W) or (H, W, 3)


@dataclass(frozen=True)
class Frame:
    """One captured image.

    `image`: (H, W) uint8 gray or (H, W, 3) uint8 BGR. `stamp_s`: the injected
    clock's monotonic time at capture (s). `seq`: capture counter from 0 over
    the source's life (gaps = frames dropped). `dropped_before`: frames that
    were captured after the previously delivered one and replaced before being
    delivered. `source_stamp_s`: the recording's own time of the frame (s;
    folder timestamps file, video position, synthetic pose stamp) or None.
    """

    image: Image
    stamp_s: float
    seq: int
    dropped_before: int
    source_stamp_s: float | None = None


class CameraState(enum.Enum):
    """Life cycle of a source."""

    STARTING = "starting"  # entered, no frame yet
    STREAMING = "streaming"  # frames arriving
    LOST = "lost"  # read/open failure or no frame for lost_after_s; reopening with backoff
    ENDED = "ended"  # a finite source (video, folder) is exhausted
    CLOSED = "closed"  # not entered, or exited


@dataclass(frozen=True)
class CameraStats:
    """Counters of a source (a snapshot)."""

    captured: int  # frames read from the device
    delivered: int  # frames handed to the consumer
    dropped_stale: int  # frames replaced by a newer one before delivery
    read_failures: int  # failed reads or opens
    reopen_count: int  # successful reopens after a failure
    lost_count: int  # times the source became LOST
    lost: bool
    state: CameraState
    last_frame_s: float | None  # clock time of the newest captured frame
    last_error: str | None


@dataclass(frozen=True)
class Capture:
    """What `_read` returns for one frame: the image and optional stamps (s)."""

    image: Image
    stamp_s: float | None = None  # None: the base stamps clock.now() after the read
    source_stamp_s: float | None = None


class EndOfStream(Exception):
    """Raised by `_read` when a finite source has no more frames."""


def convert_color(image: Any, color: str) -> Image:
    """`image` as (H, W) uint8 gray (color="gray") or (H, W, 3) uint8 BGR (color="bgr")."""
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        raise CameraError(f"image: expected uint8 pixels, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 2:
        return arr if color == "gray" else cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        if color == "gray":
            code = cv2.COLOR_BGR2GRAY if arr.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            return cv2.cvtColor(arr, code)
        return arr if arr.shape[2] == 3 else cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR)
    raise CameraError(f"image: expected (H, W) or (H, W, 3) pixels, got shape {arr.shape}")
