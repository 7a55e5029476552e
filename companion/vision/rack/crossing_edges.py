"""Corners next to a straight edge that crosses a pipe: occlusion junctions, not marks on the cladding.

Where something the model does not hold (a support beam above the pipes, a cable tray) occludes a pipe, its
outline meets the cladding's shading and highlight in strong corners. Those corners are not fixed on the pipe:
they ride on the occluder's outline, which moves across the image at the occluder's own depth. Tracked as texture
they slide along the pipe by a fraction of the camera's speed, and with few real marks in view they alone fix the
along-pipe / pitch valley that the limbs leave open: on the stress bench's beam cell
(`p4_f20_grating_tour_distort_beam_gain`, tuning seed 1) three such points carried the pose 20 cm along the pipes
and 2 deg in pitch within 35 frames.

A mark on the cladding (a spot, rust, a bolt) is smaller than the pipe is wide: no straight edge next to it spans
the pipe. An occluder's outline crosses the whole pipe (`on_crossing_edge`). Pixels are (x, y) in the image;
lengths px.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray

BoolArray = np.ndarray[Any, np.dtype[np.bool_]]

STEP_HALF_PX = 3.0  # the grey-level step is taken between points this far either side, along the pipe's axis
WINDOW_HALF_PX = 5  # rows of the window: offsets along the axis from the corner, px (a corner lies ~5 px off)
COLUMN_STEP_PX = 2.0  # columns of the window: offsets across the pipe, limb to limb
MAX_SLOPE = 0.3  # lines up to 17 deg from square across the pipe (beams and crossing pipes run square to it; a
# steeper line leaves the window's rows within half a pipe's width, and its support with it)
SLOPE_STEP = 0.05  # 0.05 x 37 px (half a pipe) = 1.9 px: about the +-1 row a line's support is read from
LIMB_MARGIN_PX = 3.0  # the columns stop this short of the limbs (their own edge)
MIN_COLUMNS = 8  # a pipe narrower than this many columns (~22 px) is not judged: a spot would span it
WEAK_FRACTION = 0.3  # a column's step is weak below this fraction of the strong columns' (75th percentile)
MIN_STEP_GREY = 12.0  # a step weaker than this (grey levels) is no edge
NOISE_STEPS = 3.5  # nor one below this many times the image's noise on a step (`step_noise`)
_ROW = 1024


def on_crossing_edge(
    gray: np.ndarray[Any, np.dtype[np.uint8]],
    uv: FloatArray,
    axis_px: FloatArray,
    offset_px: FloatArray,
    width_px: FloatArray,
    min_fraction: float,
) -> BoolArray:
    """Which corners (K,) lie near a straight edge across their pipe that steps the grey level over at least
    `min_fraction` of the pipe's width.

    `uv` (K, 2) corner pixels, `axis_px` (K, 2) image direction of the corner's pipe axis there, `offset_px` (K,)
    the corner's signed distance from the pipe's image centre line (along the axis turned by +90 deg),
    `width_px` (K,) the pipe's image width there (limb to limb). A window aligned with the pipe (rows along
    the axis within `WINDOW_HALF_PX` of the corner, columns across it from limb to limb) holds the grey-level
    step along the axis: the cladding's shading and highlight are constant along the pipe and give none, an
    occluder's outline gives one in every column where its grey level differs from the cladding's. Each column
    votes for the lines through its strongest step (a Hough transform over the lines' slope and row); the
    best line's support is the fraction of columns with a step on it. The limbs' shading may match an
    occluder's grey level over stretches, so the edge need not be unbroken. Corners on a pipe narrower than
    `MIN_COLUMNS` columns are not judged (False).
    """
    k = uv.shape[0]
    if k == 0 or min_fraction <= 0.0:
        return np.zeros(k, dtype=bool)
    # A pose far off (a relock's wide solve) can put a pipe behind or around the camera: such corners are not
    # judged, and no pipe is taken wider than twice the image (the window's columns grow with it).
    finite = np.isfinite(uv).all(axis=1) & np.isfinite(axis_px).all(axis=1) & np.isfinite(offset_px) \
        & np.isfinite(width_px)
    if not np.all(finite):
        out = np.zeros(k, dtype=bool)
        if np.any(finite):
            out[finite] = on_crossing_edge(gray, uv[finite], axis_px[finite], offset_px[finite], width_px[finite],
                                           min_fraction)
        return out
    width_px = np.minimum(width_px, 2.0 * float(max(gray.shape[:2])))
    offset_px = np.clip(offset_px, -width_px, width_px)
    ax = axis_px / np.maximum(np.linalg.norm(axis_px, axis=1, keepdims=True), 1e-12)
    normal = np.stack([-ax[:, 1], ax[:, 0]], axis=1)
    x_lo = -(0.5 * width_px + offset_px) + LIMB_MARGIN_PX  # the -normal limb, from the corner
    x_hi = 0.5 * width_px - offset_px - LIMB_MARGIN_PX
    n_col = int(np.ceil(max(float(np.max(x_hi - x_lo)), 0.0) / COLUMN_STEP_PX)) + 1
    x = x_lo[:, None] + COLUMN_STEP_PX * np.arange(n_col)[None, :]  # (K, C)
    on = x <= x_hi[:, None]
    t = np.arange(-WINDOW_HALF_PX, WINDOW_HALF_PX + 1, dtype=np.float64)  # (R,)
    step, inside = _window_steps(gray, uv, ax, normal, t, x)  # (K, R, C)
    step = np.where(inside, step, 0.0)
    top_row = np.argmax(step, axis=1)  # (K, C) each column's strongest step
    top = np.take_along_axis(step, top_row[:, None, :], axis=1)[:, 0, :]
    # the 75th percentile of the columns' strongest steps on the cladding (off the cladding sorted first)
    n_on = on.sum(axis=1)
    ranked = np.sort(np.where(on, top, -1.0), axis=1)
    q = (n_col - n_on) + np.floor(0.75 * np.maximum(n_on - 1, 0)).astype(np.intp)
    strong = ranked[np.arange(k), np.minimum(q, n_col - 1)]
    tau = np.maximum(np.maximum(WEAK_FRACTION * strong, MIN_STEP_GREY), NOISE_STEPS * step_noise(gray))  # (K,)
    # Hough votes (K, slope, row): each strong column for the lines of every slope through its strongest step
    # (a line's row at column j: row0 + slope * j * COLUMN_STEP_PX).
    slopes = np.arange(-MAX_SLOPE, MAX_SLOPE + 1e-9, SLOPE_STEP)
    n_row, n_sl = t.size, slopes.size
    dx = COLUMN_STEP_PX * np.arange(n_col)
    row0 = np.rint(top_row[:, None, :] - slopes[None, :, None] * dx[None, None, :]).astype(np.intp)  # (K, S, C)
    vote = (on & (top >= tau[:, None]))[:, None, :] & (row0 >= 0) & (row0 < n_row)
    bins = (np.arange(k)[:, None, None] * n_sl + np.arange(n_sl)[None, :, None]) * n_row + np.clip(row0, 0, n_row - 1)
    acc = np.bincount(bins.ravel(), weights=vote.ravel(), minlength=k * n_sl * n_row).reshape(k, n_sl * n_row)
    best = np.argmax(acc, axis=1)
    b_sl, b_row = slopes[best // n_row], best % n_row
    # the best line's support: columns with a step within a row of it
    rows = np.rint(b_row[:, None] + b_sl[:, None] * dx[None, :]).astype(np.intp)[None, :, :] \
        + np.array([-1, 0, 1])[:, None, None]  # (3, K, C)
    ok = (rows >= 0) & (rows < n_row)
    band = step[np.arange(k)[None, :, None], np.clip(rows, 0, n_row - 1), np.arange(n_col)[None, None, :]]
    near = np.where(ok, band, 0.0).max(axis=0)
    frac = ((near >= tau[:, None]) & on).sum(axis=1) / np.maximum(n_on, 1)
    judged = n_on >= MIN_COLUMNS
    return np.asarray(judged & (frac >= min_fraction))


def step_noise(gray: np.ndarray[Any, np.dtype[np.uint8]]) -> float:
    """Standard deviation of a step |grey(p + 3 px) - grey(p - 3 px)| that is noise alone (grey levels), from
    its 25th percentile over every 4th pixel of the image (|N(0, s)| has 0.319 s there): at least a quarter of an
    image is plain (cladding, sky, flanges), and textures and edges only raise the upper quantiles."""
    sub = gray[: gray.shape[0] - 2 * int(STEP_HALF_PX) : 4, ::4].astype(np.int16)
    d = np.abs(sub - gray[2 * int(STEP_HALF_PX) :: 4, ::4][: sub.shape[0]].astype(np.int16)).ravel()
    if d.size == 0:
        return 0.0
    q = int(0.25 * (d.size - 1))
    return float(np.partition(d, q)[q]) / 0.319


def _window_steps(
    gray: np.ndarray[Any, np.dtype[np.uint8]], uv: FloatArray, ax: FloatArray, normal: FloatArray, t: FloatArray,
    x: FloatArray,
) -> tuple[FloatArray, BoolArray]:
    """|grey(p + STEP_HALF_PX a) - grey(p - STEP_HALF_PX a)| (K, R, C) at p = uv + t a + x n for rows `t` (R,) and
    columns `x` (K, C), a the axis and n the normal (K, 2); bilinear, the border replicated; and which p lie in
    the image."""
    h, w = gray.shape[:2]
    k, c = x.shape
    r = t.size
    m = k * r * c
    rows = -(-2 * m // _ROW)  # remap's maps are images (each side below 32767): rows of _ROW points
    grid = np.zeros((2, rows * _ROW), dtype=np.float32)
    for d in (0, 1):  # the x then the y coordinate, built in place: (K, R, 1) + (K, 1, C)
        along = (uv[:, d, None] + t[None, :] * ax[:, d, None]).astype(np.float32)[:, :, None]
        acr = (x * normal[:, d, None]).astype(np.float32)[:, None, :]
        half = np.float32(STEP_HALF_PX) * ax[:, d].astype(np.float32)[:, None, None]
        plane = grid[d, :m].reshape(k, r, c)
        np.add(along + half, acr, out=plane)
        np.add(along - half, acr, out=grid[d, m : 2 * m].reshape(k, r, c))
    vals = cv2.remap(gray, grid[0].reshape(rows, _ROW), grid[1].reshape(rows, _ROW), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(-1)
    step = np.abs(vals[:m].astype(np.int16) - vals[m : 2 * m]).astype(np.float64).reshape(k, r, c)
    # the window's centres: halfway between the two points of each step
    cx = 0.5 * (grid[0, :m] + grid[0, m : 2 * m])
    cy = 0.5 * (grid[1, :m] + grid[1, m : 2 * m])
    inside = ((cx >= 0.0) & (cx <= w - 1.0) & (cy >= 0.0) & (cy <= h - 1.0)).reshape(k, r, c)
    return step, inside
