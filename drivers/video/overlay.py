"""The tracking overlay drawn on the streamed frames, and the capture-time stamp block.

`draw_overlay(image, overlay, camera, size)` returns a new BGR frame of `size` (the stream's): the
camera image resized, the visible limbs of the rack model projected at the estimated pose
(`companion.vision.rack.limbs.sample_limbs`, occlusion-aware; green when the tracker is ok, red
otherwise), the tracker's texture points at that pose (cyan dots), and text lines (pose, tracker
health, mission step, safety state) on a dark band at the bottom. Projection runs at the camera's
resolution, then pixel coordinates are scaled to the stream's.

`draw_stamp(frame, ms)` writes a 32-bit millisecond count (capture time on CLOCK_MONOTONIC) and an
8-bit checksum as a row of 40 black/white cells in the top-left corner; cells are big enough
(width / 80 px) to survive H.264 at a few hundred kbit/s. `read_stamp(frame)` reads it back (None
when the checksum fails), so a receiver on the same machine measures glass-to-decoded latency.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.limbs import sample_limbs
from companion.vision.rack.model import PipeArrays

__all__ = ["LIMB_BGR", "LIMB_LOST_BGR", "Overlay", "draw_overlay", "draw_stamp", "read_stamp", "stamp_cell_px"]

LIMB_BGR = (0, 255, 0)
LIMB_LOST_BGR = (0, 0, 255)
TEXTURE_BGR = (255, 255, 0)
_STAMP_BITS = 40  # 32 data + 8 checksum
_SAMPLES_PER_LIMB = 24


@dataclass(frozen=True)
class Overlay:
    """What to draw on one frame.

    T_rack_cam: the estimated camera pose in the rack frame (None: no rack estimate); pipes: the model's
    pipes at the estimated gaps; rack_ok: the tracker's verdict; texture_rack (N, 3): the tracker's texture
    points (rack frame, m); lines: text lines, top to bottom; alert: a large centred warning (camera lost).
    """

    T_rack_cam: FloatArray | None = None
    pipes: PipeArrays | None = None
    rack_ok: bool = False
    texture_rack: FloatArray | None = None
    lines: tuple[str, ...] = ()
    alert: str = ""


def stamp_cell_px(width: int) -> int:
    """Side of one stamp cell (px) for a frame `width` px wide."""
    return max(4, width // 80)


def _as_bgr(image: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image


def draw_overlay(image: np.ndarray[Any, Any], overlay: Overlay, camera: PinholeCamera | None,
                 size: tuple[int, int]) -> np.ndarray[Any, Any]:
    """A new BGR frame of `size` = (width, height) with `overlay` drawn (see the module docstring)."""
    w, h = size
    src = _as_bgr(image)
    out = cv2.resize(src, (w, h), interpolation=cv2.INTER_AREA if src.shape[1] > w else cv2.INTER_LINEAR)
    if not out.flags.writeable or out is src:
        out = out.copy()
    sx = w / src.shape[1]
    sy = h / src.shape[0]
    thick = max(1, round(2 * min(sx, sy) + 0.25)) if w >= 480 else 1
    if overlay.T_rack_cam is not None and overlay.pipes is not None and camera is not None:
        T = np.asarray(overlay.T_rack_cam, dtype=np.float64)
        samples = sample_limbs(T, camera, overlay.pipes, _SAMPLES_PER_LIMB, margin_px=0.0)
        if samples.uv.shape[0] >= 2:
            uv = samples.uv * np.array([sx, sy])
            # polylines per limb, broken where samples were dropped (occluded or outside the image)
            step = np.hypot(*np.diff(uv, axis=0).T)
            same = samples.limb[1:] == samples.limb[:-1]
            typical = np.median(step[same]) if np.any(same) else 0.0
            breaks = np.flatnonzero(~same | (step > 1.6 * typical + 1.0)) + 1
            colour = LIMB_BGR if overlay.rack_ok else LIMB_LOST_BGR
            pieces = [np.round(p).astype(np.int32) for p in np.split(uv, breaks) if p.shape[0] >= 2]
            cv2.polylines(out, pieces, False, colour, thick, cv2.LINE_8)
        if overlay.texture_rack is not None and overlay.texture_rack.shape[0] > 0:
            p_cam = (overlay.texture_rack - T[:3, 3]) @ T[:3, :3]
            front = p_cam[:, 2] > 0.05
            uv = camera.project(p_cam[front]) * np.array([sx, sy])
            uv = uv[np.all(np.isfinite(uv), axis=1)]
            _draw_dots(out, np.round(uv).astype(np.intp), max(1, thick // 2), TEXTURE_BGR)
    _draw_text(out, overlay.lines)
    if overlay.alert:
        scale = max(0.6, w / 640.0)
        (tw, th), _ = cv2.getTextSize(overlay.alert, cv2.FONT_HERSHEY_SIMPLEX, scale, 2)
        org = ((w - tw) // 2, (h + th) // 2)
        cv2.rectangle(out, (org[0] - 8, org[1] - th - 8), (org[0] + tw + 8, org[1] + 8), (0, 0, 0), -1)
        cv2.putText(out, overlay.alert, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 255), 2, cv2.LINE_AA)
    return out


def _draw_dots(out: np.ndarray[Any, Any], uv: np.ndarray[Any, Any], r: int, colour: tuple[int, int, int]) -> None:
    """Filled squares of half-side `r` px at the pixels `uv` (N, 2), all points at once."""
    h, w = out.shape[:2]
    d = np.arange(-r, r + 1)
    du, dv = np.meshgrid(d, d)
    u = (uv[:, 0:1] + du.reshape(1, -1)).ravel()
    v = (uv[:, 1:2] + dv.reshape(1, -1)).ravel()
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out[v[inside], u[inside]] = colour


def _draw_text(out: np.ndarray[Any, Any], lines: tuple[str, ...]) -> None:
    if not lines:
        return
    h, w = out.shape[:2]
    scale = 0.4 if w < 800 else 0.55
    line_h = round(16 * scale / 0.4)
    top = h - line_h * len(lines) - 4
    band = out[max(top, 0):, :]
    band //= 3  # darken under the text, keep the picture visible
    for k, text in enumerate(lines):
        cv2.putText(out, text, (4, top + line_h * (k + 1) - 3), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                    cv2.LINE_AA)


def _stamp_bits(ms: int) -> np.ndarray[Any, np.dtype[np.uint8]]:
    value = int(ms) & 0xFFFFFFFF
    data = value.to_bytes(4, "big")
    check = (sum(data) + 0x5A) & 0xFF
    word = (value << 8) | check
    return np.array([(word >> (_STAMP_BITS - 1 - k)) & 1 for k in range(_STAMP_BITS)], dtype=np.uint8)


def draw_stamp(frame: np.ndarray[Any, Any], ms: int) -> None:
    """Write `ms` (mod 2**32) as the stamp block in the top-left corner of the BGR `frame` (in place)."""
    c = stamp_cell_px(frame.shape[1])
    row = np.repeat(_stamp_bits(ms) * 255, c).astype(np.uint8)
    frame[:c, : row.size] = np.repeat(row[None, :], c, axis=0)[:, :, None]


def read_stamp(frame: np.ndarray[Any, Any]) -> int | None:
    """The millisecond count of the stamp block in a decoded frame (BGR or gray), None if unreadable."""
    c = stamp_cell_px(frame.shape[1])
    gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    if gray.shape[0] < c or gray.shape[1] < c * _STAMP_BITS:
        return None
    inner = gray[c // 4: c - c // 4, : c * _STAMP_BITS].astype(np.float32)  # cell centres, away from the edges
    cells = inner.reshape(inner.shape[0], _STAMP_BITS, c)[:, :, c // 4: c - c // 4].mean(axis=(0, 2))
    bits = (cells > 128).astype(np.int64)
    word = int(bits @ (1 << np.arange(_STAMP_BITS - 1, -1, -1, dtype=np.int64)))
    value, check = word >> 8, word & 0xFF
    return value if ((sum(value.to_bytes(4, "big")) + 0x5A) & 0xFF) == check else None
