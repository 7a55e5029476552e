"""First-frame search for the pipes' gaps: each pipe's shift across the rack, by its two limbs at once.

With a model whose gaps are wrong by decimetres, the tracker's coarse-to-fine first search has to
look that far for every limb, and over a grating or painted lines parallel to the pipes it finds a
bar before the limb (stress bench, 2026-11-24: the fourth pipe of the wrong-gap rack locked 22 cm
off for good). A pipe, though, is a *pair* of edges at the distance its width gives, both moving
together when the pipe shifts along rack x: this module scores every shift of each pipe on a
grid by both of its limbs' gradients at once, which a single bar or line cannot satisfy.

The score of a shift multiplies, for each limb, its mean *absolute* gradient by a factor for how
steady the grey level just inside it is along the limb, 1 / (1 + std / `inside_scale`), and takes
the smaller of the two limbs' (a pipe shows both its limbs or is not there). Signed means (the first
version) cancel where the background changes brightness along a limb: a pale pipe over a grating is
brighter than one bar and darker than the next, and the right shift scored 5-8 grey levels against
25-30 for a shift whose "limbs" were the right limb of one pipe and of its neighbour (stress bench,
wrong-gap rack over a grating, 2026-11-26). Nor can the two limbs be asked to share a polarity: a lit
cylinder is brighter than the ground on its sunny limb and darker on its shaded one. What a wrong
shift cannot fake is the inside: at the right shift a few pixels inside each limb is the pipe's
cladding, the same grey all along the limb, while a limb placed on a neighbour's edge has the ground
(grating, shadows) inside. Absolute gradients alone found the gaps in 11 of 24 first frames of fresh
stress runs, with the inside factor in 23 (signed means: 1).

Pale cladding over a pale floor (concrete, photographs) shows limbs of 6-8 grey levels, and there the
geometric mean of the two limbs (the version before 2026-11-27) let one strong edge buy a weak one: the
widest pipe slid by its own half-gap until one of its "limbs" sat on the neighbour's limb (30-35 grey
levels) and the other on its own cladding's shading (5), 8.2 against 5.2 at the truth. Hence the smaller
of the two, and no two limbs of neighbouring pipes closer than `min_gap_m` (one image edge cannot be the
limb of both). First frames of the wrong-gap rack over three grounds, 60 fresh seeds each (seeds 100-159,
never part of the stress bench's matrix; docs/rack.md, "Sixteenth session"): grating / natural / concrete
51 / 44 / 21 -> 57 / 57 / 49 with gaps within 5 cm and the camera within 10 cm. Pure function,
vectorized over samples and shifts.
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


@dataclass(frozen=True)
class GapScan:
    """Cumulative gaps (m) after the scan, and per gap the best score (grey levels per 2 px; 0: not scanned)."""

    gaps: FloatArray
    score: FloatArray


def scan_gaps(
    T_rack_cam: FloatArray,
    camera: PinholeCamera,
    pipes: PipeArrays,
    gaps: FloatArray,
    image_f32: np.ndarray[Any, np.dtype[np.float32]],
    range_m: float,
    step_m: float = 0.005,
    samples_per_limb: int = 24,
    min_score: float = 3.0,
    margin_px: float = 6.0,
    inside_px: float = 4.0,
    inside_scale: float = 10.0,
    min_gap_m: float = 0.02,
) -> GapScan:
    """Shift each parallel pipe that a gap moves (all but the first) by -range_m..range_m along rack x.

    `T_rack_cam` the camera pose (rack frame), `pipes` the pipes at the current cumulative `gaps`
    (m, shape (n-1,)), `image_f32` the gray image. For a shift s the limb samples move along their
    normals by s times their image motion per metre of rack x (first order); the profile across each
    sample is read once (blurred by 1.5 px, one `cv2.remap`) and interpolated at every shift. A
    pipe's score at s is min(m_left, m_right), m = mean |gradient| over the limb's samples (grey
    levels per 2 px, either polarity, sample by sample) / (1 + std over the samples of the grey level
    `inside_px` inside the limb / `inside_scale`); the shifts maximizing the summed score with every gap
    at least `min_gap_m` (m; or the model's own gap where that is smaller) are taken where they reach
    `min_score` and both limbs have at least 4 samples in view, else that gap is kept.
    """
    out = np.asarray(gaps, dtype=np.float64).copy()
    score_out = np.zeros(out.size)
    samples = sample_limbs(T_rack_cam, camera, pipes, samples_per_limb, margin_px, 12.0, 0.1, 3.0)
    n = samples.uv.shape[0]
    if n == 0 or out.size == 0:
        return GapScan(out, score_out)
    e_x_cam = T_rack_cam[:3, :3][0, :]  # the rack's +x in the camera frame
    duv_ds = samples.J_uv_pcam @ e_x_cam  # (N, 2) px per metre of the pipe's shift
    shifts = np.arange(-range_m, range_m + 0.5 * step_m, step_m)
    gs, ins = shifted_profiles(samples.uv, samples.normal_px, duv_ds, image_f32, shifts, range_m, inside_px)
    # Score table (gaps, shifts); gaps whose pipe is not seen well keep a flat zero row.
    table = np.zeros((out.size, shifts.size))
    seen = np.zeros(out.size, dtype=bool)
    for m in np.unique(samples.pipe):
        gi = int(pipes.gap_index[m])
        if gi < 0:
            continue
        score = pipe_score(gs, ins, samples.limb, m, inside_scale)
        if score is None:
            continue
        table[gi] = score
        seen[gi] = True
    table[table < min_score] = 0.0
    pick = _ordered_best(out, shifts, table - 1e-6 * np.abs(shifts)[None, :], min_gap_m)  # ties: the model's gap
    for g_idx in np.flatnonzero(seen & (table[np.arange(out.size), pick] > 0.0)).tolist():
        out[g_idx] = out[g_idx] + shifts[pick[g_idx]]
        score_out[g_idx] = table[g_idx, pick[g_idx]]
    return GapScan(out, score_out)


def pipe_score(
    gs: FloatArray, ins: FloatArray, limb: np.ndarray[Any, np.dtype[np.intp]], m: int, inside_scale: float
) -> FloatArray | None:
    """Pipe `m`'s score per shift (S,) from its samples' shifted gradients `gs` and inside grey levels `ins`
    ((N, S), `shifted_profiles`; `limb` (N,) each sample's limb index): min over its two limbs of the mean
    |gradient| / (1 + std of the inside grey level / `inside_scale`). None when a limb has fewer than 4 samples."""
    left = limb == 2 * m
    right = limb == 2 * m + 1
    if left.sum() < 4 or right.sum() < 4:
        return None
    mag_l = np.abs(gs[left]).mean(axis=0) / (1.0 + ins[left].std(axis=0) / inside_scale)
    mag_r = np.abs(gs[right]).mean(axis=0) / (1.0 + ins[right].std(axis=0) / inside_scale)
    return np.asarray(np.minimum(mag_l, mag_r))


def shifted_profiles(
    uv: FloatArray, normal_px: FloatArray, duv_ds: FloatArray, image_f32: np.ndarray[Any, np.dtype[np.float32]],
    shifts: FloatArray, range_m: float, inside_px: float,
) -> tuple[FloatArray, FloatArray]:
    """Each limb sample's gradient across its limb (N, S) (grey levels per 2 px, signed along its outward
    normal) and the grey level `inside_px` inside it (N, S), with the sample moved by `shifts` (S,) (m) times its image
    motion `duv_ds` (N, 2) (px per m; only the part along its normal counts, first order). The samples sit at
    pixels `uv` (N, 2) with unit outward image normals `normal_px` (N, 2).

    The profile across each sample is read once (blurred by 1.5 px, one `cv2.remap`, wide enough for
    `range_m`) and interpolated at every shift.
    """
    n = uv.shape[0]
    a = np.sum(duv_ds * normal_px, axis=1)  # along each sample's normal
    K = int(np.ceil(np.max(np.abs(a)) * range_m)) + 2
    k = np.arange(-K - 1, K + 2, dtype=np.float32)
    nrm = normal_px.astype(np.float32)
    mx = uv[:, 0:1].astype(np.float32) + k[None, :] * nrm[:, 0:1]
    my = uv[:, 1:2].astype(np.float32) + k[None, :] * nrm[:, 1:2]
    smooth = np.asarray(cv2.GaussianBlur(image_f32, (0, 0), 1.5), dtype=np.float32)
    prof = cv2.remap(smooth, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    g = prof[:, 2:] - prof[:, :-2]  # (N, 2K+1) at k = -K..K
    pos = np.clip(a[:, None] * shifts[None, :] + K, 0.0, 2.0 * K - 1e-6)  # fractional index (N, S)
    i0 = np.floor(pos).astype(np.intp)
    f = pos - i0
    rows = np.arange(n)[:, None]
    gs = (1.0 - f) * g[rows, i0] + f * g[rows, np.minimum(i0 + 1, 2 * K)]
    # Grey level `inside_px` inside each limb (the pipe's cladding when the shift is right), per shift.
    posi = np.clip(pos + 1.0 - inside_px, 0.0, 2.0 * K + 2 - 1e-6)
    j0 = np.floor(posi).astype(np.intp)
    fj = posi - j0
    ins = (1.0 - fj) * prof[rows, j0] + fj * prof[rows, np.minimum(j0 + 1, 2 * K + 2)]
    return gs, ins


def _ordered_best(
    gaps: FloatArray, shifts: FloatArray, table: FloatArray, min_gap_m: float = 0.0
) -> np.ndarray[Any, np.dtype[np.intp]]:
    """Shift index per gap maximizing the summed score with no gap below min(`min_gap_m`, the model's own
    gap) (no overlap, and no limb shared by two pipes; a rack drawn with touching pipes stays drawn so).

    Dynamic programming over the gaps in order: the best total for gap k at shift j is its score plus
    the best total of gap k-1 over the shifts that leave d̄_{k-1} + floor_k <= d̄_k (and d̄_0 >= floor_0).
    Without this a pipe can take its neighbour's limbs (widths differ by a few centimetres only). When no
    assignment satisfies the floors, every gap keeps the model's value (the shift nearest 0).
    """
    n, S = table.shape
    value = gaps[:, None] + shifts[None, :]  # candidate cumulative gaps (n, S)
    # Never ask for more room than the model itself leaves between two pipes (a rack drawn touching).
    floor = np.minimum(min_gap_m, np.maximum(np.diff(np.concatenate([[0.0], gaps])), 0.0))
    total = np.where(value[0] >= floor[0], table[0], -np.inf)
    back = np.zeros((n, S), dtype=np.intp)
    for k in range(1, n):
        order = np.argsort(value[k - 1])
        run_best = np.maximum.accumulate(total[order])
        vals = total[order]
        run_arg = order[np.maximum.accumulate(np.where(vals >= run_best, np.arange(S), 0))]
        # last candidate of gap k-1 with value <= value[k, j] - floor[k]
        idx = np.searchsorted(value[k - 1][order], value[k] - floor[k], side="right") - 1
        ok = idx >= 0
        new = np.full(S, -np.inf)
        new[ok] = table[k, ok] + run_best[idx[ok]]
        back[k, ok] = run_arg[idx[ok]]
        total = new
    pick = np.zeros(n, dtype=np.intp)
    if not np.isfinite(np.max(total)):  # no assignment keeps the pipes apart: keep the model's gaps
        return np.full(n, int(np.argmin(np.abs(shifts))), dtype=np.intp)
    pick[-1] = int(np.argmax(total))
    for k in range(n - 1, 0, -1):
        pick[k - 1] = back[k, pick[k]]
    return pick
