"""Visible limbs (eq. 10-14) against an independent projection of the cylinder silhouette; occlusion."""

from __future__ import annotations

import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import se3, so3
from companion.vision.rack import Pipe, RackModel
from companion.vision.rack.limbs import sample_limbs

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def _surface_points(c: np.ndarray, v: np.ndarray, r: float, s0: float, s1: float) -> np.ndarray:
    """Dense points on a cylinder's surface (independent of the limb formulas)."""
    e1 = np.cross(v, [0.0, 0.0, 1.0]) if abs(v[2]) < 0.9 else np.cross(v, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v, e1)
    ang = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    s = np.linspace(s0, s1, 40)
    A, S = np.meshgrid(ang, s)
    return np.asarray(c + S.ravel()[:, None] * v + r * (np.cos(A.ravel())[:, None] * e1
                                                        + np.sin(A.ravel())[:, None] * e2))


def test_limbs_bound_the_projected_silhouette(rng: np.random.Generator) -> None:
    model = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
    pipes = model.pipe_arrays()
    for _ in range(3):
        R = so3.exp(rng.normal(0, 0.15, 3)) @ R_DOWN
        T = se3.make(R, [rng.uniform(0.2, 0.8), rng.uniform(3, 6), rng.uniform(1.5, 3.0)])
        s = sample_limbs(T, CAM, pipes, 10, occlusion_margin_px=0.0)
        T_cam_rack = se3.inverse(T)
        for m in range(2):
            pts = _surface_points(pipes.starts[m], pipes.directions[m], float(pipes.radii[m]), 0.0, 10.0)
            uv = CAM.project(se3.act(T_cam_rack, pts))
            uv = uv[np.all(np.isfinite(uv), axis=1)]
            for side in range(2):
                sel = s.limb == 2 * m + side
                assert sel.sum() >= 5
                q, n = s.uv[sel], s.normal_px[sel]
                # The limb is a straight image line; every silhouette point lies inside it (not
                # beyond, along the outward normal) and the silhouette touches it.
                t = (q[-1] - q[0]) / np.linalg.norm(q[-1] - q[0])
                assert np.abs((q - q[0]) @ np.array([-t[1], t[0]])).max() < 1e-6
                d = (uv - q[0]) @ n[0]
                near = np.abs((uv - q[0]) @ t) < np.linalg.norm(q[-1] - q[0])
                assert d[near].max() < 0.02
                assert d[near].max() > -0.05


def test_samples_hidden_by_the_crossing_pipe_are_excluded() -> None:
    cross = Pipe(radius=0.12, start=(-0.5, 5.0, 0.52), direction=(1.0, 0.0, 0.0), length=2.0)
    model = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0, extra=[cross])
    T = se3.make(R_DOWN, [0.5, 5.0, 2.5])
    s = sample_limbs(T, CAM, model.pipe_arrays(), 40, occlusion_margin_px=0.0)
    o = T[:3, 3]
    # Independent visibility check: march along each sample's ray and test the crossing pipe's volume.
    par = s.pipe < 2
    ks = np.linspace(0.0, 1.0, 4000)[1:-1]
    rays = o + ks[None, :, None] * (s.p_rack[par][:, None, :] - o)
    rel = rays - np.asarray(cross.start)
    ax = rel @ np.asarray(cross.direction)
    radial = np.linalg.norm(rel - ax[..., None] * np.asarray(cross.direction), axis=-1)
    inside = (radial < cross.radius) & (ax >= 0) & (ax <= cross.length)
    assert not inside.any()
    # Samples exist on both sides of the crossing pipe (y < 5 - r and y > 5 + r) but none under it.
    y = s.p_rack[par, 1]
    assert (y < 4.85).any() and (y > 5.15).any()
    assert not ((y > 4.9) & (y < 5.1)).any()
    # The crossing pipe's own limbs are sampled.
    assert (s.pipe == 2).sum() > 0
    # Without the crossing pipe the region under it is sampled.
    s2 = sample_limbs(T, CAM, RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1]).pipe_arrays(), 40)
    assert ((s2.p_rack[:, 1] > 4.9) & (s2.p_rack[:, 1] < 5.1)).any()


def test_camera_inside_or_behind_gives_no_samples() -> None:
    model = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1])
    # Looking up at the sky from above the rack: nothing visible.
    T_up = se3.make(np.diag([1.0, 1.0, 1.0]), [0.5, 5.0, 2.5])
    assert sample_limbs(T_up, CAM, model.pipe_arrays(), 10).uv.shape[0] == 0
