"""RackTracker on rendered images: convergence, texture points, track loss, input errors."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError, TrackingError
from companion.geometry import se3, so3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import Pipe, RackEstimate, RackModel, RackTracker, RackTrackerConfig

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
CROSS = Pipe(radius=0.12, start=(-0.5, 5.0, 0.52), direction=(1.0, 0.0, 0.0), length=3.5)
MODEL = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175, 0.2], gaps=[0.1] * 4, length=10.0, extra=[CROSS])


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    e = se3.log(se3.inverse(T_true) @ T_est)
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(np.degrees(np.linalg.norm(e[3:])))


@pytest.fixture(scope="module")
def scene() -> RackScene:
    return RackScene(MODEL, seed=11)


def test_converges_from_5cm_2deg_perturbation(scene: RackScene) -> None:
    T_true = se3.make(so3.exp([0.03, -0.02, 0.2]) @ R_DOWN, [1.0, 5.3, 2.6])
    img = scene.render(T_true, CAM, noise_std=3.0, rng=np.random.default_rng(0))
    rng = np.random.default_rng(5)
    for _ in range(2):
        dv = rng.normal(size=3)
        dw = rng.normal(size=3)
        delta = np.concatenate([0.05 * dv / np.linalg.norm(dv), np.radians(2.0) * dw / np.linalg.norm(dw)])
        tr = RackTracker(MODEL, CAM, RackTrackerConfig(reset_prior_rotation_rad=0.05, reset_prior_translation_m=0.1))
        tr.reset(T_true @ se3.exp(delta))
        est = tr.track(img, 0.0)
        for k in range(1, 3):  # the same image again: refine from the converged pose
            est = tr.track(img, k * 0.04)
        dp, da = _errors(est.T_rack_cam, T_true)
        assert est.ok, est.status
        assert dp < 0.01 and da < 0.15, (dp, da)
        assert est.covariance.shape == (6, 6)
        assert np.all(np.linalg.eigvalsh(est.covariance) > 0)


def test_tracks_along_the_pipes_with_texture_points(scene: RackScene) -> None:
    tr = RackTracker(MODEL, CAM, RackTrackerConfig(max_texture_points=40))
    T0 = se3.make(R_DOWN, [1.0, 2.0, 2.5])
    tr.reset(T0)
    rng = np.random.default_rng(1)
    est: RackEstimate | None = None
    for k in range(25):
        T = se3.make(so3.exp([0.0, 0.0, 0.01 * k]) @ R_DOWN, [1.0 + 0.002 * k, 2.0 + 0.016 * k, 2.5])
        est = tr.track(scene.render(T, CAM, noise_std=3.0, rng=rng), k * 0.04)
        assert est.ok, est.status
    assert est is not None
    dp, da = _errors(est.T_rack_cam, T)
    assert est.num_texture_points >= 20
    assert dp < 0.01 and da < 0.15, (dp, da)
    assert est.residual_px < 1.0 and est.num_edge_points > 100


def test_track_loss_is_detected_when_the_camera_looks_away(scene: RackScene) -> None:
    tr = RackTracker(MODEL, CAM)
    T = se3.make(R_DOWN, [1.0, 3.0, 2.5])
    tr.reset(T)
    rng = np.random.default_rng(2)
    assert tr.track(scene.render(T, CAM, noise_std=3.0, rng=rng), 0.0).ok
    assert tr.track(scene.render(T, CAM, noise_std=3.0, rng=rng), 0.04).ok
    # The camera turns to the side (ground and sky), the tracker still believes it sees the rack.
    away = se3.make(so3.exp([0.0, np.radians(70.0), 0.0]) @ R_DOWN, [1.0, 3.0, 2.5])
    aside = se3.make(R_DOWN, [4.5, 3.0, 2.5])  # 3 m to the side: only ground texture below
    for k, T_away in enumerate([away, away, aside, aside]):
        est = tr.track(scene.render(T_away, CAM, noise_std=3.0, rng=rng), 0.08 + 0.04 * k)
        assert not est.ok
        assert est.status
        assert np.all(np.isfinite(est.T_rack_cam))


def test_texture_points_behind_the_camera_give_zero_rows_not_nan() -> None:
    # A relock's solve with no limb in reach can carry the pose past texture points; their rows must not
    # poison the normal equations (the NaN projection raised out of track() in the field loop, 2026-11-28).
    tr = RackTracker(MODEL, CAM)
    T = se3.make(R_DOWN, [1.0, 3.0, 2.5])
    tr.reset(T)
    p_rack = np.array([[1.0, 3.1, 0.3], [1.2, 2.9, 3.0], [0.9, 3.0, 2.5]])  # below, above, in the camera's plane
    tex_uv = np.array([[370.0, 250.0], [100.0, 100.0], [200.0, 300.0]])
    A = np.zeros((6, 6))
    r = np.zeros(6)
    tr._texture_rows(T, tr._pipe_arrays(tr._gaps), p_rack, tex_uv, A, r)
    assert np.all(np.isfinite(A)) and np.all(np.isfinite(r))
    assert np.all(A[2:] == 0.0) and np.all(r[2:] == 0.0)
    uv = CAM.project((p_rack[0] - T[:3, 3]) @ T[:3, :3])
    assert np.allclose(r[:2], tex_uv[0] - uv) and np.abs(A[:2]).max() > 0.0


def test_wrong_gaps_converge_when_estimated() -> None:
    true_model = RackModel.parallel(radii=[0.15] * 4, gaps=[0.1] * 3, length=10.0)
    wrong = true_model.with_cumulative_gaps([0.15, 0.35, 0.5])
    scene = RackScene(true_model, seed=4)
    tr = RackTracker(wrong, CAM, RackTrackerConfig(estimate_gaps=True))
    T = se3.make(R_DOWN, [0.75, 4.0, 2.3])
    tr.reset(T)
    rng = np.random.default_rng(3)
    for k in range(6):
        est = tr.track(scene.render(T, CAM, noise_std=3.0, rng=rng), 0.04 * k)
    np.testing.assert_allclose(est.gaps, [0.1, 0.2, 0.3], atol=0.01)
    assert est.gaps_std_m.shape == (3,) and np.all(est.gaps_std_m > 0)


def test_input_errors() -> None:
    tr = RackTracker(MODEL, CAM)
    img = np.zeros((480, 720), np.uint8)
    with pytest.raises(TrackingError, match="reset"):
        tr.track(img, 0.0)
    tr.reset(np.eye(4))
    with pytest.raises(InputError, match="size"):
        tr.track(np.zeros((100, 100), np.uint8), 0.0)
    with pytest.raises(InputError, match="uint8"):
        tr.track(np.zeros((480, 720), np.float32), 0.0)
    with pytest.raises(InputError, match="stamp_s"):
        tr.track(img, float("nan"))
    with pytest.raises(InputError, match="T_rack_cam"):
        tr.reset(np.zeros((4, 4)))
    with pytest.raises(InputError, match="robust"):
        RackTrackerConfig(robust="huber")
    bgr = np.zeros((480, 720, 3), np.uint8)
    est = tr.track(bgr, 0.0)  # nothing visible from the identity pose (looking up)
    assert not est.ok


def test_edge_bias_option_stays_small_and_pose_accurate(scene: RackScene) -> None:
    tr = RackTracker(MODEL, CAM, RackTrackerConfig(estimate_edge_bias=True, edge_bias_rate_px=0.1))
    T = se3.make(R_DOWN, [1.0, 3.0, 2.5])
    tr.reset(T)
    rng = np.random.default_rng(8)
    for k in range(6):
        T = se3.make(R_DOWN, [1.0, 3.0 + 0.02 * k, 2.5])
        est = tr.track(scene.render(T, CAM, noise_std=3.0, rng=rng), 0.04 * k)
        assert est.ok, est.status
    assert np.all(np.abs(est.edge_bias_px) < 1.0)
    dp, da = _errors(est.T_rack_cam, T)
    assert dp < 0.01 and da < 0.15, (dp, da)
    assert not est.T_rack_cam.flags.writeable


def test_initial_search_is_retried_until_a_frame_is_accepted(scene: RackScene) -> None:
    tr = RackTracker(MODEL, CAM)
    T = se3.make(R_DOWN, [1.0, 3.0, 2.5])
    tr.reset(T @ se3.exp([0.03, 0.0, 0.0, 0.0, 0.01, 0.0]))
    rng = np.random.default_rng(4)
    aside = se3.make(R_DOWN, [4.5, 3.0, 2.5])
    assert not tr.track(scene.render(aside, CAM, noise_std=3.0, rng=rng), 0.0).ok
    est = tr.track(scene.render(T, CAM, noise_std=3.0, rng=rng), 0.04)
    assert est.ok, est.status
    dp, da = _errors(est.T_rack_cam, T)
    assert dp < 0.02 and da < 0.3, (dp, da)


def _tilt_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Angle (deg) between the rack's up axis as seen by the two camera attitudes."""
    return float(np.degrees(np.arccos(np.clip(R_est[2, :] @ R_true[2, :], -1.0, 1.0))))


