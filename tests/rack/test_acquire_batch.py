"""The edge check's batched steps (several poses side by side) return what one pose at a time returns."""

from __future__ import annotations

import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import frames, se3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import RackModel
from companion.vision.rack.acquire_samples import sample_limbs_many
from companion.vision.rack.acquire_verify import check_pose, check_poses
from companion.vision.rack.limbs import sample_limbs

CAM = PinholeCamera(width=360, height=240, fx=315.0, fy=315.0, cx=180.0, cy=120.0)


def _view(yaw: float, xyz: tuple[float, float, float]) -> np.ndarray:
    T_ned_body = se3.make(frames.rotation_from_euler_zyx(0.02, -0.01, yaw), np.zeros(3))
    T = frames.T_rack_cam_from_T_ned_body(T_ned_body, frames.default_T_ned_rack(), frames.default_T_body_cam())
    T[:3, 3] = xyz
    return T


def _poses() -> list[np.ndarray]:
    return [_view(0.3, (1.0, 4.0, 2.6)), _view(-0.5, (0.2, 6.0, 1.9)),
            _view(0.1, (-9.0, 5.0, 2.0)),  # nothing in view
            _view(1.2, (1.4, 9.5, 3.5)), _view(0.0, (0.9, 5.0, 0.9)),  # the rack's end; close over the pipes
            _view(0.2, (0.15, 5.0, 0.12))]  # inside pipe 0's cylinder: its limbs are not valid


def test_sample_limbs_many_equals_sample_limbs_per_pose() -> None:
    pipes = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.1], length=10.0).pipe_arrays()
    poses = _poses()
    got = sample_limbs_many(poses, CAM, pipes, 24, 6.0, 12.0, 0.1, 3.0)
    assert sum(s.uv.shape[0] == 0 for s in got) >= 1 and sum(s.uv.shape[0] > 0 for s in got) >= 3
    for T, s in zip(poses, got, strict=True):
        ref = sample_limbs(T, CAM, pipes, 24, 6.0, 12.0, 0.1, 3.0)
        for name in ("p_rack", "p_cam", "uv", "normal_px", "J_uv_pcam", "pipe", "limb", "segments_uv",
                     "segment_limb"):
            np.testing.assert_array_equal(getattr(s, name), getattr(ref, name), err_msg=name)


def test_check_poses_equals_check_pose_per_pose(rng: np.random.Generator) -> None:
    model = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.1], length=10.0)
    truth = _view(0.3, (1.0, 4.0, 2.6))
    img = RackScene(model, seed=2).render(truth, CAM, noise_std=4.0, rng=rng).astype(np.float32)
    poses = [truth @ se3.exp(rng.normal(scale=[0.03] * 3 + [0.01] * 3)) for _ in range(3)] + _poses()[1:3]
    pols = [np.zeros(3), np.ones(3), -np.ones(3), np.zeros(3), np.zeros(3)]
    pipes = model.pipe_arrays()
    args = ((10, 5, 3), 24, 8.0, 1.5, 6.0, np.full(6, 400.0), truth[2, :3], 3000.0, 2.6, 500.0)
    got = check_poses(img, CAM, pipes, poses, pols, *args)
    for T, pol, chk in zip(poses, pols, got, strict=True):
        ref = check_pose(img, CAM, pipes, T, pol, *args)
        for name, value in vars(ref).items():
            np.testing.assert_array_equal(getattr(chk, name), value, err_msg=name)
    assert got[0].agree_fraction > 0.5
