"""The edge check's split search (`acquire_edges`) returns what the tracker's `search_edges` returns."""

from __future__ import annotations

import numpy as np
import pytest

from companion.vision.rack.acquire_edges import normal_profiles, percentile, percentile_90, pick_edges
from companion.vision.rack.edges import search_edges


@pytest.mark.parametrize("range_px", [3, 4, 5, 10])
def test_profiles_read_once_then_picked_equal_search_edges(rng: np.random.Generator, range_px: int) -> None:
    img = rng.uniform(0.0, 255.0, size=(120, 160)).astype(np.float32)
    img[:, 70:] += 60.0  # a strong vertical step among the noise
    n = 300
    uv = np.column_stack([rng.uniform(-5.0, 165.0, n), rng.uniform(-5.0, 125.0, n)])  # some off the image
    ang = rng.uniform(-np.pi, np.pi, n)
    normal = np.column_stack([np.cos(ang), np.sin(ang)])
    prof = normal_profiles(img, uv, normal, range_px, 1.5)
    for polarity in (np.ones(n), -np.ones(n), np.zeros(n), rng.choice([-1.0, 0.0, 1.0], n)):
        ref = search_edges(img, uv, normal, polarity, range_px, 8.0, tangent_offset_px=1.5)
        got = pick_edges(prof, polarity, range_px, 8.0)
        assert np.any(ref.found)
        for name in ("offset_px", "found", "sign", "strength"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))


def test_no_samples_give_no_edges() -> None:
    prof = normal_profiles(np.zeros((10, 10), dtype=np.float32), np.zeros((0, 2)), np.zeros((0, 2)), 3, 1.5)
    assert pick_edges(prof, np.zeros(0), 3, 8.0).found.size == 0


@pytest.mark.parametrize("n", [1, 2, 3, 10, 11, 239, 240])
def test_percentile_90_equals_numpy(rng: np.random.Generator, n: int) -> None:
    x = rng.gamma(2.0, 20.0, size=n)
    assert percentile_90(x) == np.percentile(x, 90)
    ties = np.round(x / 10.0)
    assert percentile_90(ties) == np.percentile(ties, 90)
    for q in (0, 1, 50, 99, 100):
        assert percentile(x, q) == np.percentile(x, q)


def test_claimed_peaks_equal_the_brute_force_comparison(rng: np.random.Generator) -> None:
    from companion.vision.rack.acquire_profile import PencilProfile

    value = rng.uniform(0.0, 10.0, 400)
    pk = np.flatnonzero((value[1:-1] >= value[:-2]) & (value[1:-1] > value[2:])) + 1
    prof = PencilProfile(theta0=-0.7, bin_rad=0.003, value=value, ref=10.0,
                         peak_theta=-0.7 + (pk + 0.5) * 0.003, peak_value=value[pk])
    theta = rng.uniform(-0.75, 0.55, size=(50, 10))
    use = rng.uniform(size=theta.shape) < 0.8
    for tol_bins in (0, 1, 2, 5):
        tol = (tol_bins + 1) * prof.bin_rad
        brute = ((np.abs(prof.peak_theta[None, None, :] - theta[:, :, None]) <= tol) & use[:, :, None]).any(axis=1)
        np.testing.assert_array_equal(prof.claimed_peaks(theta, use, tol), brute)
