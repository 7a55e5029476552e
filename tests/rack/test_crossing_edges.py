"""Corners next to an occluder's outline across a pipe are found; marks on the cladding and its shading are not."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from companion.vision.rack.crossing_edges import on_crossing_edge

H, W = 240, 320
WIDTH_PX = 80.0


def _scene(angle_deg: float, occluder_deg: float, occluder: bool, spots: list[tuple[float, float]],
           rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A pipe through the image centre whose axis is `angle_deg` from the image's +y, shaded from dark limbs to a
    highlight off its centre line; dark spots at (along, across) px from the centre; optionally a mid-grey
    occluder (a beam with a dark face on its lower side) across it, `occluder_deg` from square, its lower outline
    through the centre. Returns the 8-bit image, the axis (2,), the normal (2,) and the centre (2,)."""
    a = np.radians(angle_deg)
    axis = np.array([np.sin(a), np.cos(a)])
    normal = np.array([-axis[1], axis[0]])
    centre = np.array([W / 2.0, H / 2.0])
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    rel = np.stack([xx - centre[0], yy - centre[1]], axis=-1)
    along, across = rel @ axis, rel @ normal
    u = across / (0.5 * WIDTH_PX)  # -1..1 limb to limb
    ground = 60.0 + 25.0 * (np.sin(xx / 3.0) * np.sin(yy / 4.0) > 0)  # a grating-like ground
    cladding = 40.0 + 190.0 * np.clip(1.0 - (u - 0.3) ** 2, 0.0, 1.0)  # dark limbs, highlight right of centre
    img = np.where(np.abs(u) <= 1.0, cladding, ground)
    for s_along, s_across in spots:
        img[np.hypot(along - s_along, across - s_across) <= 6.0] = 50.0
    if occluder:
        b = np.radians(occluder_deg)
        e = np.cos(b) * normal + np.sin(b) * axis  # the outline's direction
        n_out = np.array([-e[1], e[0]])
        if n_out @ axis < 0.0:
            n_out = -n_out
        d = rel @ n_out  # > 0 on the occluder's side (towards +axis)
        img = np.where((d > 0.0) & (d <= 5.0), 70.0, img)  # the beam's dark face
        img = np.where((d > 5.0) & (d <= 45.0), 150.0, img)  # the beam's grey flange
    img = img + 6.0 * rng.standard_normal(img.shape)
    img = cv2.GaussianBlur(np.clip(img, 0, 255).astype(np.float32), (0, 0), 0.7)
    return np.clip(img, 0, 255).astype(np.uint8), axis, normal, centre


def _judge(img: np.ndarray, axis: np.ndarray, normal: np.ndarray, centre: np.ndarray,
           points: list[tuple[float, float]]) -> np.ndarray:
    """on_crossing_edge at points given as (along, across) px from the pipe's centre."""
    pts = np.array(points, dtype=np.float64)
    uv = centre + pts[:, :1] * axis + pts[:, 1:] * normal
    k = len(points)
    return on_crossing_edge(img, uv, np.tile(axis, (k, 1)), pts[:, 1], np.full(k, WIDTH_PX), 0.5)


@pytest.mark.parametrize(("angle_deg", "occluder_deg"), [(0.0, 0.0), (30.0, 0.0), (-20.0, 5.0), (90.0, -6.0)])
def test_corners_on_an_occluders_outline_are_found_wherever_they_sit_across_the_pipe(
        angle_deg: float, occluder_deg: float) -> None:
    rng = np.random.default_rng(3)
    img, axis, normal, centre = _scene(angle_deg, occluder_deg, True, [], rng)
    # Shi-Tomasi puts a junction's corner a few px inside the cladding, off the outline; across the pipe from
    # next to one limb to next to the other, including where the cladding's grey matches the flange's (~150).
    across = [-34.0, -25.0, -12.0, 0.0, 12.0, 25.0, 34.0]
    slope = np.tan(np.radians(occluder_deg))
    pts = [(c * slope - 4.0, c) for c in across]
    assert np.all(_judge(img, axis, normal, centre, pts)), pts


