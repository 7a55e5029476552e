"""Shi-Tomasi corners above a noise floor, with one structure-tensor pass (the texture detector's speed).

`cv2.goodFeaturesToTrack` followed by a floor on each corner's minimum eigenvalue computes the
eigenvalue map twice (once inside OpenCV, once for the floor) and sorts every local maximum above
its quality level (thousands on a textured image) only for the floor to keep a few. Here the map is
computed once and only the local maxima above both thresholds are ordered and thinned. The result
is exactly OpenCV's, floored: OpenCV keeps local maxima (3x3) above `quality_level` times the
mask's maximum, visits them by decreasing eigenvalue (ties: the later pixel in row-major order
first) and accepts one unless an accepted corner lies closer than `min_distance_px`, until
`max_corners` are accepted. Whether a corner is accepted depends only on the corners visited before
it, all stronger, so the accepted corners above the floor are those of the same visit restricted to
the corners above the floor. Pixels are (x, y) in the given image (OpenCV's integer pixel centres).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from companion.vision.rack.corners_jit import kernels

Float32Array = np.ndarray[Any, np.dtype[np.float32]]
_CHUNK = 256  # candidates whose mutual distances are tested in one (chunk, chunk) array
_MEDIAN_SUBSAMPLE_MIN = 8192  # below this a full selection is as quick as the bracket
_MEDIAN_STRIDE = 32  # the bracket's subsample: every 32nd value


def strong_corners(
    gray: np.ndarray[Any, np.dtype[np.uint8]],
    mask: np.ndarray[Any, np.dtype[np.uint8]],
    max_corners: int,
    min_distance_px: float,
    quality_level: float,
    block_size: int,
    min_ratio: float,
) -> Float32Array | None:
    """Corners (J, 2) float32 (x, y), in `cv2.goodFeaturesToTrack`'s order, whose minimum eigenvalue is at least
    `min_ratio` times its median over `mask` (> 0 where searched).

    Equal to `cv2.goodFeaturesToTrack(gray, max_corners, quality_level, min_distance_px, mask=mask,
    blockSize=block_size)` (gradient size 3, no Harris) filtered by `cv2.cornerMinEigenVal(gray,
    block_size, ksize=3) >= min_ratio * median` at each corner. None (the caller then runs those two)
    when the mask is empty or the maximum or the median eigenvalue is not positive.
    """
    ev = np.asarray(cv2.cornerMinEigenVal(gray, block_size, ksize=3), dtype=np.float32)
    inside = mask > 0
    vals = ev[inside]
    if vals.size == 0:
        return None
    floor = _median(vals)
    max_val = float(vals.max())
    if not (max_val > 0.0 and floor > 0.0 and min_ratio > 0.0 and min_distance_px >= 1.0):
        return None
    # OpenCV thresholds the float32 map at (float) (max * quality), keeping values strictly above.
    q32 = np.float32(max_val * quality_level)
    # The floor test compares in double: e >= min_ratio * floor  <=>  e >= the least float32 not below it.
    bound = min_ratio * floor
    f32 = np.float32(bound)
    if float(f32) < bound:
        f32 = np.nextafter(f32, np.float32(np.inf))
    ks = kernels()
    if ks is not None:
        # The same selection in one compiled pass (`corners_jit.py`).
        return np.asarray(ks.select(ev, np.ascontiguousarray(mask), q32, f32, int(max_corners),
                                    float(min_distance_px) ** 2))
    h, w = ev.shape
    cand = inside & (ev > q32) & (ev >= f32)
    # OpenCV looks at the interior only (its 3x3 maximum needs all neighbours).
    cand[0, :] = False
    cand[h - 1, :] = False
    cand[:, 0] = False
    cand[:, w - 1] = False
    idx = np.flatnonzero(cand)
    flat = ev.ravel()
    val = flat[idx]
    # Local maximum of the thresholded map: no neighbour larger (a neighbour larger than a value above the
    # threshold is above it too, so the raw map gives the same test).
    peak = np.ones(idx.size, dtype=bool)
    for off in (-w - 1, -w, -w + 1, -1, 1, w - 1, w, w + 1):
        peak &= flat[idx + off] <= val
    idx, val = idx[peak], val[peak]
    order = np.lexsort((-idx, -val))  # decreasing value, ties: the later pixel first
    idx = idx[order]
    xs = (idx % w).astype(np.int64)
    ys = (idx // w).astype(np.int64)
    min_d2 = float(min_distance_px) ** 2
    acc_x: list[int] = []
    acc_y: list[int] = []
    for s in range(0, idx.size, _CHUNK):
        cx, cy = xs[s : s + _CHUNK], ys[s : s + _CHUNK]
        free = np.ones(cx.size, dtype=bool)
        if acc_x:
            ax, ay = np.array(acc_x), np.array(acc_y)
            free = ~np.any((cx[:, None] - ax[None, :]) ** 2 + (cy[:, None] - ay[None, :]) ** 2 < min_d2, axis=1)
        near = (cx[:, None] - cx[None, :]) ** 2 + (cy[:, None] - cy[None, :]) ** 2 < min_d2
        for i in np.flatnonzero(free):
            if not free[i]:
                continue
            acc_x.append(int(cx[i]))
            acc_y.append(int(cy[i]))
            if len(acc_x) == max_corners:
                return np.array([acc_x, acc_y], dtype=np.float32).T.copy()
            free &= ~near[i]
    return np.array([acc_x, acc_y], dtype=np.float32).reshape(2, -1).T.copy()


def shi_tomasi(
    gray: np.ndarray[Any, np.dtype[np.uint8]],
    mask: np.ndarray[Any, np.dtype[np.uint8]],
    max_corners: int,
    min_distance_px: float,
    quality_level: float,
    block_size: int,
) -> Float32Array:
    """`cv2.goodFeaturesToTrack(gray, max_corners, quality_level, min_distance_px, mask=mask, blockSize=block_size)`
    (gradient size 3, no Harris) as (J, 2) float32 (x, y), J = 0 when it finds none: the same corners, chosen by
    the compiled selection from OpenCV's eigenvalue map when it is available (half the detector's time)."""
    ks = kernels()
    if ks is not None and max_corners > 0 and min_distance_px >= 1.0:
        ev = np.asarray(cv2.cornerMinEigenVal(gray, block_size, ksize=3), dtype=np.float32)
        max_val = float(cv2.minMaxLoc(ev, mask)[1])
        if max_val > 0.0:
            return np.asarray(ks.select(ev, np.ascontiguousarray(mask), np.float32(max_val * quality_level),
                                        np.float32(-np.inf), int(max_corners), float(min_distance_px) ** 2))
    found = cv2.goodFeaturesToTrack(gray, maxCorners=int(max_corners), qualityLevel=quality_level,
                                    minDistance=float(min_distance_px), mask=mask, blockSize=block_size)
    return np.zeros((0, 2), dtype=np.float32) if found is None else np.asarray(found, np.float32).reshape(-1, 2)


def _median(vals: Float32Array) -> float:
    """`np.median` of a non-empty 1-D array without NaN (the same value).

    The middle rank(s) are bracketed between two values of a strided subsample, checked by counting, and
    selected among the values inside the bracket only (a few percent of them): one full selection over the
    ~2e5 eigenvalues of a mask took about 4 % of a tracked frame (the texture detector's noise floor). The
    bracket spans six standard deviations of a random subsample's rank either side, but a strided subsample of
    an image is not random (a periodic or sorted array defeats it): when the count shows that the bracket
    misses, the whole array is selected, so the result is exact either way. For an even count
    the lower middle value is the largest below the upper one (`np.median` selects three ranks).
    """
    n = vals.size
    h = n // 2
    k_lo = h if n % 2 else h - 1  # the lower middle rank (= h for an odd count)
    src = vals
    if n >= _MEDIAN_SUBSAMPLE_MIN:
        sub = vals[::_MEDIAN_STRIDE]
        m = sub.size
        c = (h * m) // n
        pad = 3 * int(math.sqrt(m)) + 8  # the rank of a sample quantile has a standard deviation <= sqrt(m) / 2
        i_lo, i_hi = max(c - pad, 0), min(c + pad, m - 1)
        part = np.partition(sub, [i_lo, i_hi])
        lo, hi = part[i_lo], part[i_hi]
        below = vals < lo
        n_below = int(np.count_nonzero(below))
        mid = vals[~below & (vals <= hi)]
        if n_below <= k_lo and h < n_below + mid.size:
            src, h, k_lo = mid, h - n_below, k_lo - n_below
    p = np.partition(src, h)
    if k_lo == h:
        return float(p[h])
    return float((p[:h].max() + p[h]) / 2.0)
