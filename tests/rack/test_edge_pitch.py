"""The edges' pitch fed into a vision-only track (`edge_pitch.py`, `RackTrackerConfig.edge_pitch_gain`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.data import data_path
from companion.errors import InputError
from companion.geometry import se3, so3
from companion.sim.rack_scene import RackScene
from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig, tracker_maps
from companion.vision.rack.edge_pitch import (
    edge_pitch_step_rad,
    rotate_about_centre,
    rotate_on_pipes,
    rotation_about_rack_x,
)
from companion.vision.rack.texture_check import valley_step_rad
from tests.rack.spies import spy_edges_see_along

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
TWO = RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
PAPER = RackModel.load(data_path("racks/paper_5pipe.toml"))


def _on_pipes(rng: np.random.Generator, model: RackModel, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n random points on the parallel pipes' surfaces: (pipe (n,), offset from the axis start (n, 3))."""
    pipes = model.pipe_arrays()
    pipe = rng.integers(0, model.num_parallel, n)
    axial = rng.uniform(0.0, 10.0, n)
    az = rng.uniform(0.0, 2.0 * np.pi, n)
    v = pipes.directions[pipe]
    u = np.cross(v, np.array([0.0, 0.0, 1.0]))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    wv = np.cross(v, u)
    radial = (np.cos(az)[:, None] * u + np.sin(az)[:, None] * wv) * pipes.radii[pipe][:, None]
    return pipe, axial[:, None] * v + radial


def test_rotation_about_rack_x_is_right_handed() -> None:
    np.testing.assert_allclose(rotation_about_rack_x(0.3), so3.exp(np.array([0.3, 0.0, 0.0])), atol=1e-15)
    np.testing.assert_array_equal(rotation_about_rack_x(0.0), np.eye(3))


def test_points_stay_on_their_pipes_and_keep_this_frames_projections() -> None:
    """Rotated about the camera centre and put back on their cylinders, texture points keep their pipe's radius
    and the rigid rotation's axial position; from the rotated pose their projections move by no more than the
    radial correction (angle times the distance along the pipe) shows: this frame's residuals stay as they were."""
    rng = np.random.default_rng(7)
    pipes = TWO.pipe_arrays()
    pipe, off = _on_pipes(rng, TWO, 200)
    centre = np.array([0.2, 4.0, 2.0])
    angle = 3e-5  # a typical step: 0.01 of 0.2 deg
    R = rotation_about_rack_x(angle)
    moved = rotate_on_pipes(off, pipe, pipes, centre, R)
    v = pipes.directions[pipe]
    radial = moved - np.einsum("ni,ni->n", moved, v)[:, None] * v
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), pipes.radii[pipe], rtol=1e-12)
    rigid = rotate_about_centre(pipes.starts[pipe] + off, centre, R) - pipes.starts[pipe]
    np.testing.assert_allclose(np.einsum("ni,ni->n", moved, v), np.einsum("ni,ni->n", rigid, v), atol=1e-12)
    along = np.abs((pipes.starts[pipe] + off)[:, 1] - centre[1])
    assert np.all(np.linalg.norm(moved - rigid, axis=1) <= angle * along + 1e-9)
    T = se3.make(R_DOWN, centre)
    T2 = T.copy()
    T2[:3, :3] = R @ T[:3, :3]
    near = along < 1.0  # in view
    uv_old = CAM.project((pipes.starts[pipe[near]] + off[near] - T[:3, 3]) @ T[:3, :3])
    uv_new = CAM.project((pipes.starts[pipe[near]] + moved[near] - T2[:3, 3]) @ T2[:3, :3])
    np.testing.assert_allclose(uv_new, uv_old, atol=0.02)
    assert rotate_on_pipes(np.zeros((0, 3)), np.zeros(0, dtype=np.intp), pipes, centre, R).shape == (0, 3)


def test_step_is_the_edge_rows_gauss_newton_step_about_rack_x() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 7))
    w = rng.uniform(0.5, 1.0, 40)
    r = rng.normal(size=40)
    R = so3.exp(rng.normal(size=3))
    assert edge_pitch_step_rad(A, w, r, 25, R) == valley_step_rad(A, w, r, np.arange(25), R)


