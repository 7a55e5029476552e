"""Texture point detection: no points on plain, noisy cladding when a corner-strength floor is set, nor on an
unmodelled occluder's outline when the crossing-edge test is on."""

from __future__ import annotations

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import se3
from companion.vision.rack import RackModel
from companion.vision.rack.texture import detect_points

CAM = PinholeCamera(width=360, height=240, fx=315.0, fy=315.0, cx=180.0, cy=120.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def test_corner_floor_keeps_spots_and_drops_noise() -> None:
    model = RackModel.parallel(radii=[0.3], gaps=[], length=10.0)
    T = se3.make(R_DOWN, [0.3, 5.0, 2.0])  # above the pipe's axis: it fills the image's middle band
    rng = np.random.default_rng(0)
    plain = np.clip(170.0 + 6.0 * rng.standard_normal((240, 360)), 0, 255).astype(np.float32)
    spotted = plain.copy()
    spots = [(150, 80), (200, 160)]
    for u, v in spots:
        cv2.circle(spotted, (u, v), 6, 60.0, -1)
    poly = [np.array([[120.0, 10.0], [240.0, 10.0], [240.0, 230.0], [120.0, 230.0]])]

    def detect(img: np.ndarray, ratio: float) -> np.ndarray:
        gray = np.asarray(cv2.GaussianBlur(img, (0, 0), 0.7)).astype(np.uint8)
        args = (gray, T, CAM, model.pipe_arrays(), poly, np.zeros((0, 2)), 20, 10.0, 0.4)
        return detect_points(*args, min_corner_ratio=ratio)[2]

    # Relative quality alone: with no spot in view, noise corners fill the budget; the floor drops them.
    assert detect(plain, 0.0).shape[0] >= 10
    assert detect(plain, 10.0).shape[0] == 0
    uv = detect(spotted, 10.0)
    assert 1 <= uv.shape[0] <= 2 * len(spots)
    assert all(np.min(np.linalg.norm(np.array(spots) - q, axis=1)) < 9.0 for q in uv)


def test_no_points_on_an_unmodelled_beams_outline_and_the_spots_kept() -> None:
    """A beam above the pipes (not in the model) makes strong corners where its outline crosses them; those slide
    along the pipes as the camera moves. With `crossing_edge_fraction` they are not taken; the spots still are."""
    from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
    from companion.vision.rack.ground import pipe_silhouettes

    model = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175], gaps=[0.1] * 3, length=10.0)
    beam_y, beam_z = 5.3, 1.0
    cfg = FieldSceneConfig(ground="grating", num_spots=40, spots_y_m=(4.6, 5.6), overhead_beams_y_m=(beam_y,),
                           overhead_beam_z_m=beam_z)
    scene = FieldRackScene(model, seed=2, config=cfg)
    cam = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
    pipes = model.pipe_arrays()
    centre_x = 0.5 * float(pipes.starts[-1, 0] + pipes.radii[-1] - pipes.radii[0])
    T = se3.make(R_DOWN, [centre_x, beam_y - 0.25, 2.7])
    gray = scene.render(T, cam, noise_std=6.0, blur_sigma_px=0.7, rng=np.random.default_rng(1))
    polys = pipe_silhouettes(T, cam, pipes)

    def image_lines(points_rack: np.ndarray) -> np.ndarray:
        return cam.project((points_rack - T[:3, 3]) @ T[:3, :3])

    # the beam's outline: its long edges (along rack x) at both faces, as image segments sampled densely
    xs = np.linspace(-1.0, 2.5, 400)
    outline = np.vstack([image_lines(np.stack([xs, np.full_like(xs, y), np.full_like(xs, z)], axis=1))
                         for y in (beam_y - 0.07, beam_y + 0.07) for z in (beam_z - 0.15, beam_z)])
    spots_uv = image_lines(scene.spot_points_rack)

    def detect(fraction: float) -> tuple[int, int]:
        uv = detect_points(gray, T, cam, pipes, polys, np.zeros((0, 2)), 50, 12.0, 0.4, 10.0,
                           crossing_edge_fraction=fraction)[2]
        d_out = np.min(np.linalg.norm(uv[:, None, :] - outline[None, :, :], axis=2), axis=1)
        d_spot = np.min(np.linalg.norm(uv[:, None, :] - spots_uv[None, :, :], axis=2), axis=1)
        # spots right at the outline are junctions too (partly covered): only those clear of it must stay
        return int(np.sum(d_out <= 8.0)), int(np.sum((d_spot <= 8.0) & (d_out > 12.0)))

    on_outline_off, spots_off = detect(0.0)
    on_outline_on, spots_on = detect(0.5)
    assert on_outline_off >= 3  # without the test the outline's corners are taken
    assert on_outline_on == 0
    assert spots_off >= 10 and spots_on >= spots_off


def test_junctions_with_a_modelled_crossing_pipe_and_at_the_pipes_ends_are_left_to_the_tracker() -> None:
    """The model explains those edges across the pipes (a pipe's end is a fixed place on it): the crossing-edge
    test leaves corners there as they were without it."""
    from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
    from companion.vision.rack.ground import pipe_silhouettes
    from companion.vision.rack.model import Pipe

    cross = Pipe(radius=0.15, start=(-0.5, 5.0, 0.57), direction=(1.0, 0.0, 0.0), length=2.8)
    model = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175], gaps=[0.1] * 3, length=10.0, extra=[cross])
    scene = FieldRackScene(model, seed=3, config=FieldSceneConfig(ground="concrete", num_spots=40))
    cam = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
    pipes = model.pipe_arrays()
    for y in (5.0 - 0.3, 0.35):  # the crossing pipe in the view's upper half; the pipes' ends in view
        T = se3.make(R_DOWN, [0.85, y, 2.7])
        gray = scene.render(T, cam, noise_std=6.0, blur_sigma_px=0.7, rng=np.random.default_rng(2))
        polys = pipe_silhouettes(T, cam, pipes)
        off, on = (detect_points(gray, T, cam, pipes, polys, np.zeros((0, 2)), 50, 12.0, 0.4, 10.0,
                                 crossing_edge_fraction=f)[2] for f in (0.0, 0.5))
        assert off.shape[0] >= 5
        np.testing.assert_array_equal(on, off)
