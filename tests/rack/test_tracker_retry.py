"""A refused or marginal frame solved again from starts that do not extrapolate the last turn (`tracker_health.py`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.camera import PinholeCamera
from companion.geometry import frames, se3, so3
from companion.sim.rack_scene import RackScene
from companion.sim.render import SceneRenderer
from companion.sim.run import sim_config
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig
from drivers.camera import load_camera_model

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MODEL = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175], gaps=[0.1] * 3, length=10.0)


def _shaking(roll_deg: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Poses and frames of a camera creeping along the pipes while its roll (about the pipes) jumps by
    `roll_deg` and back every other frame: the constant-velocity prediction is then twice the turn off."""
    rolls = [0.0] * 4 + [roll_deg if k % 2 == 0 else 0.0 for k in range(16)]
    poses = [se3.make(so3.exp([0.0, np.radians(r), 0.03]) @ R_DOWN, [0.6, 4.0 + 0.01 * k, 2.0])
             for k, r in enumerate(rolls)]
    scene = RackScene(MODEL, seed=2)
    rng = np.random.default_rng(1)
    return poses, [scene.render(T, CAM, noise_std=3.0, rng=rng) for T in poses]


def _run(poses: list[np.ndarray], imgs: list[np.ndarray], retry: bool, prior: bool) -> tuple[int, float, list]:
    """(refused frames, largest position error (m), the estimates) of one tracker over the frames."""
    tr = RackTracker(MODEL, CAM, RackTrackerConfig(retry_refused=retry))
    tr.reset(poses[0])
    refused, worst, ests = 0, 0.0, []
    for k, T in enumerate(poses):
        kw = {"R_prior": T[:3, :3], "R_prior_std_rad": np.radians(0.3)} if prior else {}
        est = tr.track(imgs[k], 0.04 * k, **kw)
        refused += 0 if est.ok else 1
        worst = max(worst, float(np.linalg.norm(est.T_rack_cam[:3, 3] - T[:3, 3])))
        ests.append(est)
    return refused, worst, ests


def test_a_shaking_camera_is_tracked_through_its_reversals() -> None:
    poses, imgs = _shaking(0.8)  # the prediction 1.6 deg off, 18 px at the pipes; the last attitude 9 px
    refused_before, _, _ = _run(poses, imgs, retry=False, prior=False)
    refused, worst_m, _ = _run(poses, imgs, retry=True, prior=False)
    assert refused_before >= 3, refused_before
    assert refused == 0 and worst_m < 0.01, (refused, worst_m)


def test_the_attitude_prior_starts_a_retry_where_the_last_attitude_is_too_far() -> None:
    poses, imgs = _shaking(1.2)  # the last attitude 13 px off: beyond the edge search as well
    refused_last_attitude, _, _ = _run(poses, imgs, retry=True, prior=False)
    refused_prior, _, _ = _run(poses, imgs, retry=True, prior=True)
    refused_prior_no_retry, _, _ = _run(poses, imgs, retry=False, prior=True)
    assert refused_prior <= refused_last_attitude - 4, (refused_prior, refused_last_attitude)
    assert refused_prior <= refused_prior_no_retry - 4, (refused_prior, refused_prior_no_retry)


def test_frames_accepted_clearly_at_the_first_try_are_not_touched() -> None:
    poses = [se3.make(so3.exp([0.0, 0.002 * k, 0.03]) @ R_DOWN, [0.6, 4.0 + 0.01 * k, 2.0]) for k in range(12)]
    scene = RackScene(MODEL, seed=2)
    rng = np.random.default_rng(3)
    imgs = [scene.render(T, CAM, noise_std=3.0, rng=rng) for T in poses]
    _, _, with_retry = _run(poses, imgs, retry=True, prior=False)
    _, _, without = _run(poses, imgs, retry=False, prior=False)
    assert all(e.ok for e in with_retry)
    for a, b in zip(with_retry, without, strict=True):
        assert np.array_equal(a.T_rack_cam, b.T_rack_cam)


