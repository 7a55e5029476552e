"""The camera's position along the pipes from a crossing pipe, searched wide when it comes into view.

Along parallel pipes only texture and ground points carry the position, from frame to frame, and
they drift (`along_pipe.py`). A crossing pipe is the one thing that corrects it, but the tracker's
edge search reaches `search_range_px` from the prediction: once the drift is larger, the crossing
pipe's limbs are matched to whatever lies there. On `companion sim`'s field frames
(`bench/rack_field_loop.py --library --prior-std-deg 0 --seed 1`, 2026-11-28) the pose was 11 cm
behind along pipe 3 as the crossing pipe came into view, 20 px at its depth; its upper limb was
matched to the edge of its own highlight and the pass ended 37 cm off, which no later frame undid.

This module scores every shift of the camera along the rack's y axis (the pipes' direction) on a
grid by the crossing pipes' two limbs at once, as `gap_scan` scores a pipe's shift across the rack:
per limb the mean absolute gradient over its samples, divided by 1 + the std of the grey level just
inside it / `inside_scale` (the cladding is one grey all along the limb; a pipe's highlight or the
ground is not), and the smaller of the two limbs' (a pipe shows both its limbs or it is not there).
Pure function, vectorized over samples and shifts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.gap_scan import pipe_score, shifted_profiles
from companion.vision.rack.limbs import sample_limbs
from companion.vision.rack.model import PipeArrays

# A pipe counts as crossing the parallel ones when its axis is at least 45 deg from theirs (rack y).
_CROSSING_MAX_COS = 0.7


@dataclass(frozen=True)
class AlongScan:
    """The best shift of the camera along rack +y (m; 0 when nothing was scanned), its score, the score without a
    shift and the best score more than the crossing pipes' diameter from the best shift (grey levels per 2 px; 0
    when no crossing pipe shows both limbs); `at_edge`: the best lies at the end of the range (the truth may lie
    beyond it)."""

    shift_m: float
    score: float
    score_at_zero: float
    runner_up: float = 0.0
    at_edge: bool = False


def crossing_pipes(pipes: PipeArrays) -> np.ndarray[Any, np.dtype[np.intp]]:
    """Indices of the pipes whose axis crosses the rack's y axis (the parallel pipes' direction)."""
    return np.flatnonzero(np.abs(pipes.directions[:, 1]) < _CROSSING_MAX_COS)


def scan_along(
    T_rack_cam: FloatArray,
    camera: PinholeCamera,
    pipes: PipeArrays,
    image_f32: np.ndarray[Any, np.dtype[np.float32]],
    range_m: float,
    step_m: float = 0.005,
    samples_per_limb: int = 24,
    margin_px: float = 6.0,
    inside_px: float = 4.0,
    inside_scale: float = 10.0,
) -> AlongScan:
    """Score camera positions `T_rack_cam` shifted by -`range_m`..`range_m` (m) along rack +y by the crossing pipes.

    A shift s of the camera moves each limb sample by -s J R_rack_camᵀ e_y (first order). A crossing
    pipe's score at s is min(m_left, m_right) with m = mean |gradient| over the limb's samples / (1 + std
    over them of the grey level `inside_px` inside the limb / `inside_scale`); the shift's score is the
    sum over the crossing pipes that show at least 4 samples on each limb. Ties go to the smaller shift.
    """
    crossing = crossing_pipes(pipes)
    none = AlongScan(0.0, 0.0, 0.0)
    if crossing.size == 0 or not range_m > 0.0:
        return none
    samples = sample_limbs(T_rack_cam, camera, pipes, samples_per_limb, margin_px, 12.0, 0.1, 3.0)
    on = np.isin(samples.pipe, crossing)
    if np.count_nonzero(on) < 8:
        return none
    e_y_cam = T_rack_cam[:3, :3][1, :]  # the rack's +y in the camera frame
    duv_ds = -(samples.J_uv_pcam[on] @ e_y_cam)  # (N, 2) px per metre of the camera's move along +y
    if not np.all(np.isfinite(duv_ds)):  # a far-off pose (a relock's first guess): nothing to score
        return none
    n_half = int(np.ceil(range_m / step_m))
    shifts = step_m * np.arange(-n_half, n_half + 1, dtype=np.float64)
    gs, ins = shifted_profiles(samples.uv[on], samples.normal_px[on], duv_ds, image_f32, shifts, range_m, inside_px)
    limb = samples.limb[on]
    total = np.zeros(shifts.size)
    seen = False
    for m in crossing.tolist():
        score = pipe_score(gs, ins, limb, m, inside_scale)
        if score is None:
            continue
        total += score
        seen = True
    if not seen:
        return none
    best = int(np.argmax(total - 1e-6 * np.abs(shifts)))
    # The runner-up away from the best (beyond the crossing pipes' diameter): a second place as good is
    # another structure that looks like the pipe, and so may the best be.
    far = np.abs(shifts - shifts[best]) > 2.0 * float(np.max(pipes.radii[crossing]))
    second = float(np.max(total[far])) if np.any(far) else 0.0
    return AlongScan(float(shifts[best]), float(total[best]), float(total[n_half]), second,
                     abs(best - n_half) >= n_half - 1)
