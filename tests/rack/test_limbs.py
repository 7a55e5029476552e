"""Visible limbs (eq. 10-14) against an independent projection of the cylinder silhouette; occlusion."""

from __future__ import annotations

import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import se3, so3
from companion.vision.rack import Pipe, RackModel
from companion.vision.rack.limbs import limb_lines, occluded, ray_cylinder_hits, sample_limbs
from companion.vision.rack.model import PipeArrays

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


def _dense_hits(o: np.ndarray, d: np.ndarray, pipes: PipeArrays, margin: np.ndarray) -> np.ndarray:
    """The former dense `ray_cylinder_hits`: both roots of every (ray, pipe) pair (the reference)."""
    c, v, r, L = pipes.starts, pipes.directions, pipes.radii, pipes.lengths
    w = o[None, :] - c
    wv = np.einsum("mi,mi->m", w, v)
    dv, dw = d @ v.T, d @ w.T
    A = 1.0 - dv * dv
    B = dw - dv * wv[None, :]
    rr = r[None, :] + np.asarray(margin, dtype=np.float64).reshape(-1, 1)
    C = (np.einsum("mi,mi->m", w, w) - wv * wv)[None, :] - rr * rr
    disc = B * B - A * C
    hit = (disc > 0.0) & (A > 1e-12)
    sq = np.sqrt(np.where(hit, disc, 0.0))
    As = np.where(hit, A, 1.0)
    t_out = np.full(A.shape, np.inf)
    for t in ((-B - sq) / As, (-B + sq) / As):
        s = wv[None, :] + t * dv
        np.copyto(t_out, t, where=hit & (t > 0.0) & (s >= 0.0) & (s <= L[None, :]) & (t < t_out))
    return t_out


def test_hits_and_occlusion_equal_the_dense_computation(rng: np.random.Generator) -> None:
    """Roots only where the line meets a cylinder (and, for occlusion, not on the point's own pipe)
    give bit for bit the distances and flags of computing them for every pair."""
    cross = Pipe(radius=0.12, start=(-0.5, 5.0, 0.52), direction=(1.0, 0.0, 0.0), length=2.0)
    model = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.1], length=10.0, extra=[cross])
    pipes = model.pipe_arrays()
    for _ in range(20):
        o = np.array([rng.uniform(-0.5, 1.5), rng.uniform(-1.0, 11.0), rng.uniform(0.2, 3.0)])
        p = pipes.starts[rng.integers(0, 4, 300)] + rng.uniform(-0.3, 0.3, (300, 3)) + [0.0, 5.0, 0.0]
        d = p - o
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        margin = rng.uniform(0.0, 0.02, 300)
        np.testing.assert_array_equal(ray_cylinder_hits(o, d, pipes, margin), _dense_hits(o, d, pipes, margin))
        own = rng.integers(0, 4, 300)
        t = _dense_hits(o, d, pipes, margin)
        t[np.arange(300), own] = np.inf
        np.testing.assert_array_equal(occluded(o, p, own, pipes, margin),
                                      np.any(t < dist[:, None] * (1.0 - 1e-6), axis=1))


def test_given_limb_lines_are_used_as_computed() -> None:
    model = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
    pipes = model.pipe_arrays()
    T = se3.make(so3.exp(np.array([0.1, -0.05, 0.2])) @ R_DOWN, [0.4, 5.0, 2.0])
    a = sample_limbs(T, CAM, pipes, 16)
    b = sample_limbs(T, CAM, pipes, 16, lines=limb_lines(T[:3, 3], pipes))
    for name in ("p_cam", "uv", "normal_px", "J_uv_pcam", "limb", "segments_uv"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