def test_the_retry_starts_keep_the_position_and_tilt_onto_the_prior() -> None:
    tr = RackTracker(MODEL, CAM, RackTrackerConfig())
    T_last = se3.make(so3.exp([0.0, 0.01, 0.03]) @ R_DOWN, [0.6, 4.0, 2.0])
    tr.reset(T_last)
    T_pred = se3.make(so3.exp([0.02, -0.03, 0.05]) @ R_DOWN, [0.62, 4.05, 2.01])
    R_prior = so3.exp([0.004, 0.002, 0.4]) @ R_DOWN  # its heading is ignored: only the up direction counts
    starts = tr._retry_starts(T_pred, R_prior)
    assert len(starts) == 2 and len(tr._retry_starts(T_pred, None)) == 1
    last_attitude, tilted = starts
    np.testing.assert_allclose(last_attitude[:3, :3], T_last[:3, :3])
    for T in starts:
        np.testing.assert_allclose(T[:3, 3], T_pred[:3, 3])
    np.testing.assert_allclose(tilted[2, :3], R_prior[2, :], atol=1e-12)  # the up direction seen by the camera
    # the smallest rotation that does it: the turn from the prediction equals the angle between the two up directions
    turn = np.linalg.norm(so3.log(T_pred[:3, :3].T @ tilted[:3, :3]))
    assert abs(turn - np.arccos(np.clip(T_pred[2, :3] @ R_prior[2, :], -1.0, 1.0))) < 1e-9


def test_a_retry_must_pass_clearly() -> None:
    """The first try was refused, so the frame is doubtful: a retry at 2.9 px with 45 % of the samples agreeing
    (it passes the first try's checks) is not taken; one at 0.8 px with 90 % is."""

    class _Samples:
        uv = np.zeros((200, 2))

    tr = RackTracker(MODEL, CAM, RackTrackerConfig())
    assert not tr._clear_retry({"samples": _Samples(), "residual_px": 2.9, "n_agree": 90})
    assert not tr._clear_retry({"samples": _Samples(), "residual_px": 0.8, "n_agree": 120})
    assert tr._clear_retry({"samples": _Samples(), "residual_px": 0.8, "n_agree": 180})


def test_a_marginal_solve_is_replaced_only_by_a_clearly_better_retry() -> None:
    """A first try that passed with 130 of 200 samples agreeing: a clear retry with 150 (the same solve, just over the
    bar) does not replace it, one with 160 (a fifth more) does; a retry at 2 px never does."""

    class _Samples:
        uv = np.zeros((200, 2))

    tr = RackTracker(MODEL, CAM, RackTrackerConfig())
    T_pred = se3.make(R_DOWN, [0.6, 4.0, 2.0])
    first = {"samples": _Samples(), "residual_px": 1.6, "n_agree": 130, "T": T_pred}
    assert not tr._better_retry({"samples": _Samples(), "residual_px": 0.9, "n_agree": 150, "T": T_pred}, first,
                                T_pred, False)
    assert tr._better_retry({"samples": _Samples(), "residual_px": 0.9, "n_agree": 160, "T": T_pred}, first,
                            T_pred, False)
    assert not tr._better_retry({"samples": _Samples(), "residual_px": 2.0, "n_agree": 190, "T": T_pred}, first,
                                T_pred, False)


