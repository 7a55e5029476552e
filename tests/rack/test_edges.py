"""Edge search: sub-pixel accuracy, polarity, bounded range."""

from __future__ import annotations

import cv2
import numpy as np

from companion.vision.rack.edges import search_edges


def _step_image(edge_x: float, left: float, right: float, width: int = 200, height: int = 60) -> np.ndarray:
    """Anti-aliased vertical step at x = edge_x (pixel-centre convention), blurred a little."""
    x = np.arange(width, dtype=np.float64)
    frac = np.clip(x + 0.5 - edge_x, 0.0, 1.0)  # coverage of the right intensity in each pixel
    row = left + (right - left) * frac
    img = np.tile(row, (height, 1)).astype(np.float32)
    return np.asarray(cv2.GaussianBlur(img, (0, 0), 1.0))


def test_subpixel_edge_position() -> None:
    for edge_x in (100.0, 100.3, 100.5, 100.8):
        img = _step_image(edge_x, 200.0, 60.0)
        uv = np.array([[96.0, 30.0], [104.5, 20.0]])
        n = np.array([[1.0, 0.0], [1.0, 0.0]])
        m = search_edges(img, uv, n, np.array([-1.0, 0.0]), 10, 5.0)
        assert m.found.all()
        np.testing.assert_allclose(uv[:, 0] + m.offset_px, edge_x, atol=0.08)
        np.testing.assert_array_equal(m.sign, [-1.0, -1.0])


def test_polarity_rejects_the_opposite_edge() -> None:
    # Bright band between two edges: rising at x = 80, falling at x = 100.
    img = np.minimum(_step_image(80.0, 50.0, 200.0), _step_image(100.0, 200.0, 50.0))
    uv = np.array([[92.0, 30.0]])
    n = np.array([[1.0, 0.0]])
    rising = search_edges(img, uv, n, np.array([1.0]), 15, 5.0)
    falling = search_edges(img, uv, n, np.array([-1.0]), 15, 5.0)
    assert rising.found[0] and falling.found[0]
    assert abs(92.0 + rising.offset_px[0] - 80.0) < 0.15
    assert abs(92.0 + falling.offset_px[0] - 100.0) < 0.15


def test_bounded_range_and_flat_image() -> None:
    img = _step_image(150.0, 200.0, 60.0)
    m = search_edges(img, np.array([[100.0, 30.0]]), np.array([[1.0, 0.0]]), np.array([0.0]), 12, 5.0)
    assert not m.found[0]  # the only edge is 50 px away
    flat = np.full((60, 200), 90.0, dtype=np.float32)
    m = search_edges(flat, np.array([[100.0, 30.0]]), np.array([[0.0, 1.0]]), np.array([0.0]), 12, 5.0)
    assert not m.found[0]


def test_expected_inner_profile_prefers_the_limb_over_a_stronger_ground_edge() -> None:
    # A dark limb (x = 100) rising inwards into pale cladding (x < 100), then shadowed ground (x 100..105)
    # and lit ground beyond: the lit/shadow step at 105 is stronger than the limb's, with the same sign.
    x = np.arange(200, dtype=np.float64)
    row = np.where(x < 100, 60.0 + 4.0 * np.clip(100 - x, 0, 25), np.where(x < 105, 80.0, 180.0))
    img = np.asarray(cv2.GaussianBlur(np.tile(row, (40, 1)).astype(np.float32), (0, 0), 0.8))
    uv = np.array([[101.0, 20.0]])
    n = np.array([[1.0, 0.0]])  # outward: from the pipe to the ground
    plain = search_edges(img, uv, n, np.array([1.0]), 8, 5.0)
    assert abs(101.0 + plain.offset_px[0] - 105.0) < 0.6  # gradient alone: the shadow boundary
    # The limb's inner profile, as learned at the true edge (a falling ramp towards the limb).
    at_limb = search_edges(img, np.array([[100.0, 20.0]]), n, np.array([1.0]), 1, 5.0, inner_ref=np.zeros((1, 8)))
    ref = at_limb.inner
    assert ref.shape == (1, 8) and abs(np.linalg.norm(ref) - 1.0) < 1e-6
    matched = search_edges(img, uv, n, np.array([1.0]), 8, 5.0, inner_ref=ref)
    assert matched.found[0] and abs(101.0 + matched.offset_px[0] - 100.0) < 0.6
    # No reference (zero row): the plain search.
    none = search_edges(img, uv, n, np.array([1.0]), 8, 5.0, inner_ref=np.zeros((1, 8)))
    np.testing.assert_allclose(none.offset_px, plain.offset_px)


