"""Rack acquisition: the tracker's edge search (`edges.search_edges`) split in two, for the edge check.

`check_pose` searches the same samples twice when it learns a limb's polarity on the first
iteration: the image profiles along the normals do not depend on the polarity, only the choice
of the edge does. `normal_profiles` reads them (one `cv2.remap`, three parallel lines a
`tangent_offset_px` apart averaged); `pick_edges` chooses the edge of each sample for a polarity.
Together they return exactly what `search_edges(..., tangent_offset_px=...)` returns (central
difference, the default distance prior, no inner-profile reference): the same float32
arithmetic in the same order. `percentile` is `np.percentile` (linear) with one partition.
Pixels follow OpenCV (integer coordinates are pixel centres).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.vision.rack.edges import EdgeMeasurements, _search_constants, pick_in_gradients

Float32Array = np.ndarray[Any, np.dtype[np.float32]]

__all__ = ["normal_profiles", "percentile", "percentile_90", "pick_edges"]


def normal_profiles(image_f32: Float32Array, uv: FloatArray, normal: FloatArray, range_px: int,
                    tangent_offset_px: float) -> Float32Array:
    """Grey levels (N, 2R+3) along the unit `normal` (N, 2) of each sample `uv` (N, 2) at k = -R-1..R+1 px,
    the mean of three lines `tangent_offset_px` (> 0) apart."""
    n = uv.shape[0]
    k, _ = _search_constants(int(range_px), None)
    if n == 0:
        return np.zeros((0, k.size), dtype=np.float32)
    nrm = normal.astype(np.float32)
    base = uv.astype(np.float32)
    taps = np.array([-tangent_offset_px, 0.0, tangent_offset_px], dtype=np.float32)
    # base + tap * tangent + k * normal, per coordinate (tangent = (-n_y, n_x)), as search_edges sums them.
    bx, by = base[:, None, None, 0], base[:, None, None, 1]
    nx, ny = nrm[:, None, None, 0], nrm[:, None, None, 1]
    t3, k3 = taps[None, :, None], k[None, None, :]
    mx = (bx + t3 * -ny) + k3 * nx
    my = (by + t3 * nx) + k3 * ny
    prof = cv2.remap(image_f32, mx.reshape(n * 3, -1), my.reshape(n * 3, -1), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(prof.reshape(n, 3, -1).mean(axis=1), dtype=np.float32)


def pick_edges(prof: Float32Array, polarity: FloatArray, range_px: int, threshold: float) -> EdgeMeasurements:
    """The edge of each sample in its profile (`normal_profiles`) for `polarity` (N,) (+1/-1 the sign of
    the gradient along the normal, 0 either): `search_edges`' choice (`edges.pick_in_gradients`)."""
    n = prof.shape[0]
    R = int(range_px)
    if n == 0:
        z = np.zeros(0)
        return EdgeMeasurements(offset_px=z, found=np.zeros(0, dtype=bool), sign=z, strength=z)
    _, prior = _search_constants(R, None)
    g = prof[:, 2:] - prof[:, :-2]  # (N, 2R+1) at k = -R..R
    offset, found, _, g_b = pick_in_gradients(g, polarity, prior, R, threshold)
    return EdgeMeasurements(offset_px=offset, found=found, sign=np.sign(g_b).astype(np.float64),
                            strength=np.abs(g_b).astype(np.float64), inner=np.zeros((n, 0)))


def percentile_90(x: FloatArray) -> float:
    """`np.percentile(x, 90)` of a non-empty 1-D float array without NaN (the same value)."""
    return percentile(x, 90)


def percentile(x: FloatArray, q: int) -> float:
    """`np.percentile(x, q)` (linear method) of a non-empty 1-D float array without NaN, 0 <= q <= 100
    (the same value: numpy's index, weight and interpolation, with one partition)."""
    n = x.size
    virtual = (n - 1) * (q / 100)
    if virtual >= n - 1:
        return float(np.max(x))
    lo = int(np.floor(virtual))
    part = np.partition(x, (lo, lo + 1))
    a, b = part[lo], part[lo + 1]
    t = virtual - lo
    d = b - a
    return float(b - d * (1.0 - t)) if t >= 0.5 else float(a + d * t)
