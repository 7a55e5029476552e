"""Renderer: deterministic by seed, textured, occlusion, noise from its own generator."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import se3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import Pipe, RackModel

CAM = PinholeCamera(width=240, height=160, fx=210.0, fy=210.0, cx=120.0, cy=80.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MODEL = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0,
                           extra=[Pipe(radius=0.1, start=(-0.5, 5.0, 0.5), direction=(1, 0, 0), length=2.0)])


def test_deterministic_for_a_seed() -> None:
    T = se3.make(R_DOWN, [0.4, 4.0, 2.5])
    a = RackScene(MODEL, seed=3).render(T, CAM)
    b = RackScene(MODEL, seed=3).render(T, CAM)
    c = RackScene(MODEL, seed=4).render(T, CAM)
    assert a.dtype == np.uint8 and a.shape == (160, 240)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - c.astype(int)).mean() > 1.0
    n1 = RackScene(MODEL, seed=3).render(T, CAM, noise_std=5.0, rng=np.random.default_rng(1))
    n2 = RackScene(MODEL, seed=3).render(T, CAM, noise_std=5.0, rng=np.random.default_rng(1))
    np.testing.assert_array_equal(n1, n2)
    with pytest.raises(InputError, match="rng"):
        RackScene(MODEL, seed=3).render(T, CAM, noise_std=5.0)


def test_pipes_ground_and_occlusion_where_expected() -> None:
    scene = RackScene(MODEL, seed=1)
    T = se3.make(R_DOWN, [0.4, 5.0, 2.5])
    img = scene.render_float(T, CAM)
    T_cam_rack = se3.inverse(T)
    # The top of pipe 1 away from the crossing pipe is bright paint; the gap between pipes is ground.
    top = CAM.project(se3.act(T_cam_rack, np.array([0.15, 4.6, 0.3])))
    gap = CAM.project(se3.act(T_cam_rack, np.array([0.35, 4.6, 0.0])))
    assert img[round(top[1]), round(top[0])] > 0.4
    assert img[round(gap[1]), round(gap[0])] < 0.3
    # The crossing pipe occludes pipe 1 at y = 5: its image there equals the crossing pipe's shading,
    # which is the same with or without pipe 1 underneath.
    no_p1 = RackScene(RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], extra=list(MODEL.extra)), seed=1)
    over = CAM.project(se3.act(T_cam_rack, np.array([0.15, 5.0, 0.6])))
    u, v = round(over[0]), round(over[1])
    assert abs(img[v, u] - no_p1.render_float(T, CAM)[v, u]) < 1e-6
    np.testing.assert_allclose(scene.cumulative_gaps, [0.1])
