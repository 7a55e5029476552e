"""Drift-free texture tracking: tangent-plane warps, template alignment, and no drift in the tracker."""

from __future__ import annotations

import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import se3, so3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig
from companion.vision.rack.limbs import ray_cylinder_hits
from companion.vision.rack.templates import align_templates, sample_patches, tangent_plane_warps

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def _plane_homography(T_cur: np.ndarray, T_ref: np.ndarray, X: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Pixel homography current -> reference induced by the plane n.(p - X) = 0 (independent form)."""
    K = CAM.K
    R_c, o_c = T_cur[:3, :3], T_cur[:3, 3]
    R_r, o_r = T_ref[:3, :3], T_ref[:3, 3]
    # In current-camera coordinates the plane is n_c . q = d_c.
    n_c = R_c.T @ n
    d_c = float(n @ (X - o_c))
    R = R_r.T @ R_c  # current -> reference rotation
    t = R_r.T @ (o_c - o_r)
    return np.asarray(K @ (R + np.outer(t, n_c) / d_c) @ np.linalg.inv(K))


def test_warps_match_the_plane_homography_jacobian() -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        T_cur = se3.make(so3.exp(rng.normal(0, 0.1, 3)) @ R_DOWN, [0.3, 2.0, 2.5] + rng.normal(0, 0.2, 3))
        T_ref = se3.make(so3.exp(rng.normal(0, 0.1, 3)) @ R_DOWN, [0.5, 2.2, 2.8] + rng.normal(0, 0.2, 3))
        uv = np.array([[300.0 + rng.uniform(-100, 100), 250.0 + rng.uniform(-80, 80)]])
        d = CAM.unproject(uv)[0] @ T_cur[:3, :3].T
        X = T_cur[:3, 3] + 2.3 * d
        n = np.array([0.4, 0.1, 1.0])
        n /= np.linalg.norm(n)
        A = tangent_plane_warps(T_cur, CAM, uv, X[None], n[None], T_ref[:3, :3][None], T_ref[:3, 3][None])[0]
        Hm = _plane_homography(T_cur, T_ref, X, n)

        def f(p: np.ndarray, Hm: np.ndarray = Hm) -> np.ndarray:
            q = Hm @ np.array([p[0], p[1], 1.0])
            return np.asarray(q[:2] / q[2])

        eps = 1e-3
        J = np.stack([(f(uv[0] + [eps, 0]) - f(uv[0] - [eps, 0])) / (2 * eps),
                      (f(uv[0] + [0, eps]) - f(uv[0] - [0, eps])) / (2 * eps)], axis=1)
        # A is a 1 px forward difference of the exact map: equal up to its curvature.
        np.testing.assert_allclose(A, J, atol=3e-3)


def _blobs(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-20.0, 20.0, (60, 2))
    sigmas = rng.uniform(2.5, 5.0, 60)  # soft spots, like rust (sharper ones carry interpolation bias)
    amps = rng.uniform(-60.0, 60.0, 60)
    return centres, sigmas, amps


def _render_blobs(seed: int, shape: tuple[int, int], to_texture: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Image whose pixel x shows the analytic texture at to_texture @ (x - origin) (no resampling)."""
    centres, sigmas, amps = _blobs(seed)
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    q = np.stack([u - origin[0], v - origin[1]], axis=-1) @ to_texture.T
    d2 = ((q[..., None, :] - centres) ** 2).sum(-1)
    return np.asarray(120.0 + (amps * np.exp(-0.5 * d2 / sigmas**2)).sum(-1), dtype=np.float32)


def test_alignment_recovers_a_warped_patch_from_an_offset_start() -> None:
    # The current view sees the texture through an affine map (scale, rotation, shear) and
    # centred on a fractional pixel; both images are rendered from the same analytic texture.
    M = np.array([[1.25, 0.18], [-0.12, 0.9]])  # d(current px) / d(reference px)
    Minv = np.linalg.inv(M)
    c_ref = np.array([40.0, 40.0])
    c_cur = np.array([41.3, 38.7])
    ref = _render_blobs(1, (80, 80), np.eye(2), c_ref)
    cur = _render_blobs(1, (80, 80), Minv, c_cur)
    rng = np.random.default_rng(2)
    cur = (0.8 * cur + 20.0 + rng.normal(0.0, 1.0, cur.shape)).astype(np.float32)  # exposure change + noise
    patches = sample_patches(ref, c_ref[None], 10)
    starts = c_cur + np.array([[1.4, -1.1], [-0.9, -1.3], [0.0, 0.0]])
    res = align_templates(cur, starts, np.repeat(Minv[None], 3, axis=0), np.repeat(patches, 3, axis=0), 5, 6)
    assert np.all(res.inside)
    np.testing.assert_allclose(res.uv, np.repeat(c_cur[None], 3, axis=0), atol=0.04)
    assert np.all(res.ncc > 0.95)


def test_alignment_flags_windows_outside_the_reference() -> None:
    ref = _render_blobs(4, (200, 200), np.eye(2), np.array([100.0, 100.0]))
    patches = sample_patches(ref, np.array([[100.0, 100.0]]), 6)
    res = align_templates(ref, np.array([[100.0, 100.0]]), 2.5 * np.eye(2)[None], patches, 5, 2)
    assert not res.inside[0]


def test_tracked_points_stay_on_their_surface_point_over_a_long_sideways_climb() -> None:
    """Every texture point's pixel stays on the image of the surface point it was found at."""
    model = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
    scene = RackScene(model, seed=7)
    pipes = model.pipe_arrays()
    tracker = RackTracker(model, CAM, RackTrackerConfig(max_texture_points=20))
    poses = [se3.make(so3.exp([0.0, 0.004 * k, 0.003 * k]) @ R_DOWN,
                      [0.25 + 0.006 * k, 4.0 + 0.01 * k, 2.2 + 0.008 * k]) for k in range(90)]
    tracker.reset(poses[0])
    rng = np.random.default_rng(0)
    truth: dict[int, tuple[np.ndarray, int]] = {}  # point id -> (surface point, frame found)
    errors_old: list[float] = []
    for k, T in enumerate(poses):
        est = tracker.track(scene.render(T, CAM, noise_std=6.0, rng=rng), k * 0.04)
        assert est.ok, est.status
        tm = tracker._texture
        for i, pid in enumerate(tm.point_id.tolist()):
            if pid not in truth:
                # The surface point under the pixel it was found at (true pose of that frame).
                d = CAM.unproject(tm.uv_last[i : i + 1]) @ T[:3, :3].T
                t = ray_cylinder_hits(T[:3, 3], d, pipes)[0, tm.pipe[i]]
                truth[pid] = (T[:3, 3] + t * d[0], k)
            elif k - truth[pid][1] >= 40:
                p_cam = (truth[pid][0] - T[:3, 3]) @ T[:3, :3]
                errors_old.append(float(np.linalg.norm(CAM.project(p_cam[None])[0] - tm.uv_last[i])))
    assert len(errors_old) > 200
    # Frame-to-frame Lucas-Kanade alone is off by ~1.5 px after 80 frames here.
    assert np.median(errors_old) < 0.25, np.median(errors_old)
    assert np.percentile(errors_old, 90) < 0.6, np.percentile(errors_old, 90)
