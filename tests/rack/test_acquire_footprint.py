"""The acquisition's "explained" share over the rack's footprint (`profile_scores(..., footprint_pitches)`).

A pencil profile is built by hand: a clutter floor, the limbs a pose predicts as peaks, the pipes' own
shading inside them, and ground stripes beside the rack; the share of the peak mass each pose explains
is checked against what the model can and cannot say about those peaks.
"""

from __future__ import annotations

import numpy as np

from companion.vision.rack.acquire_match import predict_limb_angles
from companion.vision.rack.acquire_profile import PencilProfile, profile_scores

BIN_RAD = 0.002
THETA0 = -2.6
X_AXES = np.array([0.0, 0.45, 0.9])  # three pipes, 45 cm apart
RADII = np.array([0.15, 0.15, 0.15])
FLOOR = 5.0


def _profile(peaks_rad: list[float], peak_height: float = 20.0) -> PencilProfile:
    """A profile at FLOOR with a peak of `peak_height` at each angle (one bin wide, smoothed like the real one)."""
    value = np.full(1500, FLOOR)
    for t in peaks_rad:
        b = int((t - THETA0) / BIN_RAD)
        value[b] = peak_height
        value[b - 1] = value[b + 1] = 0.5 * (peak_height + FLOOR)
    ref = float(value.max())  # the real profile's 99th percentile: its limbs when they fill the image
    pk = np.flatnonzero((value[1:-1] >= value[:-2]) & (value[1:-1] > value[2:]) & (value[1:-1] >= 0.5 * ref)) + 1
    return PencilProfile(theta0=THETA0, bin_rad=BIN_RAD, value=value, ref=ref,
                         peak_theta=THETA0 + (pk + 0.5) * BIN_RAD, peak_value=value[pk],
                         floor=float(np.median(value)))


def _scores(profile: PencilProfile, x_m: float, footprint: float | None) -> float:
    X, Z, S = np.array([x_m]), np.array([3.0]), np.array([1.0])
    _, explained = profile_scores(profile, X, Z, S, X_AXES, RADII, (THETA0, THETA0 + 1500 * BIN_RAD),
                                  lambda th: np.full(th.shape, 500.0), 1, 40.0, None, footprint)
    return float(explained[0])


def _limbs(x_m: float) -> np.ndarray:
    th, vis = predict_limb_angles(np.array([x_m]), np.array([3.0]), np.zeros(1), np.ones(1), X_AXES, RADII)
    assert vis.all()
    return th[0]


def test_ground_stripes_far_beside_the_rack_and_the_pipes_shading_do_not_count_against_it() -> None:
    limbs = _limbs(0.45)
    middles = [0.5 * (limbs[2 * m] + limbs[2 * m + 1]) for m in range(3)]  # highlights inside the pipes
    span = limbs.max() - limbs.min()
    stripes = [limbs.max() + span * k for k in (3.0, 3.3, 3.6, 3.9)]  # far beside the rack
    prof = _profile(list(limbs) + middles + stripes)
    whole = _scores(prof, 0.45, None)
    assert 0.4 < whole < 0.5  # 6 of 13 equal peaks
    assert _scores(prof, 0.45, 1.5) == 1.0


def test_a_real_pipe_next_to_the_footprint_counts_against_a_pose_one_pipe_off() -> None:
    # The true camera over the middle pipe sees all three; a pose one pipe over (x + 0.45) explains the
    # two pipes it puts in the places of pipes 1 and 2 and leaves pipe 0's limbs, a pitch beside its
    # footprint, unexplained.
    prof = _profile(list(_limbs(0.45)))
    assert _scores(prof, 0.45, 1.5) == 1.0
    off = _scores(prof, 0.0, 1.5)
    assert off < 0.8


def test_clutter_peaks_just_above_the_floor_weigh_little() -> None:
    limbs = _limbs(0.45)
    span = limbs.max() - limbs.min()
    # Gravel: many small peaks a little above the floor, inside the footprint's margin.
    gravel = list(limbs.max() + span * np.linspace(0.1, 0.4, 6))
    value_limbs = _profile(list(limbs) + gravel)
    strong = _scores(value_limbs, 0.45, 1.5)
    assert strong < 1.0  # as tall as the limbs: they count
    prof = _profile(list(limbs))
    for t in gravel:  # the same places, a fifth as tall above the floor
        b = int((t - THETA0) / BIN_RAD)
        prof.value[b] = FLOOR + 3.0
    ref = float(prof.value.max())
    pk = np.flatnonzero((prof.value[1:-1] >= prof.value[:-2]) & (prof.value[1:-1] > prof.value[2:])
                        & (prof.value[1:-1] >= 0.2 * ref)) + 1
    low = PencilProfile(theta0=THETA0, bin_rad=BIN_RAD, value=prof.value, ref=ref,
                        peak_theta=THETA0 + (pk + 0.5) * BIN_RAD, peak_value=prof.value[pk], floor=FLOOR)
    assert low.peak_theta.size == 12  # the gravel peaks are peaks of the profile
    assert _scores(low, 0.45, 1.5) == 1.0  # but below a quarter of the way from the floor to the limbs
    assert _scores(low, 0.45, None) < 1.0
