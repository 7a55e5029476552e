"""The simulator's renderer with either appearance model (`companion sim --appearance`)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import se3
from companion.sim.rack_scene_field import FieldRackScene
from companion.sim.render import SceneRenderer

CAM = PinholeCamera(width=120, height=80, fx=105.0, fy=105.0, cx=60.0, cy=40.0)
T_BODY_DOWN = se3.make(np.diag([1.0, -1.0, -1.0]), [1.0, 4.0, -2.0])  # rack frame = NED here: camera looks at +z


def test_field_appearance_renders_the_field_scene() -> None:
    field = SceneRenderer(np.eye(4), np.eye(4), CAM, seed=3, appearance="field")
    default = SceneRenderer(np.eye(4), np.eye(4), CAM, seed=3)
    assert isinstance(field.scene, FieldRackScene)
    a, b = field(T_BODY_DOWN), default(T_BODY_DOWN)
    assert a.shape == (CAM.height, CAM.width) and a.dtype == np.uint8
    assert float(np.mean(np.abs(a.astype(float) - b.astype(float)))) > 5.0


def test_unknown_appearance_is_an_input_error() -> None:
    with pytest.raises(InputError, match="appearance"):
        SceneRenderer(np.eye(4), np.eye(4), CAM, appearance="photo")
