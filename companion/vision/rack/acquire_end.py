"""Along-pipe position from the rack's end: where the parallel pipes' limbs stop in the image.

The pipes' edges fix the camera across the pipes, in height and in attitude, but not along them:
an acquisition without a crossing pipe in view keeps the prior's y (metres off after a start
"somewhere near the rack"). The rack's ends do fix it: seen from above, every limb of a parallel
pipe ends at rack y = 0 (and y = length). `rack_end_fix` samples the image gradient across each
limb line predicted at the given pose, extended a span beyond the end, finds the along-pipe
position where the limbs' edges stop (one step shared by all limbs) and returns the correction
to the camera's y, or `found = False` when no end is in view, the step is weak, or two places
explain it alike. Vectorized: every sample of every limb in one `cv2.remap`.

Frames: `rack` (z up, pipes along +y), `cam` (OpenCV optical); `T_rack_cam` the camera pose in
the rack frame. Pure: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.vision.rack.limbs import limb_lines
from companion.vision.rack.model import RackModel

__all__ = ["RackEndFix", "rack_end_fix"]


@dataclass(frozen=True)
class RackEndFix:
    """`found`: an end of the rack was located; `dy_m`: add to the camera's rack y (m); `end_y_m`:
    the end used (0 or the rack's length, rack y); `agreement`: fraction of the limb samples whose
    edge presence agrees with the step (1 = a clean end); `num_limbs`: limbs seen on both sides."""

    found: bool
    dy_m: float
    end_y_m: float
    agreement: float
    num_limbs: int


_NOT_FOUND = RackEndFix(False, 0.0, 0.0, 0.0, 0)


def rack_end_fix(
    image: Any, model: RackModel, camera: PinholeCamera, T_rack_cam: Any, *, span_m: float = 1.0,
    step_m: float = 0.01, search_px: int = 3, min_contrast: float = 8.0, margin_px: float = 6.0,
    min_side_m: float = 0.15, min_agreement: float = 0.8, side_agreement: float = 0.5, distinct_m: float = 0.08,
    ambiguity: float = 0.05,
) -> RackEndFix:
    """Locate an end of `model`'s parallel pipes in `image` ((H, W) uint8) near the pose `T_rack_cam`.

    The limb lines are sampled every `step_m` (rack y) within `span_m` of each end, the strongest
    grey step within `search_px` across the line (either polarity) is the edge strength; an edge is
    present when it reaches `min_contrast` and half the 90th percentile of the limb's strengths. The end
    is where presence switches: the position maximising the fraction of samples that agree (edge
    on the rack's side in at least `side_agreement` of its samples, none beyond in at least
    `min_agreement`), with at least two limbs
    seen over `min_side_m` on both sides. It is accepted when the mean of the two reaches
    `min_agreement` and no other local maximum `distinct_m` or more away comes within `ambiguity`
    of it.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 2 or img.shape != (camera.height, camera.width):
        raise InputError(f"image: expected ({camera.height}, {camera.width}) uint8, got {img.shape} {img.dtype}")
    T = check_transform(T_rack_cam, "T_rack_cam")
    if not (span_m > 0 and step_m > 0 and search_px >= 1):
        raise InputError("span_m, step_m, search_px: must be positive")
    pipes = model.pipe_arrays()
    n = model.num_parallel
    o = T[:3, 3]
    lines = limb_lines(o, pipes)
    R = T[:3, :3]
    offsets = np.arange(-span_m, span_m + 0.5 * step_m, step_m)  # along y, relative to the end
    best = _NOT_FOUND
    for end_y in (0.0, float(model.length)):
        # (L, S, 3) points on the limb lines of the parallel pipes at rack y = end + offset
        pt = lines.point[: 2 * n]
        d = lines.direction[: 2 * n]
        s = (end_y + offsets[None, :] - pt[:, 1:2]) / d[:, 1:2]
        P = pt[:, None, :] + s[..., None] * d[:, None, :]
        Q = P + 0.02 * lines.outward[: 2 * n][:, None, :]
        uv = camera.project((P.reshape(-1, 3) - o) @ R).reshape(P.shape[0], P.shape[1], 2)
        uq = camera.project((Q.reshape(-1, 3) - o) @ R).reshape(P.shape[0], P.shape[1], 2)
        nrm = uq - uv
        nrm /= np.maximum(np.linalg.norm(nrm, axis=2, keepdims=True), 1e-9)
        ok = np.all(np.isfinite(uv), axis=2) & np.all(np.isfinite(nrm), axis=2)
        uv = np.where(ok[..., None], uv, -100.0)
        inside = ok & (uv[..., 0] >= margin_px) & (uv[..., 0] <= camera.width - 1 - margin_px) \
            & (uv[..., 1] >= margin_px) & (uv[..., 1] <= camera.height - 1 - margin_px)
        if np.count_nonzero(inside) < 20:
            continue
        strength = _edge_strength(img, uv, np.where(ok[..., None], nrm, 0.0), search_px)
        fix = _step(strength, inside, offsets, end_y, step_m, min_contrast, min_side_m, min_agreement,
                    side_agreement, distinct_m, ambiguity)
        if fix.found and (not best.found or fix.agreement > best.agreement):
            best = fix
    return best


def _edge_strength(img: Any, uv: FloatArray, nrm: FloatArray, search_px: int) -> FloatArray:
    """(L, S) strongest |grey step| over 2 px across the line within ±search_px of it."""
    k = np.arange(-search_px - 1, search_px + 2, dtype=np.float64)  # sample offsets across
    pts = uv[..., None, :] + k[None, None, :, None] * nrm[..., None, :]  # (L, S, K, 2)
    mx = pts[..., 0].astype(np.float32).reshape(-1, k.size)
    my = pts[..., 1].astype(np.float32).reshape(-1, k.size)
    prof = cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    steps = np.abs(prof[:, 2:] - prof[:, :-2])  # central differences over 2 px
    return np.asarray(steps.max(axis=1).reshape(uv.shape[0], uv.shape[1]), dtype=np.float64)


def _step(strength: FloatArray, inside: Any, offsets: FloatArray, end_y: float, step_m: float,
          min_contrast: float, min_side_m: float, min_agreement: float, side_agreement: float,
          distinct_m: float, ambiguity: float) -> RackEndFix:
    """The along-pipe position where the edges stop, scored over all limbs (see `rack_end_fix`)."""
    # Per limb: half its 90th percentile (a limb darkened by shading is weaker than its neighbours).
    srt = np.sort(np.where(inside, strength, -np.inf), axis=1)  # the limb's samples in view last
    n_in = np.count_nonzero(inside, axis=1)
    k = srt.shape[1] - n_in + np.floor(0.9 * np.maximum(n_in - 1, 0)).astype(np.intp)
    p90 = np.where(n_in > 0, srt[np.arange(srt.shape[0]), np.minimum(k, srt.shape[1] - 1)], 0.0)
    present = (strength >= np.maximum(min_contrast, 0.5 * p90)[:, None]) & inside
    # On the rack side of the end (y > end at y = 0, y < end at y = length) the edges must be present.
    rack_side = 1.0 if end_y == 0.0 else -1.0
    S = offsets.size
    # Cumulative counts over the position index: samples before / after each candidate step.
    pres_c = np.cumsum(present, axis=1)
    ins_c = np.cumsum(inside, axis=1)
    tot_p, tot_i = pres_c[:, -1:], ins_c[:, -1:]
    before_p, before_i = pres_c[:, :-1], ins_c[:, :-1]  # samples with index <= j, candidates j in 0..S-2
    after_p, after_i = tot_p - before_p, tot_i - before_i
    if rack_side > 0:  # rack after the step: present after, absent before
        in_p, in_n, out_a, out_n = after_p, after_i, before_i - before_p, before_i
    else:
        in_p, in_n, out_a, out_n = before_p, before_i, after_i - after_p, after_i
    min_n = max(round(min_side_m / step_m), 1)
    both = (in_n >= min_n) & (out_n >= min_n)  # (L, S-1): the limb seen on both sides of the step
    num_limbs = np.count_nonzero(both, axis=0)
    # Edges present on the rack's side and absent beyond, each side on its own (a featureless image
    # is "absent" everywhere, a limb running out of the image "present" everywhere).
    frac_in = np.sum(np.where(both, in_p, 0), axis=0) / np.maximum(np.sum(np.where(both, in_n, 0), axis=0), 1)
    frac_out = np.sum(np.where(both, out_a, 0), axis=0) / np.maximum(np.sum(np.where(both, out_n, 0), axis=0), 1)
    frac = np.where((num_limbs >= 2) & (frac_in >= side_agreement) & (frac_out >= min_agreement),
                    0.5 * (frac_in + frac_out), 0.0)
    j = int(np.argmax(frac))
    if frac[j] < min_agreement:
        return _NOT_FOUND
    y_step = end_y + 0.5 * (offsets[j] + offsets[j + 1])
    # Another local maximum (the best within distinct_m around it) nearly as good: two places explain it.
    w = max(round(distinct_m / step_m), 1)
    local_max = np.asarray(cv2.dilate(frac.astype(np.float32)[None, :], np.ones((1, 2 * w + 1), np.uint8)))[0]
    peaks = (frac >= local_max - 1e-6) & (np.abs(np.arange(S - 1) - j) > w)
    if np.any(peaks & (frac >= frac[j] - ambiguity)):
        return _NOT_FOUND
    return RackEndFix(True, float(end_y - y_step), float(end_y), float(frac[j]), int(num_limbs[j]))