def test_attitude_prior_pulls_the_tilt_by_its_weight() -> None:
    model = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
    scene = RackScene(model, seed=4)
    T = se3.make(so3.exp([0.02, 0.01, 0.05]) @ R_DOWN, [0.3, 4.0, 2.3])
    rng = np.random.default_rng(2)
    frames = [scene.render(T, CAM, noise_std=3.0, rng=rng) for _ in range(6)]
    # A prior tilted 1 deg about the pipes' axis (the roll that trades against a sideways slide).
    R_off = so3.exp([0.0, np.radians(1.0), 0.0]) @ T[:3, :3]
    tilts = {}
    for std_deg in (None, 0.02, 30.0):
        tr = RackTracker(model, CAM)
        tr.reset(T)
        for k, img in enumerate(frames):
            if std_deg is None:
                est = tr.track(img, 0.04 * k)
            else:
                est = tr.track(img, 0.04 * k, R_prior=R_off, R_prior_std_rad=np.radians(std_deg))
            assert est.ok, est.status
        tilts[std_deg] = _tilt_deg(est.T_rack_cam[:3, :3], T[:3, :3])
    assert tilts[None] < 0.2 and tilts[30.0] < 0.2  # vision alone, and with a prior too weak to matter
    assert 0.7 < tilts[0.02] < 1.05  # a strong prior wins in the direction it constrains
    tr = RackTracker(model, CAM)
    tr.reset(T)
    with pytest.raises(InputError, match="R_prior"):
        tr.track(frames[0], 0.0, R_prior=T[:3, :3])
    with pytest.raises(InputError, match="R_prior: not a rotation"):
        tr.track(frames[0], 0.0, R_prior=np.eye(3) * 2.0, R_prior_std_rad=0.01)
    with pytest.raises(InputError, match="R_prior: contains NaN"):
        tr.track(frames[0], 0.0, R_prior=np.full((3, 3), np.nan), R_prior_std_rad=0.01)
    with pytest.raises(InputError, match="R_prior_std_rad"):
        tr.track(frames[0], 0.0, R_prior=T[:3, :3], R_prior_std_rad=0.0)