def _limb_image(edge_x: float, radius_px: float, limb: float, centre: float, ground: float,
                blur_px: float = 0.8, width: int = 200, height: int = 40) -> np.ndarray:
    """A cylinder's limb at x = edge_x (pipe on the left): its shading goes from `centre` to `limb`
    as the square root of the distance from the silhouette (the normal of a cylinder turns that way),
    the ground right of it; 8x supersampled (pixel area), then blurred (optics)."""
    xs = (np.arange(width * 8, dtype=np.float64) + 0.5) / 8.0 - 0.5  # pixel-centre convention
    d = np.clip((edge_x - xs) / radius_px, 0.0, 1.0)
    row = np.where(xs < edge_x, limb + (centre - limb) * np.sqrt(d), ground)
    row = row.reshape(width, 8).mean(axis=1)
    img = np.tile(row, (height, 1)).astype(np.float32)
    return np.asarray(cv2.GaussianBlur(img, (0, 0), blur_px))


def test_silhouette_of_a_shaded_limb_where_the_gradient_peak_is_inside() -> None:
    # Pale cladding darkening towards its limb over a ground of about the limb's brightness: the
    # steepest gradient lies inside the pipe; the silhouette fit finds the silhouette itself.
    from companion.vision.rack.edges import refine_silhouette

    n = np.array([[1.0, 0.0]] * 3)
    for edge_x in (100.0, 100.3, 100.6):
        for limb, ground in ((95.0, 110.0), (60.0, 110.0), (120.0, 40.0)):
            img = _limb_image(edge_x, 40.0, limb, 175.0, ground)
            uv = np.array([[97.0, 10.0], [99.5, 20.0], [102.0, 30.0]])
            m = search_edges(img, uv, n, np.zeros(3), 6, 2.0)  # the strongest gradient, either sign
            assert m.found.all()
            refined = refine_silhouette(img, uv, n, m.offset_px)
            np.testing.assert_allclose(uv[:, 0] + refined, edge_x, atol=0.35)  # the gradient peak: up to 2.6 px off
    # the case that motivates it: the gradient peak is more than a pixel inside
    img = _limb_image(100.3, 40.0, 95.0, 175.0, 110.0)
    m = search_edges(img, np.array([[100.0, 20.0]]), np.array([[1.0, 0.0]]), np.array([-1.0]), 8, 2.0)
    assert 100.0 + m.offset_px[0] < 100.3 - 1.0


def test_inner_windows_equal_the_direct_normalisation_bit_for_bit() -> None:
    # The window-major form (speed, issue #14) must give exactly what the per-window reductions give.
    from companion.vision.rack.edges import _inner_windows

    rng = np.random.default_rng(14)
    for M, R in ((3, 5), (8, 12), (13, 7), (8, 1)):
        n_cand = 2 * R + 1
        # Blurred-image profiles (not exact in float32) and a flat one (norm floor).
        prof = (255.0 * rng.random((40, n_cand + M + 2))).astype(np.float32)
        prof[0] = 17.25
        w = np.lib.stride_tricks.sliding_window_view(prof[:, 1:], M, axis=1)[:, :n_cand, :]
        w = w - w.mean(axis=2, keepdims=True)
        direct = w / np.maximum(np.sqrt((w * w).sum(axis=2, keepdims=True)), 1e-3)
        fast = _inner_windows(prof, M, n_cand)
        assert fast.flags.c_contiguous and fast.dtype == np.float32
        np.testing.assert_array_equal(fast, direct)


