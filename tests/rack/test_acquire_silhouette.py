"""The acquisition's edge check moves gradient peaks to the limbs' silhouettes on its fine iterations."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import se3, so3
from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig
from companion.vision.rack import AcquisitionConfig, RackModel
from companion.vision.rack.acquire_verify import check_poses

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MODEL = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.25] * 2, length=10.0)


@pytest.mark.parametrize("ground", ["concrete", "natural"])
def test_silhouettes_hold_the_across_pipe_position_of_pale_shaded_pipes(ground: str) -> None:
    """Pale cladding darkening towards its limbs, lit from one side (the field appearance of issue #14):
    the gradient peaks lie inside the shaded limbs, so the check refined from the true pose slides 1-3.4 cm
    across the pipes; with the silhouettes it stays within 1 cm (measured 0.04-0.8 cm)."""
    peak_cm, sil_cm = [], []
    for seed in range(3):
        scene = FieldRackScene(MODEL, seed=seed, config=FieldSceneConfig(ground=ground, shadows=False, num_spots=0))
        T = se3.make(so3.exp(np.radians([0.5, -0.4, 8.0])) @ R_DOWN, [0.65 + 0.1 * seed, 4.0, 3.0])
        img = scene.render(T, CAM, noise_std=3.0, rng=np.random.default_rng(seed)).astype(np.float32)
        for silhouette, out in (((0, 0.0), peak_cm), ((3, 0.08), sil_cm)):
            check = check_poses(img, CAM, MODEL.pipe_arrays(), [T], [np.zeros(3)], (3, 3, 3), 24, 8.0, 1.5, 6.0,
                                np.full(6, 1e-6), silhouette=silhouette)[0]
            out.append(100.0 * abs(float(check.T_rack_cam[0, 3] - T[0, 3])))
    assert max(sil_cm) < 1.0, sil_cm
    assert max(peak_cm) > 1.0 and float(np.mean(sil_cm)) < 0.5 * float(np.mean(peak_cm)), (peak_cm, sil_cm)


def test_silhouette_settings_are_checked() -> None:
    with pytest.raises(InputError, match="silhouette_range_px"):
        AcquisitionConfig(silhouette_range_px=-1)
    with pytest.raises(InputError, match="silhouette_max_rms"):
        AcquisitionConfig(silhouette_max_rms=float("nan"))
    with pytest.raises(InputError, match="silhouette_min_height_m"):
        AcquisitionConfig(silhouette_min_height_m=float("inf"))
    AcquisitionConfig(silhouette_range_px=0)  # off
