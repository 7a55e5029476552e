"""Shi-Tomasi corner selection from an eigenvalue map, compiled (numba, optional: `companion/jit.py`).

`cv2.goodFeaturesToTrack` spends about as long choosing its corners (a dilation and a threshold of the whole map,
a scan, a sort of every local maximum, a distance test) as computing the minimum-eigenvalue map they come from:
1.8 of 4.3 ms per call on the ground points' 720x480 frames (scratch timing on the `bench/rack_stress.py
--throughput` frames). `_select` makes the same choice from the map `cv2.cornerMinEigenVal` returns in one
pass over the pixels and one sort of the candidates, with the rules `corners.py` states (OpenCV's): local maxima
(3x3, interior pixels) inside the mask above the quality threshold, and above the floor when one is given,
visited by decreasing eigenvalue (ties: the later pixel first) and accepted unless an accepted corner lies
closer than the minimum distance. Only comparisons: the corners are OpenCV's exactly (`tests/rack/test_corners.py`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.jit import compile_kernels, register


def _select(ev: Any, mask: Any, q32: Any, f32: Any, max_corners: int, min_d2: float) -> Any:
    """Corners (J, 2) float32 (x, y) of the float32 map `ev` (H, W) where `mask` (H, W) uint8 > 0: interior 3x3
    local maxima strictly above `q32` and at least `f32` (float32 thresholds), in OpenCV's order and spacing
    (squared distance at least `min_d2` px² from every accepted corner), at most `max_corners`."""
    h, w = ev.shape
    n = max(h - 2, 0) * max(w - 2, 0)  # room for every interior pixel (np.empty: no pass to fill it)
    idx = np.empty(n, dtype=np.int64)
    val = np.empty(n, dtype=np.float32)
    m = 0
    # Candidates from the last pixel to the first: a stable sort by decreasing value then keeps the later pixel
    # first among equal values, as OpenCV's sort does.
    for y in range(h - 2, 0, -1):
        for x in range(w - 2, 0, -1):
            v = ev[y, x]
            if mask[y, x] == 0 or not (v > q32 and v >= f32):
                continue
            if (ev[y - 1, x - 1] > v or ev[y - 1, x] > v or ev[y - 1, x + 1] > v or ev[y, x - 1] > v
                    or ev[y, x + 1] > v or ev[y + 1, x - 1] > v or ev[y + 1, x] > v or ev[y + 1, x + 1] > v):
                continue
            idx[m] = y * w + x
            val[m] = v
            m += 1
    order = np.argsort(-val[:m], kind="mergesort")
    # An accepted corner blocks every pixel nearer than the minimum distance (integer offsets, the same test).
    r = math.ceil(math.sqrt(min_d2))
    blocked = np.zeros((h, w), dtype=np.bool_)
    out = np.empty((min(m, max_corners), 2), dtype=np.float32)
    k = 0
    for j in range(m):
        if k == max_corners:
            break
        p = idx[order[j]]
        cy = p // w
        cx = p - cy * w
        if blocked[cy, cx]:
            continue
        out[k, 0] = cx
        out[k, 1] = cy
        k += 1
        for dy in range(max(-r, -cy), min(r, h - 1 - cy) + 1):
            for dx in range(max(-r, -cx), min(r, w - 1 - cx) + 1):
                if dx * dx + dy * dy < min_d2:
                    blocked[cy + dy, cx + dx] = True
    return out[:k]


@dataclass(frozen=True)
class Kernels:
    """The compiled kernel (a numba dispatcher with `_select`'s signature)."""

    select: Any


def _build(njit: Any) -> Kernels:
    return Kernels(select=njit(_select))


def _warm_up(ks: Kernels) -> None:
    ks.select(np.zeros((3, 3), dtype=np.float32), np.ones((3, 3), dtype=np.uint8), np.float32(0.0),
              np.float32(0.0), 1, 1.0)


def kernels() -> Kernels | None:
    """The compiled kernel, or None (numba unavailable or `COMPANION_JIT=0`: OpenCV's detector, or numpy)."""
    return compile_kernels("rack.corners", _build, _warm_up)


register(kernels)