def test_a_slanted_outline_is_found_from_the_pipes_middle() -> None:
    # 12 deg from square: the line leaves the window's rows within half the pipe's width of a corner next to a
    # limb (a documented limit), but from the middle it is found.
    rng = np.random.default_rng(8)
    img, axis, normal, centre = _scene(15.0, 12.0, True, [], rng)
    slope = np.tan(np.radians(12.0))
    assert np.all(_judge(img, axis, normal, centre, [(c * slope - 4.0, c) for c in (-10.0, 0.0, 10.0)]))


def test_spots_shading_and_plain_cladding_are_not_occluders() -> None:
    rng = np.random.default_rng(4)
    spots = [(-60.0, -15.0), (50.0, 18.0)]
    img, axis, normal, centre = _scene(10.0, 0.0, False, spots, rng)
    pts = [(-60.0, -15.0), (-54.0, -15.0), (-60.0, -9.0),  # a spot's centre and rim
           (50.0, 18.0), (44.0, 24.0),
           (0.0, 10.0), (0.0, 30.0), (0.0, -30.0), (20.0, 0.0)]  # the highlight's sides, the limbs' shading
    assert not np.any(_judge(img, axis, normal, centre, pts))


def test_a_spot_well_clear_of_an_occluder_is_kept_and_one_at_its_outline_is_not() -> None:
    rng = np.random.default_rng(5)
    img, axis, normal, centre = _scene(0.0, 0.0, True, [(-40.0, 5.0)], rng)
    got = _judge(img, axis, normal, centre, [(-40.0, 5.0), (-4.0, 5.0)])
    assert list(got) == [False, True]


def test_next_to_a_limb_with_no_cladding_across_it_is_not_judged_and_off_or_empty_returns_all_false() -> None:
    rng = np.random.default_rng(6)
    img, axis, _normal, centre = _scene(0.0, 0.0, True, [], rng)
    # a pipe 12 px wide (its limbs 6 px either side) is too narrow to tell a spot from an outline
    uv = centre[None, :] - 4.0 * axis[None, :]
    assert not on_crossing_edge(img, uv, axis[None, :], np.zeros(1), np.full(1, 12.0), 0.5)[0]
    assert on_crossing_edge(img, uv, axis[None, :], np.zeros(1), np.full(1, WIDTH_PX), 0.5)[0]
    assert not on_crossing_edge(img, uv, axis[None, :], np.zeros(1), np.full(1, WIDTH_PX), 0.0)[0]
    assert on_crossing_edge(img, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), 0.5).shape == (0,)


def test_corners_at_the_image_border_do_not_raise_and_noise_alone_is_no_edge() -> None:
    rng = np.random.default_rng(7)
    noise = np.clip(128.0 + 6.0 * rng.standard_normal((H, W)), 0, 255).astype(np.uint8)
    uv = np.array([[0.0, 0.0], [W - 1.0, H - 1.0], [W / 2.0, H / 2.0], [-50.0, 30.0]])
    k = uv.shape[0]
    got = on_crossing_edge(noise, uv, np.tile([0.0, 1.0], (k, 1)), np.zeros(k), np.full(k, WIDTH_PX), 0.5)
    assert not np.any(got)


def test_non_finite_or_huge_geometry_is_not_judged_and_does_not_raise() -> None:
    rng = np.random.default_rng(9)
    img, axis, _normal, centre = _scene(0.0, 0.0, True, [], rng)
    uv = np.tile(centre - 4.0 * axis, (4, 1))
    axes = np.tile(axis, (4, 1))
    axes[1] = np.nan
    widths = np.array([WIDTH_PX, WIDTH_PX, np.inf, 1e9])
    got = on_crossing_edge(img, uv, axes, np.zeros(4), widths, 0.5)
    assert got.shape == (4,) and bool(got[0]) and not got[1] and not got[2]


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), float("inf")])
def test_the_config_refuses_a_fraction_outside_zero_to_one(bad: float) -> None:
    from companion.errors import InputError
    from companion.vision.rack import RackTrackerConfig

    with pytest.raises(InputError, match="texture_crossing_edge_fraction"):
        RackTrackerConfig(texture_crossing_edge_fraction=bad)