def test_distance_prior_prefers_the_limb_over_a_stronger_edge_a_few_pixels_out() -> None:
    # A faint limb step (40 grey levels) at x = 100 and a strong ground step (120) of the same sign at x = 105.
    img = np.maximum(_step_image(100.0, 60.0, 100.0), _step_image(105.0, 60.0, 180.0))
    uv = np.array([[100.0, 30.0]])
    n = np.array([[1.0, 0.0]])
    flat = search_edges(img, uv, n, np.array([0.0]), 12, 5.0)  # the default: a Gaussian as wide as the range
    near = search_edges(img, uv, n, np.array([0.0]), 12, 5.0, prior_sigma_px=2.0)
    assert flat.found[0] and near.found[0]
    assert abs(flat.offset_px[0] - 5.0) < 0.6  # the strongest edge in range
    assert abs(near.offset_px[0]) < 0.2  # the nearest one that is strong enough for its distance


def _grating_beyond_a_shaded_limb() -> np.ndarray:
    # Pale cladding falling to a shaded limb (60) at x = 100, a dark grating bar (20) from 100 to 103 and
    # a bright one (150) beyond: the limb's step (60 -> 20) is weaker than the bar's (20 -> 150) 3 px out,
    # and of the other sign (with both polarities accepted, as on a limb whose contrast changes sign).
    x = np.arange(200, dtype=np.float64)
    row = np.where(x < 100, 60.0 + 3.0 * np.clip(100 - x, 0, 25), np.where(x < 103, 20.0, 150.0))
    return np.asarray(cv2.GaussianBlur(np.tile(row, (40, 1)).astype(np.float32), (0, 0), 0.8))


def test_innermost_edge_takes_the_limb_before_a_stronger_grating_edge() -> None:
    img = _grating_beyond_a_shaded_limb()
    uv = np.array([[100.0, 20.0]])
    n = np.array([[1.0, 0.0]])  # outward: from the pipe to the ground
    strongest = search_edges(img, uv, n, np.array([0.0]), 8, 5.0)
    inner = search_edges(img, uv, n, np.array([0.0]), 8, 5.0, innermost_ratio=0.3)
    assert strongest.found[0] and inner.found[0]
    assert abs(strongest.offset_px[0] - 2.5) < 0.6  # the grating's bright bar
    assert abs(inner.offset_px[0] + 0.5) < 0.6  # the limb (the step between pixels 99 and 100)
    # Too high a ratio for the limb's share of the best score: the strongest edge again.
    high = search_edges(img, uv, n, np.array([0.0]), 8, 5.0, innermost_ratio=0.95)
    np.testing.assert_allclose(high.offset_px, strongest.offset_px)


def test_innermost_edge_leaves_samples_with_a_learnt_profile_alone() -> None:
    img = _grating_beyond_a_shaded_limb()
    uv = np.array([[100.0, 20.0], [100.0, 20.0]])
    n = np.array([[1.0, 0.0], [1.0, 0.0]])
    # The first sample's reference is the profile just inside the grating's edge (as if learnt there), the
    # second has none: only the second one takes the innermost candidate.
    at_bar = search_edges(img, np.array([[103.0, 20.0]]), n[:1], np.array([0.0]), 1, 5.0, inner_ref=np.zeros((1, 8)))
    ref = np.vstack([at_bar.inner, np.zeros((1, 8))])
    both = search_edges(img, uv, n, np.zeros(2), 8, 5.0, inner_ref=ref, innermost_ratio=0.3)
    assert both.found.all()
    assert abs(both.offset_px[0] - 2.5) < 0.6
    assert abs(both.offset_px[1] + 0.5) < 0.6


def test_innermost_edge_ignores_a_maximum_at_the_end_of_the_range() -> None:
    # A weaker step (60 grey levels) 4 px inside the limb's (80) whose gradient peaks at the inner end of a
    # 4 px range: cut off there (its true peak may lie beyond), it is not a candidate; the limb is.
    x = np.arange(200)
    row = np.where(x <= 95, 60.0, np.where(x < 100, 120.0, 200.0))
    img = np.tile(row, (40, 1)).astype(np.float32)
    uv = np.array([[100.0, 20.0]])
    n = np.array([[1.0, 0.0]])
    plain = search_edges(img, uv, n, np.array([1.0]), 4, 5.0)
    inner = search_edges(img, uv, n, np.array([1.0]), 4, 5.0, innermost_ratio=0.1)
    assert plain.found[0] and inner.found[0]
    assert abs(plain.offset_px[0] + 0.5) < 0.6
    np.testing.assert_allclose(inner.offset_px, plain.offset_px)
