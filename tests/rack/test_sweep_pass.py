"""The rack tracker alone along one pass of the example mission, through the crossing pipe.

`companion sim`'s camera and scene (360x240, f = 315, the paper's 5-pipe rack with its crossing
pipe at y = 6 m, default appearance model), the pose the example mission flies over pipe 1: 2.0 m
above its top, from y = 1.5 m to y = 8.5 m at 0.5 m/s, 15 frames/s, with a degree or so of
attitude wobble, then a 2 s hover at the end. Against the real ArduCopter SITL the fused estimate
ended this pass 7.7-11.2 cm off (issue #17); the cause was the tracker itself: with texture rows
weighing 20 edge rows, texture points born with the pose's error near the crossing pipe held that
error (x +4 cm, y +7.5 cm here). This test pins the pass's worst and final errors.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.sim.render import SceneRenderer
from companion.sim.run import sim_config
from companion.vision.rack import RackTracker
from drivers.camera import load_camera_model

FPS = 15.0
R_RACK_BODY = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # nose along +y, body z down


def _T_ned_body(T_ned_rack: np.ndarray, x_m: float, y_m: float, t_s: float) -> np.ndarray:
    roll, pitch = np.deg2rad(1.0 * np.sin(0.7 * t_s)), np.deg2rad(1.5 * np.sin(0.45 * t_s + 1.0))
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    R_x = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    R_y = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    T = np.eye(4)
    T[:3, :3] = R_RACK_BODY @ R_y @ R_x
    T[:3, 3] = [x_m, y_m, 2.3]  # pipe 1's top is 0.30 m above the support plane
    return np.asarray(T_ned_rack @ T)


@pytest.mark.parametrize(("x_m", "seed"), [(0.15, 5), (1.95, 6)])
def test_pass_through_the_crossing_pipe(tmp_path: Path, x_m: float, seed: int) -> None:
    config = sim_config(tmp_path, {})
    camera = load_camera_model(config.camera)
    render = SceneRenderer.from_config(config, camera, seed=seed)
    tracker = RackTracker(render.model, camera)
    ys = np.concatenate([np.arange(1.5, 8.5, 0.5 / FPS), np.full(30, 8.5)])
    tracker.reset(render.T_rack_cam(_T_ned_body(render.T_ned_rack, x_m, ys[0], 0.0)))
    err_m = np.full((ys.size, 3), np.nan)
    for i, y in enumerate(ys):
        T_ned_body = _T_ned_body(render.T_ned_rack, x_m, float(y), i / FPS)
        est = tracker.track(render(T_ned_body), i / FPS)
        if est.ok:
            err_m[i] = np.asarray(est.T_rack_cam)[:3, 3] - render.T_rack_cam(T_ned_body)[:3, 3]
    assert not np.isnan(err_m).any(), f"lost {int(np.isnan(err_m[:, 0]).sum())} frames"
    horizontal = np.hypot(err_m[:, 0], err_m[:, 1])
    final = np.linalg.norm(err_m[-30:].mean(axis=0))
    # measured (texture_weight 2): worst 2.1 / 1.8 cm, final 1.5 / 1.0 cm; with 20 the worst was 8.8 / 4.2 cm
    assert horizontal.max() <= 0.035, f"worst horizontal error {horizontal.max():.3f} m"
    assert final <= 0.02, f"error at the end of the pass {final:.3f} m"