def test_a_solve_that_jumped_from_the_prediction_is_replaced_by_a_clear_retry_that_did_not() -> None:
    """The motion prior's sigmas (3 cm, 0.01 rad by default) measure the jump. After a jump beyond `JUMP_SIGMA` a
    clear retry with at least as many samples agreeing replaces the first try, unless it jumped as far itself."""

    class _Samples:
        uv = np.zeros((200, 2))

    tr = RackTracker(MODEL, CAM, RackTrackerConfig())
    T_pred = se3.make(R_DOWN, [0.6, 4.0, 2.0])
    T_far = se3.make(so3.exp([0.0, 0.01, 0.0]) @ R_DOWN, [0.6, 4.0, 1.8])  # 20 cm and 0.01 rad: sqrt(6.7^2 + 1)
    assert abs(tr._jump_sigma(T_far, T_pred) - np.hypot(0.2 / 0.03, 1.0)) < 1e-9
    assert tr._jump_sigma(T_pred, T_pred) == 0.0
    first = {"samples": _Samples(), "residual_px": 1.3, "n_agree": 142, "T": T_far}
    near = se3.make(R_DOWN, [0.62, 4.01, 2.0])
    assert tr._better_retry({"samples": _Samples(), "residual_px": 1.2, "n_agree": 142, "T": near}, first, T_pred, True)
    assert not tr._better_retry({"samples": _Samples(), "residual_px": 1.2, "n_agree": 142, "T": T_far}, first,
                                T_pred, True)
    assert not tr._better_retry({"samples": _Samples(), "residual_px": 1.2, "n_agree": 141, "T": near}, first,
                                T_pred, True)


# Fifteen body poses in NED (x, y, z m; roll, pitch, yaw rad) of `bench/rack_field_loop.py --library --seed 24`,
# frames 362-376: the drone starts its transit to pipe 3 at up to 0.75 m/s, and the sim's wobble turns it by
# -0.8 deg in roll within two frames (index 11 -> 12).
FIELD_SEED_24 = np.array([
    (8.00404, -0.90302, -1.29706, 0.009263, 0.035122, -0.014596),
    (8.00260, -0.89295, -1.29575, 0.010795, 0.030599, -0.017717),
    (7.99613, -0.86901, -1.29178, -0.003654, 0.017304, -0.014921),
    (8.00056, -0.83767, -1.28865, -0.012757, 0.015479, -0.016217),
    (8.00087, -0.81118, -1.29109, -0.006652, 0.019234, -0.015093),
    (8.00902, -0.78699, -1.29364, 0.008672, 0.018798, -0.009561),
    (7.99823, -0.73958, -1.29480, 0.005477, 0.027145, -0.008529),
    (8.00636, -0.69170, -1.29682, 0.002576, 0.033837, -0.009386),
    (7.99857, -0.65526, -1.29487, -0.006112, 0.038914, -0.010967),
    (7.99204, -0.60828, -1.29459, -0.002604, 0.041732, -0.005785),
    (7.98904, -0.57498, -1.29676, 0.001043, 0.045649, -0.004325),
    (7.99004, -0.53464, -1.29649, -0.007746, 0.054709, -0.004391),
    (7.98324, -0.48246, -1.29705, -0.021238, 0.047237, -0.003278),
    (7.97938, -0.44371, -1.29777, -0.030590, 0.040571, -0.001203),
    (7.98313, -0.39590, -1.29069, -0.027630, 0.039822, -0.001232),
])


def test_a_marginal_solve_after_a_turn_is_replaced_by_a_clear_retry(tmp_path: Path) -> None:
    """The sim's field appearance at 15 frames/s: the turn makes the prediction's roll 1.2 deg off, and the solve
    from it passes the health checks but only just (55-60 % agreeing, 2-3 px), 9-12 cm off; the pose then slid
    one pipe over within 4 frames in the field loop. Solved again from the last attitude it is within 3 cm."""
    cfg = sim_config(tmp_path, {})
    cam = load_camera_model(cfg.camera)
    render = SceneRenderer.from_config(cfg, cam, seed=24, appearance="field")
    poses = [se3.make(frames.rotation_from_euler_zyx(r, p, y), [x, yy, z]) for x, yy, z, r, p, y in FIELD_SEED_24]
    imgs = [render(T) for T in poses]  # the first two only advance the renderer's noise, as the flight before did
    truth = [render.T_rack_cam(T) for T in poses]
    worst_cm = {}
    for marginal in (False, True):
        tr = RackTracker(RackModel.load(cfg.rack.model), cam, RackTrackerConfig(retry_marginal=marginal))
        tr.reset(truth[2])
        errs = []
        for k in range(2, len(poses)):
            est = tr.track(imgs[k] if imgs[k].ndim == 2 else imgs[k][..., 0], k / 15.0)
            assert est.ok
            errs.append(100.0 * float(np.linalg.norm(est.T_rack_cam[:3, 3] - truth[k][:3, 3])))
        worst_cm[marginal] = max(errs)
    assert worst_cm[False] > 6.0, worst_cm
    assert worst_cm[True] < 3.0, worst_cm


