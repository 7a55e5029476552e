"""`corners.strong_corners` returns exactly OpenCV's Shi-Tomasi corners above the eigenvalue floor."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from companion.vision.rack import corners, corners_jit
from companion.vision.rack.corners import shi_tomasi, strong_corners


def _reference(gray: np.ndarray, mask: np.ndarray, max_corners: int, min_distance: float, ratio: float) -> np.ndarray:
    """The texture detector's former two passes: goodFeaturesToTrack, then the floor at each corner."""
    corners = cv2.goodFeaturesToTrack(gray, maxCorners=max_corners, qualityLevel=0.02, minDistance=min_distance,
                                      mask=mask, blockSize=7)
    if corners is None:
        return np.zeros((0, 2), dtype=np.float32)
    c = corners.reshape(-1, 2)
    ev = cv2.cornerMinEigenVal(gray, 7, ksize=3)
    floor = float(np.median(ev[mask > 0]))
    ci = np.rint(c).astype(np.intp)
    return c[ev[ci[:, 1], ci[:, 0]] >= ratio * floor]


def _scene(rng: np.random.Generator, kind: str) -> tuple[np.ndarray, np.ndarray]:
    h, w = 180, 260
    if kind == "spots":  # grey cladding, noise, a few dark spots (the texture detector's case)
        img = np.full((h, w), 150.0) + rng.normal(0.0, 3.0, (h, w))
        for _ in range(40):
            cv2.circle(img, (int(rng.integers(5, w - 5)), int(rng.integers(5, h - 5))), int(rng.integers(1, 4)),
                       float(rng.uniform(40, 110)), -1)
    elif kind == "noise":  # many corners of similar strength
        img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)), (0, 0), 1.2)
    else:  # a periodic pattern: many equal eigenvalues (the tie order matters)
        yy, xx = np.mgrid[0:h, 0:w]
        img = 128.0 + 100.0 * (((xx // 7) + (yy // 7)) % 2)
    gray = np.clip(img, 0, 255).astype(np.uint8)
    mask = np.zeros((h, w), dtype=np.uint8)
    cv2.fillConvexPoly(mask, np.array([[3, 10], [250, 0], [255, 170], [10, 179]], dtype=np.int32), 255)
    cv2.circle(mask, (100, 90), 12, 0, -1)
    return gray, mask


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("kind", ["spots", "noise", "checker"])
@pytest.mark.parametrize("ratio", [0.5, 3.0, 10.0])
def test_equal_to_opencv_then_floor(kind: str, ratio: float, compiled: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """Both selections: the compiled one (`corners_jit.py`) and the numpy one it replaces."""
    if not compiled:
        monkeypatch.setattr(corners, "kernels", lambda: None)
    elif corners_jit.kernels() is None:
        pytest.skip("numba not available here")
    rng = np.random.default_rng(140 + int(10 * ratio))
    gray, mask = _scene(rng, kind)
    for max_corners, min_distance in ((8, 12.0), (94, 12.0), (500, 5.0), (60, 12.4)):
        got = strong_corners(gray, mask, max_corners, min_distance, 0.02, 7, ratio)
        want = _reference(gray, mask, max_corners, min_distance, ratio)
        if got is None:  # degenerate map (only allowed for a non-positive median)
            assert float(np.median(cv2.cornerMinEigenVal(gray, 7, ksize=3)[mask > 0])) <= 0.0
            continue
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("kind", ["spots", "noise", "checker"])
def test_shi_tomasi_is_opencvs_detector(kind: str) -> None:
    """`shi_tomasi` (the compiled selection from OpenCV's eigenvalue map) returns `cv2.goodFeaturesToTrack`'s corners
    in its order, for the ground points' quality level and the texture's, dense and sparse, with ties (checker)."""
    rng = np.random.default_rng(150)
    gray, mask = _scene(rng, kind)
    for max_corners, min_distance, quality in ((8, 12.0, 0.01), (120, 12.0, 0.01), (500, 5.0, 0.02), (60, 12.4, 0.01),
                                               (40, 1.0, 0.05)):
        found = cv2.goodFeaturesToTrack(gray, maxCorners=max_corners, qualityLevel=quality, minDistance=min_distance,
                                        mask=mask, blockSize=7)
        want = np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2)
        got = shi_tomasi(gray, mask, max_corners, min_distance, quality, 7)
        assert got.dtype == np.float32 and got.shape[0] > 0
        np.testing.assert_array_equal(got, want)
    flat = np.full((40, 50), 90, dtype=np.uint8)
    assert shi_tomasi(flat, np.full((40, 50), 255, np.uint8), 10, 12.0, 0.01, 7).shape == (0, 2)
    assert shi_tomasi(gray, np.zeros_like(mask), 10, 12.0, 0.01, 7).shape == (0, 2)


def test_degenerate_maps_ask_for_the_fallback() -> None:
    flat = np.full((40, 50), 90, dtype=np.uint8)
    mask = np.full((40, 50), 255, dtype=np.uint8)
    assert strong_corners(flat, mask, 10, 12.0, 0.02, 7, 10.0) is None
    assert strong_corners(flat, np.zeros_like(mask), 10, 12.0, 0.02, 7, 10.0) is None


def test_median_equals_numpys() -> None:
    from companion.vision.rack.corners import _median

    rng = np.random.default_rng(1414)
    for _ in range(200):
        n = int(rng.integers(1, 3000))
        v = (rng.normal(size=n) * 10 ** rng.uniform(-8, 3)).astype(np.float32)
        if rng.random() < 0.3:
            v[: n // 2] = v[0]  # repeated values
        assert _median(v) == float(np.median(v))


def test_median_of_large_arrays_equals_numpys_when_the_bracket_misses_too() -> None:
    # Above 8192 values the middle rank is bracketed by a strided subsample; a periodic array whose period is the
    # stride (the subsample one value repeated) or a sorted one must still give numpy's median (the fallback).
    from companion.vision.rack.corners import _median

    rng = np.random.default_rng(1415)
    cases = [np.tile(np.arange(32, dtype=np.float32), 700), np.sort(rng.random(50_001).astype(np.float32)),
             np.sort(rng.random(50_000).astype(np.float32))[::-1].copy(), np.zeros(9000, dtype=np.float32)]
    for _ in range(40):
        n = int(rng.integers(8192, 250_000))
        v = (rng.exponential(size=n) ** 3 * 10 ** rng.uniform(-8, 3)).astype(np.float32)
        if rng.random() < 0.3:
            v[: n // 3] = v[1]  # a third tied
        cases.append(v)
    for v in cases:
        assert _median(v) == float(np.median(v))
