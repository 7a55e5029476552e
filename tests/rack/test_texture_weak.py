"""The projector onto the pose directions the limbs hardly constrain, where texture rows weigh more."""

from __future__ import annotations

import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import se3, so3
from companion.vision.rack import RackModel
from companion.vision.rack.limbs import sample_limbs
from companion.vision.rack.motion import pose_jacobian
from companion.vision.rack.tracker_solve import weak_projector

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # camera looking down, x along rack x


def _edge_rows(T: np.ndarray, model: RackModel) -> np.ndarray:
    s = sample_limbs(T, CAM, model.pipe_arrays(), 32)
    return np.asarray(np.einsum("nij,ni->nj", pose_jacobian(s.J_uv_pcam, s.p_cam), s.normal_px))


def test_along_pipe_translation_is_weak_and_seen_directions_are_not() -> None:
    rng = np.random.default_rng(7)
    for n_pipes in (2, 5):
        model = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175, 0.2][:n_pipes], gaps=[0.1] * (n_pipes - 1),
                                   length=10.0)
        pipes = model.pipe_arrays()
        for _ in range(3):
            T = se3.make(so3.exp(rng.normal(0.0, 0.1, 3)) @ R_DOWN,
                         [rng.uniform(0.2, 0.6), rng.uniform(3.0, 6.0), rng.uniform(1.8, 3.0)])
            A_e = _edge_rows(T, model)
            P = weak_projector(A_e, np.ones(A_e.shape[0]), T, pipes, 0.01)
            assert np.allclose(P @ P, P, atol=1e-9)  # a projector
            along = np.zeros(6)
            along[:3] = T[:3, :3].T @ pipes.directions[0]  # translation along the pipes, camera frame
            assert np.allclose(P @ along, along, atol=1e-6)  # invisible to limbs: fully kept
            # What P keeps moves the limbs at most sqrt(ratio) as much as the best-seen direction
            # (rotations scaled to metres at the scene's depth, as the projector does).
            depth = T[2, 3]
            D = np.diag([1.0, 1.0, 1.0, 1.0 / depth, 1.0 / depth, 1.0 / depth])
            sigma_max = np.linalg.svd(A_e @ D, compute_uv=False)[0]
            for _k in range(5):
                xi = P @ rng.normal(size=6)
                z = np.linalg.solve(D, xi)
                if np.linalg.norm(z) > 1e-9:
                    assert np.linalg.norm(A_e @ xi) <= np.sqrt(0.01) * sigma_max * np.linalg.norm(z) + 1e-9
            # the weak directions: along the pipes, and with few pipes (short lever arms between four
            # limbs) the roll / sideways-slide and pitch / along-slide pairs too; more pipes, fewer
            rank = round(float(np.trace(P)))
            assert 1 <= rank <= (4 if n_pipes == 2 else 3)