# Eleven body poses (as FIELD_SEED_24) of `bench/rack_field_loop.py --library --prior-std-deg 0 --seed 36`, frames
# 136-146: the drone holds over pipe 1 while the wobble sways it, an unmodelled pole standing beside the pipe's limb.
FIELD_SEED_36 = np.array([
    (0.986020257464265, -0.9345697617832301, -1.278242330021693,
     0.024216663902202673, 0.020790522943745993, -0.010704184443482576),
    (0.9878703790027646, -0.9390905540061681, -1.2841660388501346,
     0.027255504054660287, 0.01959470401572698, -0.01348205599179614),
    (0.9898762986214841, -0.9402700668625321, -1.2825274048061908,
     0.031834681147639016, 0.009166291915197033, -0.009130337068930036),
    (0.9892417625378993, -0.947213425412471, -1.28380828470288,
     0.035555118880727696, -0.002347956545955489, -0.0069488215369419),
    (0.9947415580290256, -0.9370799853022705, -1.282282293619261,
     0.04167861029578567, -0.009596479570912477, -0.010850821711556838),
    (1.015521302164611, -0.928232263234979, -1.282961985950344,
     0.04716348157375166, -0.017772707216055224, -0.014636709946659223),
    (1.0182401665800884, -0.9431807097814354, -1.2847098427413626,
     0.04539552553802624, -0.01784650738578225, -0.014034467662493711),
    (1.0243615040937288, -0.9334763292530699, -1.2828598860730862,
     0.04089199771187874, -0.016564706770689597, -0.013720259574197412),
    (1.0286862920276878, -0.9396493833179844, -1.2805666209414173,
     0.05259033805517685, -0.0103803523257257, -0.01230758484752803),
    (1.0316316788436712, -0.9361128302078431, -1.284206956036203,
     0.052003763872016696, -0.007745119011552425, -0.007933167017899477),
    (1.0484153720892728, -0.9339828424855527, -1.2840283269721242,
     0.04584880182356557, -0.002763797145607727, -0.005429486652136309),
])


def test_a_solve_that_walked_onto_a_pole_is_taken_back(tmp_path: Path) -> None:
    """The sim's field appearance: the solve of the eighth tracked frame walks onto a pole beside the first pipe's
    limb and passes marginally (84 of 160 samples agreeing at 2.9 px), 18 cm off, the next one 36 cm off. The retry
    from the last attitude (154 of 160 at 0.7 px) keeps every frame within 2 cm. (In the field loop's own run the same
    pole took a frame that passed clearly, which the jump test catches: `JUMP_SIGMA`.)"""
    cfg = sim_config(tmp_path, {})
    cam = load_camera_model(cfg.camera)
    render = SceneRenderer.from_config(cfg, cam, seed=36, appearance="field")
    poses = [se3.make(frames.rotation_from_euler_zyx(r, p, y), [x, yy, z]) for x, yy, z, r, p, y in FIELD_SEED_36]
    imgs = [render(T) for T in poses]  # the first two only advance the renderer's noise
    truth = [render.T_rack_cam(T) for T in poses]
    worst_cm = {}
    for retry in (False, True):
        tr = RackTracker(RackModel.load(cfg.rack.model), cam, RackTrackerConfig(retry_marginal=retry))
        tr.reset(truth[2])
        errs = []
        for k in range(2, len(poses)):
            est = tr.track(imgs[k] if imgs[k].ndim == 2 else imgs[k][..., 0], k / 15.0)
            assert est.ok or not retry
            errs.append(100.0 * float(np.linalg.norm(est.T_rack_cam[:3, 3] - truth[k][:3, 3])))
        worst_cm[retry] = max(errs)
    assert worst_cm[False] > 10.0, worst_cm
    assert worst_cm[True] < 2.0, worst_cm
