"""Rack acquisition: limb grouping, pattern matching, verification, rejection, end to end."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import frames, se3, so3
from companion.sim.rack_scene import RackScene, RackSceneConfig
from companion.vision.rack import (
    AcquisitionConfig,
    AcquisitionPrior,
    RackModel,
    RackTracker,
    RackTrackerConfig,
    acquire_rack,
)
from companion.vision.rack.acquire_lines import LimbClusters, Segments, limb_clusters
from companion.vision.rack.acquire_match import anchor_hypotheses, predict_limb_angles, section_hypotheses
from companion.vision.rack.acquire_verify import up_axis_with_jacobian
from companion.vision.rack.limbs import limb_lines
from tests.numdiff import central_jacobian

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
PAPER = Path(__file__).resolve().parents[2] / "missions" / "racks" / "paper_5pipe.toml"
RADII = (0.15, 0.20, 0.15, 0.175, 0.20)


def five_pipes() -> RackModel:
    return RackModel.parallel(radii=RADII, gaps=[0.10] * 4, length=10.0)


def view(roll: float, pitch: float, yaw: float, xyz: tuple[float, float, float]) -> np.ndarray:
    """T_rack_cam for a body attitude (rad, NED) with the default mount and rack alignment."""
    T_ned_body = se3.make(frames.rotation_from_euler_zyx(roll, pitch, yaw), np.zeros(3))
    T = frames.T_rack_cam_from_T_ned_body(T_ned_body, frames.default_T_ned_rack(), frames.default_T_body_cam())
    T[:3, 3] = xyz
    return T


def synthetic_segments(T: np.ndarray, model: RackModel, pieces: int) -> tuple[Segments, np.ndarray]:
    """Each parallel pipe's limbs projected and cut into `pieces` segments (as an occluder would), with
    the contrast of a bright pipe on dark ground; also the camera's up axis (cam frame)."""
    pipes = model.pipe_arrays()
    o = T[:3, 3]
    lines = limb_lines(o, pipes)
    R = T[:3, :3]
    uv0, uv1, con = [], [], []
    for limb in range(2 * model.num_parallel):
        a = lines.point[limb] + (o[1] - 1.0 - lines.point[limb][1]) * lines.direction[limb]
        ends = [a + s * lines.direction[limb] for s in np.linspace(0.0, 2.0, 2 * pieces)]
        px = CAM.project((np.asarray(ends) - o) @ R)
        out_px = CAM.project((np.asarray(ends) + 0.05 * lines.outward[limb] - o) @ R)
        for k in range(pieces):
            p0, p1 = px[2 * k], px[2 * k + 1]
            t = p1 - p0
            right = np.array([-t[1], t[0]])
            # Brighter on the pipe side: the side away from the outward normal.
            inward_is_right = float(right @ (px[2 * k] - out_px[2 * k])) > 0
            uv0.append(p0)
            uv1.append(p1)
            con.append(60.0 if inward_is_right else -60.0)
    uv0a, uv1a = np.asarray(uv0), np.asarray(uv1)
    r0 = np.column_stack([CAM.normalized(uv0a), np.ones(len(uv0))])
    r1 = np.column_stack([CAM.normalized(uv1a), np.ones(len(uv1))])
    n = np.cross(r0, r1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    seg = Segments(uv0=uv0a, uv1=uv1a, length_px=np.hypot(*(uv1a - uv0a).T), normal_cam=n, contrast=np.asarray(con))
    return seg, R[2, :]


# ---------------------------------------------------------------------------------------------- grouping
def test_limb_clusters_merge_broken_limbs_and_alternate_polarity() -> None:
    model = five_pipes()
    T = view(0.02, -0.03, 0.4, (1.1, 5.0, 2.6))
    seg, up = synthetic_segments(T, model, pieces=3)
    d = T[:3, :3][1, :]  # rack +y in the camera frame
    limbs = limb_clusters(seg, np.ones(seg.length_px.size, dtype=bool), d, up, CAM, 4.0 / 630.0)
    assert limbs.theta.size == 10  # 3 pieces per limb merged into one limb each
    assert np.all(np.diff(limbs.theta) > 0)
    # Bright pipes: +1 entering a pipe (left limb), -1 leaving it, left to right.
    np.testing.assert_array_equal(limbs.polarity, np.tile([1.0, -1.0], 5))
    x_axes = model.pipe_arrays().starts[:5, 0]
    th, vis = predict_limb_angles(np.array([1.1]), np.array([2.6]), np.zeros(1), np.ones(1), x_axes,
                                  np.asarray(RADII))
    assert vis.all()
    np.testing.assert_allclose(limbs.theta, th[0], atol=2e-4)


def test_pairs_are_grouped_by_the_width_the_height_predicts() -> None:
    model = five_pipes()
    x_axes = model.pipe_arrays().starts[:5, 0]
    r = np.asarray(RADII)
    th, _ = predict_limb_angles(np.array([0.9]), np.array([2.4]), np.zeros(1), np.ones(1), x_axes, r)
    limbs = LimbClusters(theta=th[0], polarity=np.tile([1.0, -1.0], 5), length_px=np.full(10, 300.0),
                         contrast=np.full(10, 50.0), d=np.array([0.0, 1.0, 0.0]), e_x=np.array([1.0, 0.0, 0.0]),
                         e_z=np.array([0.0, 0.0, -1.0]))
    X, Z, _, P, M = anchor_hypotheses(limbs, x_axes, r, 2.4, 0.15, (1,))
    assert np.all(P == 1.0)  # gaps (dark, -1 then +1) never pair as pipes
    assert np.all(np.abs(Z - 2.4) <= 0.15)
    # Every true pipe pair is found with its own model pipe and gives the true camera position.
    for m in range(5):
        hit = (m == M) & (np.abs(X - 0.9) < 1e-9) & (np.abs(Z - 2.4) < 1e-9)
        assert np.count_nonzero(hit) == 1
    # Pairs that span a gap or several pipes are too wide for any radius at this height.
    assert X.size < 5 * 5


# ---------------------------------------------------------------------------------------------- matching
def _runs(n: int) -> list[tuple[int, ...]]:
    return [tuple(range(a, b)) for a in range(n) for b in range(a + 1, n + 1)]


def _pattern(model: RackModel, run: tuple[int, ...], sign: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Radii and gaps of a run of pipes as seen left to right in the image."""
    order = list(run) if sign > 0 else list(run)[::-1]
    radii = tuple(round(model.radii[m], 6) for m in order)
    gaps = tuple(round(model.gaps[min(a, b)], 6) for a, b in itertools.pairwise(order))
    return radii, gaps


@pytest.mark.parametrize("sign", [1, -1])
@pytest.mark.parametrize("run", _runs(5))
def test_pattern_matching_every_run_of_pipes_in_view_either_direction(run: tuple[int, ...], sign: int) -> None:
    model = five_pipes()
    pa = model.pipe_arrays()
    x_axes, r = pa.starts[:5, 0], pa.radii[:5]
    X_true, Z_true = float(np.mean(x_axes[list(run)])) + 0.1, 2.5
    th, _ = predict_limb_angles(np.array([X_true]), np.array([Z_true]), np.zeros(1), np.array([float(sign)]),
                                x_axes, r)
    keep = np.sort(np.concatenate([2 * np.asarray(run), 2 * np.asarray(run) + 1]))
    obs = np.sort(th[0, keep])
    limbs = LimbClusters(theta=obs, polarity=np.tile([1.0, -1.0], len(run)), length_px=np.full(obs.size, 300.0),
                         contrast=np.full(obs.size, 50.0), d=np.array([0.0, 1.0, 0.0]),
                         e_x=np.array([1.0, 0.0, 0.0]), e_z=np.array([0.0, 0.0, -1.0]))
    # The image shows exactly this run: its field of view ends just outside the outer limbs.
    theta_range = (float(obs[0]) - 0.01, float(obs[-1]) + 0.01)
    hyps = section_hypotheses(limbs, x_axes, r, Z_true, 0.05 * Z_true, (1, -1), theta_range,
                              lambda t: np.full(np.shape(t), 300.0), 8.0 / 630.0, 40.0, 0.0175, 40, 0.05)
    true = [h for h in hyps if h.sign == sign and abs(h.x_m - X_true) < 0.01 and abs(h.z_m - Z_true) < 0.02]
    assert len(true) == 1, "the true placement must be among the hypotheses"
    h_true = true[0]
    expected = tuple(run) if sign > 0 else tuple(run)[::-1]
    assert h_true.pipes == expected
    assert h_true.score == pytest.approx(1.0)
    best = max(h.score for h in hyps)
    assert h_true.score == pytest.approx(best)
    # Every run that looks the same (either direction) is offered too; other explanations as good
    # only where a run looks the same up to the scale the height's uncertainty allows.
    perfect = {(h.pipes, h.sign) for h in hyps if h.score > 0.999}
    for o in _runs(5):
        for s in (1, -1):
            if len(o) == len(run) and _pattern(model, o, s) == _pattern(model, run, sign):
                assert (o if s > 0 else o[::-1], s) in perfect
    seen_r, seen_g = map(np.asarray, _pattern(model, run, sign))
    for pipes, s in perfect:
        r_o, g_o = map(np.asarray, _pattern(model, tuple(sorted(pipes)), s))
        scale = r_o / seen_r
        assert len(pipes) == len(run) and np.all(np.abs(scale - 1.0) <= 3 * 0.05 + 0.02)
        if len(run) >= 2:
            np.testing.assert_allclose(g_o / seen_g, scale.mean(), atol=0.35)


@pytest.mark.parametrize("sign", [1, -1])
@pytest.mark.parametrize("run", _runs(5))
def test_pattern_matching_every_subset_of_the_pipes_in_view_seen(run: tuple[int, ...], sign: int) -> None:
    """A camera above the rack sees a contiguous run of pipes (those in its field of view); any subset of
    them may show its limbs (the others' lost to rust, shadow or an occluder: pipes 0, 2 and 4 seen of
    0-4). For every subset the true placement is proposed, with exactly the seen pipes as its pipes and
    the unseen limbs counted as predicted but unexplained."""
    model = five_pipes()
    pa = model.pipe_arrays()
    x_axes, r = pa.starts[:5, 0], pa.radii[:5]
    X_true, Z_true = float(np.mean(x_axes[list(run)])) + 0.1, 2.5
    th, _ = predict_limb_angles(np.array([X_true]), np.array([Z_true]), np.zeros(1), np.array([float(sign)]),
                                x_axes, r)
    in_view = np.concatenate([2 * np.asarray(run), 2 * np.asarray(run) + 1])
    theta_range = (float(th[0, in_view].min()) - 0.01, float(th[0, in_view].max()) + 0.01)
    for k in range(1, len(run) + 1):
        for seen in itertools.combinations(run, k):
            obs = np.sort(th[0, np.concatenate([2 * np.asarray(seen), 2 * np.asarray(seen) + 1])])
            limbs = LimbClusters(theta=obs, polarity=np.tile([1.0, -1.0], len(seen)),
                                 length_px=np.full(obs.size, 300.0), contrast=np.full(obs.size, 50.0),
                                 d=np.array([0.0, 1.0, 0.0]), e_x=np.array([1.0, 0.0, 0.0]),
                                 e_z=np.array([0.0, 0.0, -1.0]))
            hyps = section_hypotheses(limbs, x_axes, r, Z_true, 0.05 * Z_true, (1, -1), theta_range,
                                      lambda t: np.full(np.shape(t), 300.0), 8.0 / 630.0, 40.0, 0.0175, 40, 0.05)
            true = [h for h in hyps if h.sign == sign and abs(h.x_m - X_true) < 0.01 and abs(h.z_m - Z_true) < 0.02]
            assert len(true) == 1, f"seen {seen}: the true placement must be among the hypotheses"
            assert true[0].pipes == (seen if sign > 0 else seen[::-1])
            assert true[0].score == pytest.approx(len(seen) / len(run))


# ---------------------------------------------------------------------------------------------- geometry
def test_up_axis_jacobian_matches_central_differences(rng: np.random.Generator) -> None:
    T = se3.exp(rng.normal(size=6))

    def f(d: np.ndarray) -> np.ndarray:
        return up_axis_with_jacobian(T @ se3.exp(d))[0]

    _, J = up_axis_with_jacobian(T)
    np.testing.assert_allclose(J, central_jacobian(f, np.zeros(6)), atol=1e-7)


# ---------------------------------------------------------------------------------------------- inputs
def test_prior_and_config_reject_bad_values_naming_the_field() -> None:
    with pytest.raises(InputError, match="height_m"):
        AcquisitionPrior(roll_rad=0.0, pitch_rad=0.0, height_m=-1.0, height_std_m=0.1)
    with pytest.raises(InputError, match="roll_rad"):
        AcquisitionPrior(roll_rad=float("nan"), pitch_rad=0.0, height_m=2.0, height_std_m=0.1)
    with pytest.raises(InputError, match="T_body_cam"):
        AcquisitionPrior(roll_rad=0.0, pitch_rad=0.0, height_m=2.0, height_std_m=0.1, T_body_cam=np.eye(3))
    with pytest.raises(InputError, match="line_scale"):
        AcquisitionConfig(line_scale=2.0)
    for name in ("min_pipe_agree", "min_limb_run"):  # fractions of a limb's samples
        for bad in (0.0, 1.5, float("nan")):
            with pytest.raises(InputError, match=name):
                AcquisitionConfig(**{name: bad})
    prior = AcquisitionPrior(roll_rad=0.0, pitch_rad=0.0, height_m=2.0, height_std_m=0.1)
    with pytest.raises(InputError, match="image"):
        acquire_rack(np.zeros((10, 10), dtype=np.uint8), five_pipes(), CAM, prior)


# ---------------------------------------------------------------------------------------------- images
def _prior(T: np.ndarray, roll: float, pitch: float, yaw: float | None, y_std: float = 1.0) -> AcquisitionPrior:
    return AcquisitionPrior(roll_rad=roll, pitch_rad=pitch, height_m=float(T[2, 3]), height_std_m=0.05 * T[2, 3],
                            y_m=float(T[1, 3]) + 0.3, y_std_m=y_std, yaw_rad=yaw, yaw_std_rad=0.3)


def test_rendered_view_is_acquired_and_locks(rng: np.random.Generator) -> None:
    model = RackModel.load(PAPER)
    roll, pitch, yaw = 0.03, -0.02, 0.35
    T = view(roll, pitch, yaw, (1.0, 3.5, 2.8))
    img = RackScene(model, seed=3).render(T, CAM, noise_std=4.0, rng=rng)
    res = acquire_rack(img, model, CAM, _prior(T, roll, pitch, None))
    assert res.confident, res.status
    best = res.best
    assert best is not None and not best.reversed
    assert best.pipes == (0, 1, 2, 3, 4)
    assert not best.y_observed  # the crossing pipe (y = 6 m) is out of view
    d = best.T_rack_cam[:3, 3] - T[:3, 3]
    assert abs(d[0]) < 0.03 and abs(d[2]) < 0.03
    assert abs(d[1]) == pytest.approx(0.3, abs=1e-9)  # y is the prior's...
    e_y = best.T_rack_cam[1, :3]
    assert float(np.sqrt(e_y @ best.covariance[:3, :3] @ e_y)) == pytest.approx(1.0, rel=0.05)  # ...with its std
    assert np.all(np.linalg.eigvalsh(best.covariance) > 0)
    tracker = RackTracker(model, CAM, RackTrackerConfig())
    tracker.reset(best.T_rack_cam)
    est = tracker.track(img, 0.0)
    assert est.ok
    d = est.T_rack_cam[:3, 3] - T[:3, 3]
    assert abs(d[0]) < 0.03 and abs(d[2]) < 0.03
    assert np.rad2deg(np.linalg.norm(so3.log(est.T_rack_cam[:3, :3] @ T[:3, :3].T))) < 1.0


def test_crossing_pipe_in_view_gives_y(rng: np.random.Generator) -> None:
    model = RackModel.load(PAPER)
    roll, pitch, yaw = -0.02, 0.01, -0.4
    T = view(roll, pitch, yaw, (0.9, 5.8, 2.6))
    img = RackScene(model, seed=4).render(T, CAM, noise_std=4.0, rng=rng)
    res = acquire_rack(img, model, CAM, _prior(T, roll, pitch, yaw))
    assert res.confident, res.status
    best = res.best
    assert best is not None and best.y_observed
    assert abs(best.T_rack_cam[1, 3] - T[1, 3]) < 0.03
    e_y = best.T_rack_cam[1, :3]
    assert float(np.sqrt(e_y @ best.covariance[:3, :3] @ e_y)) < 0.05


def test_symmetric_rack_without_heading_is_never_confident(rng: np.random.Generator) -> None:
    # Radii 15, 20, 15 cm with equal gaps look the same travelling either way along the pipes.
    model = RackModel.parallel(radii=RADII[:3], gaps=[0.10] * 2, length=10.0)
    roll, pitch, yaw = 0.01, 0.02, 0.2
    T = view(roll, pitch, yaw, (0.65, 5.0, 2.5))
    img = RackScene(model, seed=5).render(T, CAM, noise_std=4.0, rng=rng)
    res = acquire_rack(img, model, CAM, _prior(T, roll, pitch, None))
    assert not res.confident
    assert len(res.hypotheses) >= 2
    assert {h.reversed for h in res.hypotheses[:2]} == {False, True}
    # With the heading known to 17 deg the direction of travel is decided.
    res = acquire_rack(img, model, CAM, _prior(T, roll, pitch, yaw))
    assert res.confident and res.best is not None and not res.best.reversed


def test_no_rack_in_view_is_rejected(rng: np.random.Generator) -> None:
    model = RackModel.load(PAPER)
    T = view(0.0, 0.0, 0.3, (-6.0, 5.0, 2.5))  # over the ground, 6 m beside the rack
    img = RackScene(model, seed=6).render(T, CAM, noise_std=4.0, rng=rng)
    res = acquire_rack(img, model, CAM, _prior(T, 0.0, 0.0, None))
    assert not res.confident
    assert res.hypotheses == ()


def test_single_featureless_pipe_is_rejected(rng: np.random.Generator) -> None:
    lone = RackModel.parallel(radii=[0.20], gaps=[], length=10.0)
    T = view(0.01, 0.0, 0.2, (0.2, 5.0, 2.5))
    img = RackScene(lone, seed=7, config=RackSceneConfig(spots_per_m2=0.0)).render(T, CAM, noise_std=4.0, rng=rng)
    res = acquire_rack(img, five_pipes(), CAM, _prior(T, 0.01, 0.0, None))
    assert not res.confident


def test_longest_agreeing_run_bridges_short_gaps_within_a_limb() -> None:
    from companion.vision.rack.acquire_verify import _longest_runs

    limb = np.array([0] * 10 + [1] * 12 + [3] * 4)
    agree = np.array([1, 1, 0, 0, 0, 1, 0, 1, 1, 1,  # limb 0: a three-sample gap stays, a one-sample gap is bridged
                      1, 1, 1, 0, 0, 1, 1, 1, 0, 0, 0, 0,  # limb 1: a two-sample gap is
                      0, 0, 0, 0], dtype=bool)
    runs = _longest_runs(limb, agree, 4)
    assert runs[0] == 5  # samples 5-9 (sample 6 bridged); samples 2-4 break the run
    assert runs[1] == 8  # samples 10-17
    assert runs[2] == 0 and runs[3] == 0


def test_a_limb_learning_the_sign_against_the_clear_majority_stays_open() -> None:
    from companion.vision.rack.acquire_verify import _learn, _Refinement
    from companion.vision.rack.edges import EdgeMeasurements
    from companion.vision.rack.limbs import LimbSamples

    n_limbs, per = 6, 8
    limb = np.repeat(np.arange(n_limbs), per)
    n = limb.size
    samples = LimbSamples(p_rack=np.zeros((n, 3)), p_cam=np.zeros((n, 3)), uv=np.zeros((n, 2)),
                          normal_px=np.zeros((n, 2)), J_uv_pcam=np.zeros((n, 2, 3)), pipe=limb // 2, limb=limb)
    sign = np.where(limb == 1, 1.0, -1.0)  # limb 1 (a search that reached the neighbour's facing limb) disagrees

    def learnt(sign_: np.ndarray) -> np.ndarray:
        st = _Refinement(np.eye(4), np.zeros(n_limbs))
        meas = EdgeMeasurements(offset_px=np.zeros(n), found=np.ones(n, dtype=bool), sign=sign_,
                                strength=np.full(n, 30.0))
        assert _learn(st, samples, meas)
        assert not st.learn.any()
        return st.limb_pol

    np.testing.assert_array_equal(learnt(sign), [-1.0, 0.0, -1.0, -1.0, -1.0, -1.0])
    # Without a clear majority (half the limbs each way) every limb keeps the sign it showed.
    even = np.where(limb < 3, 1.0, -1.0)
    np.testing.assert_array_equal(learnt(even), [1.0, 1.0, 1.0, -1.0, -1.0, -1.0])
