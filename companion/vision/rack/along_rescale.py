"""The along-pipe travel the ground alone carried, rescaled when the ground's height is known better.

Over parallel pipes with no texture in view and no crossing pipe, the position along the pipes follows
the ground points only (`ground.py`), whose image motion measures the travel divided by the ground's
depth below the camera. With the ground's height wrong by a third, that stretch's travel is wrong by
about as much, and nothing corrects it later: texture points met further on are placed from the
drifted pose. Once something at a known depth measures the travel again (texture points on the pipes),
the ground's height is fitted against it and comes closer to the truth; the stretch's travel is then
what its image motion says at that height. That height is the mean over the frames whose travel the
texture measured (at least `MIN_HEIGHT_FRAMES` of them): one frame's height jitters by a decimetre,
which on a metre-long stretch would move the pose back and forth by centimetres. And a rescale is made
only when it is clear: at least `SIGNIFICANCE` times |S2| times the spread of those heights (their
standard deviation, floored at `MIN_HEIGHT_SPREAD_M`; the frames' heights are correlated, so it is not
divided by their number). Smaller corrections are left to the next texture-measured frames, and none
below `MIN_SHIFT_M` is made: that is the along-pipe noise of a frame's own solve, and a shift of half a
centimetre tipped a marginal run over (the stress bench's wrong-gap cell with the prior, 2026-12-02).
Nor one beyond `MAX_FRACTION` of the stretch's net travel: for a stretch flown at one ground height the
correction is the net travel times (z_i - z) / (c - z_i), beyond a half only for a ground height wrong
by half the camera's depth to it; larger ones come from back-and-forth steps booked at heights that
wandered, where the first-order depth model's own errors add up over the gross travel (the beam cell of
the stress bench's held-back seeds: -3.2 cm on a 3 cm net of a 363-frame stretch, which doubled its error).

Before any texture point measures a height, the long-baseline height filtered over the frames
(`ground_height.py`, `ground_height_vertical.py`) rescales the stretch once it is surer than
`FILTER_MAX_STD_M` (`filter_correction_m`): a flight along the pipes books its first seconds at the rough first
guess, and the spots may be seconds away.

Each ground-held frame i adds its along-pipe step dy_i (m, rack +y) measured at the camera height c_i
(m, rack z) and ground height z_i (m): its image motion is proportional to dy_i / (c_i - z_i), so at a
ground height z the step is dy_i (c_i - z) / (c_i - z_i). With S1 = sum of the steps as applied,
S2 = sum dy_i / (c_i - z_i) and S3 = sum dy_i c_i / (c_i - z_i), the travel at height z is S3 - z S2,
and the correction still to apply is S3 - z S2 - S1. Pure functions on a small frozen ledger.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

MIN_TEXTURE_POINTS = 3  # a frame with fewer texture points in its solve is held by the ground (the tracker's count)
MIN_DEPTH_M = 0.3  # below this the camera is at the ground: its depth ratio means nothing
MIN_HEIGHT_FRAMES = 10  # texture-measured frames whose ground heights are averaged before a rescale
MIN_HEIGHT_SPREAD_M = 0.05  # floor of the heights' spread in the significance test
SIGNIFICANCE = 3.0  # a rescale smaller than this many of its standard deviations is not made
MIN_SHIFT_M = 0.02  # nor one smaller than this
MAX_FRACTION = 0.5  # nor one larger than this fraction of the stretch's net travel
# A long-baseline height (`filter_correction_m`) is used once surer than this: half the first guess's 2 m, so
# once fits have told the filter something. The solver's floor for a handed height (0.5 m) waited 10-40 frames
# longer on the along cell, each booked at the first guess (docs/rack.md, "Thirty-sixth session on #14").
FILTER_MAX_STD_M = 1.0


@dataclass(frozen=True)
class AlongLedger:
    """The ground-held stretch since the last absolute along-pipe fix (all in metres, rack frame)."""

    applied_m: float = 0.0  # S1: the stretch's along-pipe travel as the pose has it
    per_depth: float = 0.0  # S2: sum of dy_i / (c_i - z_i) (unitless)
    height_weighted_m: float = 0.0  # S3: sum of dy_i c_i / (c_i - z_i)
    frames: int = 0  # ground-held frames in the stretch
    height_sum_m: float = 0.0  # sum of the ground heights of the texture-measured frames since
    height_frames: int = 0  # and their number
    height_sq_sum_m2: float = 0.0  # and the sum of their squares


def record_step(ledger: AlongLedger, dy_m: float, camera_z_m: float, ground_z_m: float) -> AlongLedger:
    """The ledger with one ground-held step `dy_m` (along the pipes) taken at camera height `camera_z_m` over
    the ground plane at `ground_z_m` (its height as the frame's solve used it); unchanged if the camera is
    not at least `MIN_DEPTH_M` above that plane."""
    depth = float(camera_z_m) - float(ground_z_m)
    if not depth >= MIN_DEPTH_M:
        return ledger
    return replace(ledger, applied_m=ledger.applied_m + float(dy_m),
                   per_depth=ledger.per_depth + float(dy_m) / depth,
                   height_weighted_m=ledger.height_weighted_m + float(dy_m) * float(camera_z_m) / depth,
                   frames=ledger.frames + 1)


def record_height(ledger: AlongLedger, ground_z_m: float) -> AlongLedger:
    """The ledger with the ground height `ground_z_m` (m) fitted on a frame whose travel texture measured."""
    return replace(ledger, height_sum_m=ledger.height_sum_m + float(ground_z_m),
                   height_frames=ledger.height_frames + 1,
                   height_sq_sum_m2=ledger.height_sq_sum_m2 + float(ground_z_m) ** 2)


def clear_correction_m(ledger: AlongLedger) -> float:
    """The along-pipe shift (m, rack +y) to the texture-measured frames' mean height (`correction_m`), or 0.0
    before `MIN_HEIGHT_FRAMES` of them, when it is not `SIGNIFICANCE` times its standard deviation or when it
    is smaller than `MIN_SHIFT_M` or larger than `MAX_FRACTION` of the stretch's net travel."""
    n = ledger.height_frames
    if n < MIN_HEIGHT_FRAMES:
        return 0.0
    mean = ledger.height_sum_m / n
    spread = max(float(np.sqrt(max(ledger.height_sq_sum_m2 / n - mean * mean, 0.0))), MIN_HEIGHT_SPREAD_M)
    shift = correction_m(ledger, mean)
    if abs(shift) < max(SIGNIFICANCE * abs(ledger.per_depth) * spread, MIN_SHIFT_M):
        return 0.0
    return shift if abs(shift) <= MAX_FRACTION * abs(ledger.applied_m) else 0.0


def filter_correction_m(ledger: AlongLedger, ground_z_m: float, ground_std_m: float) -> float:
    """The along-pipe shift (m, rack +y) to the long-baseline ground height `ground_z_m` (m, rack z; filtered
    over the frames, `ground_height.py` / `ground_height_vertical.py`) with standard deviation `ground_std_m`,
    while no texture point has measured a height in the stretch; 0.0 when that height is not yet surer than
    `FILTER_MAX_STD_M`, or the shift is smaller than its own standard deviation |S2| `ground_std_m` or
    `MIN_SHIFT_M`, or larger than `MAX_FRACTION` of the stretch's net travel.

    A stretch flown before that height was known was booked at the rough first guess (a 2 m standard
    deviation, a third too long on the stress bench's along cell), and no texture may come for seconds. The
    filtered height's own steps are far smaller than its spread, so one standard deviation (not the
    texture rule's `SIGNIFICANCE` over single frames' heights) is enough to keep it from shifting the pose
    back and forth; once texture points measure heights, `clear_correction_m` takes over."""
    if ledger.height_frames or not (np.isfinite(ground_std_m) and 0.0 < ground_std_m <= FILTER_MAX_STD_M):
        return 0.0
    shift = correction_m(ledger, ground_z_m)
    if abs(shift) < max(abs(ledger.per_depth) * float(ground_std_m), MIN_SHIFT_M):
        return 0.0
    return shift if abs(shift) <= MAX_FRACTION * abs(ledger.applied_m) else 0.0


def correction_m(ledger: AlongLedger, ground_z_m: float) -> float:
    """Along-pipe shift (m, rack +y) that brings the stretch's travel to what it is at ground height
    `ground_z_m`: S3 - z S2 - S1."""
    return ledger.height_weighted_m - float(ground_z_m) * ledger.per_depth - ledger.applied_m


def after_shift(ledger: AlongLedger, shift_m: float) -> AlongLedger:
    """The ledger once `shift_m` (from `correction_m`) has been applied to the pose: only S1 moves (the steps'
    image motion, hence S2 and S3, is what it was)."""
    return replace(ledger, applied_m=ledger.applied_m + float(shift_m))