def test_first_frame_after_a_reset_weighs_the_attitude_prior_by_its_own_residuals() -> None:
    """Until a frame is accepted the residual scale is a guess (0.5 px^2, several times a converged
    frame's): the first frame measures its own before it weighs the prior, so a prior 1 deg off (at a
    1 deg standard deviation) pulls the tilt of two pipes about half as far as it did with the guess."""
    model = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
    scene = RackScene(model, seed=4)
    for seed in (2, 3):
        rng = np.random.default_rng(seed)
        rot = [0.02 * rng.standard_normal(), 0.02 * rng.standard_normal(), 0.3 * rng.standard_normal()]
        T = se3.make(so3.exp(rot) @ R_DOWN, [0.3 + 0.2 * rng.standard_normal(), 4.0, 2.3 + 0.5 * rng.random()])
        img = scene.render(T, CAM, noise_std=3.0, rng=rng)
        R_off = so3.exp([0.0, np.radians(1.0), 0.0]) @ T[:3, :3]  # 1 deg about the pipes' axis
        tr = RackTracker(model, CAM)
        tr.reset(T, position_std_m=0.05, rotation_std_rad=np.radians(1.0))
        est = tr.track(img, 0.0, R_prior=R_off, R_prior_std_rad=np.radians(1.0))
        assert est.ok, est.status
        # 0.36-0.41 deg with the guessed scale, 0.15-0.17 now
        assert _tilt_deg(est.T_rack_cam[:3, :3], T[:3, :3]) < 0.3


def test_edge_distance_sigma_must_not_be_negative() -> None:
    with pytest.raises(InputError, match="edge_distance_sigma_px"):
        RackTrackerConfig(edge_distance_sigma_px=-1.0)
    RackTrackerConfig(edge_distance_sigma_px=0.0)  # off


@pytest.mark.parametrize("power", [-0.5, 5.0, float("nan")])
def test_edge_strength_weight_must_be_a_small_power(power: float) -> None:
    with pytest.raises(InputError, match="edge_strength_weight"):
        RackTrackerConfig(edge_strength_weight=power)
    RackTrackerConfig(edge_strength_weight=0.0)  # off


@pytest.mark.parametrize("ratio", [-0.1, 1.5, float("nan")])
def test_edge_innermost_ratio_must_be_a_fraction(ratio: float) -> None:
    with pytest.raises(InputError, match="edge_innermost_ratio"):
        RackTrackerConfig(edge_innermost_ratio=ratio)
    RackTrackerConfig(edge_innermost_ratio=0.0)  # off