def _frames(model: RackModel, y0: float, n: int, dy: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    scene = RackScene(model, seed=5)
    rng = np.random.default_rng(1)
    Ts = [se3.make(R_DOWN, [0.2 if model is TWO else 0.9, y0 + dy * k, 2.0 if model is TWO else 2.4])
          for k in range(n)]
    return Ts, [scene.render(T, CAM, noise_std=3.0, rng=rng) for T in Ts]


def _track(model: RackModel, Ts: list[np.ndarray], imgs: list[np.ndarray], pitch0_deg: float,
           prior: bool = False, **kw: Any) -> np.ndarray:
    """Pitch errors (deg, about rack x) of a track started `pitch0_deg` off in pitch."""
    tr = RackTracker(model, CAM, RackTrackerConfig(**kw))
    T0 = Ts[0].copy()
    T0[:3, :3] = rotation_about_rack_x(np.radians(pitch0_deg)) @ T0[:3, :3]
    tr.reset(T0)
    out = []
    for k, (T, img) in enumerate(zip(Ts, imgs, strict=True)):
        extra: dict[str, Any] = {"R_prior": T[:3, :3], "R_prior_std_rad": np.radians(0.5)} if prior else {}
        est = tr.track(img, 0.04 * k, **extra)
        assert est.ok
        out.append(np.degrees(so3.log(np.asarray(est.T_rack_cam)[:3, :3] @ T[:3, :3].T))[0])
    return np.array(out)


def test_a_start_pitch_error_decays_with_the_edges_pitch_and_stays_without() -> None:
    """Two pipes with texture, started 0.5 deg off in pitch: the texture and ground points placed from the
    first poses keep that pitch (the freeze); fed the edges' own pitch, the track comes back towards it."""
    Ts, imgs = _frames(TWO, 4.0, 70, 0.004)
    frozen = _track(TWO, Ts, imgs, 0.5, edge_pitch_gain=0.0)
    fed = _track(TWO, Ts, imgs, 0.5, edge_pitch_gain=0.05)
    assert np.mean(np.abs(frozen[-30:])) > 0.2  # the start's error still there after 40 frames
    assert np.mean(np.abs(fed[-30:])) < 0.8 * np.mean(np.abs(frozen[-30:]))
    assert not np.array_equal(fed, frozen)


@pytest.mark.parametrize("case", ["prior", "gaps", "crossing"])
def test_not_applied_with_a_prior_estimated_gaps_or_a_crossing_pipe_in_view(
    case: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the attitude prior, with the gaps estimated, or while the edges see along the paper rack's crossing
    pipe, the gain changes nothing to the bit."""
    seen = spy_edges_see_along(monkeypatch, tracker_maps)
    if case == "crossing":
        Ts, imgs = _frames(PAPER, 5.9, 6, 0.01)
        kw: dict[str, Any] = {"ground_points": 0}
        model, pitch0 = PAPER, 0.0
    else:
        Ts, imgs = _frames(TWO, 4.0, 8, 0.004)
        kw = {"estimate_gaps": True} if case == "gaps" else {}
        model, pitch0 = TWO, 0.3
    prior = case == "prior"
    off = _track(model, Ts, imgs, pitch0, prior=prior, edge_pitch_gain=0.0, **kw)
    assert not seen  # gain 0: not even asked
    on = _track(model, Ts, imgs, pitch0, prior=prior, edge_pitch_gain=0.05, **kw)
    np.testing.assert_array_equal(on, off)
    if case == "crossing":
        assert len(seen) == len(Ts) - 1 and all(seen)  # every tracked frame after the first asked, and saw along
    else:
        assert not seen


def test_gain_is_validated() -> None:
    for bad in (-0.01, 1.5, float("nan")):
        with pytest.raises(InputError, match="edge_pitch_gain"):
            RackTrackerConfig(edge_pitch_gain=bad)
