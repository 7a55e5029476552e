"""Field appearance model: sparse spots where they should be, distortion matching the calibration,
beam occlusion, ground shadows, the camera pipeline (gain, motion blur, JPEG), deterministic by seed."""

from __future__ import annotations

import inspect

import cv2
import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.errors import InputError
from companion.geometry import se3
from companion.sim.rack_scene import RackScene
from companion.sim.rack_scene_field import FieldRackScene, FieldSceneConfig, decode_frame
from companion.vision.rack import RackModel

CAM = PinholeCamera(width=360, height=240, fx=315.0, fy=315.0, cx=180.0, cy=120.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MODEL = RackModel.parallel(radii=[0.15, 0.2, 0.15, 0.175], gaps=[0.1, 0.1, 0.1], length=10.0)
NO_BEAMS = {"beam_spacing_m": 0.0, "shadows": False}


def _visible_spots(scene: FieldRackScene, T: np.ndarray, cam: PinholeCamera, margin_px: float) -> np.ndarray:
    """Pixels of the spot centres that face the camera and project inside the image (no occluder here)."""
    X = scene.spot_points_rack
    T_cam_rack = se3.inverse(T)
    uv = cam.project(se3.act(T_cam_rack, X))
    # Outward normal at the spot: from the pipe axis (parallel pipes along +y) to the point.
    arr = scene.model.pipe_arrays()
    dist_xz = np.abs(X[:, None, 0] - arr.starts[None, :, 0]) + np.abs(X[:, None, 2] - arr.starts[None, :, 2])
    m = np.argmin(dist_xz, axis=1)
    n = X - arr.starts[m] - ((X - arr.starts[m]) @ np.array([0.0, 1.0, 0.0]))[:, None] * np.array([0.0, 1.0, 0.0])
    facing = np.einsum("ij,ij->i", n, T[:3, 3] - X) > 0.2 * np.linalg.norm(T[:3, 3] - X, axis=1) * arr.radii[m]
    return uv[facing & cam.in_image(uv, margin_px)]


def _spot_blobs(scene_a: FieldRackScene, scene_b: FieldRackScene, T: np.ndarray, cam: PinholeCamera) -> np.ndarray:
    """Centroids of the image regions where the scene with spots is darker than the one without."""
    diff = scene_a.render_float(T, cam) - scene_b.render_float(T, cam)
    _, _, stats, cents = cv2.connectedComponentsWithStats((diff > 0.08).astype(np.uint8))
    return np.asarray(cents[1:][stats[1:, cv2.CC_STAT_AREA] >= 3])


def test_render_signature_matches_the_default_scene_and_is_deterministic() -> None:
    ours = list(inspect.signature(FieldRackScene.render).parameters)
    theirs = list(inspect.signature(RackScene.render).parameters)
    assert ours[: len(theirs)] == theirs
    assert list(inspect.signature(FieldRackScene.render_float).parameters) == list(
        inspect.signature(RackScene.render_float).parameters)
    T = se3.make(R_DOWN, [0.6, 4.0, 2.4])
    a = FieldRackScene(MODEL, seed=3).render(T, CAM, noise_std=6.0, rng=np.random.default_rng(1))
    b = FieldRackScene(MODEL, seed=3).render(T, CAM, noise_std=6.0, rng=np.random.default_rng(1))
    c = FieldRackScene(MODEL, seed=4).render(T, CAM, noise_std=6.0, rng=np.random.default_rng(1))
    assert a.dtype == np.uint8 and a.shape == (240, 360)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - c.astype(int)).mean() > 2.0
    with pytest.raises(InputError, match="rng"):
        FieldRackScene(MODEL, seed=3).render(T, CAM, noise_std=5.0)
    with pytest.raises(InputError, match="ground"):
        FieldSceneConfig(ground="lawn")
    with pytest.raises(InputError, match="num_spots"):
        FieldSceneConfig(num_spots=-1)


@pytest.mark.parametrize("num_spots", [10, 50])
def test_the_spots_in_view_are_the_f_spots_in_total_over_the_rack(num_spots: int) -> None:
    cfg = FieldSceneConfig(num_spots=num_spots, **NO_BEAMS)  # type: ignore[arg-type]
    scene = FieldRackScene(MODEL, seed=5, config=cfg)
    bare = FieldRackScene(MODEL, seed=5, config=FieldSceneConfig(num_spots=0, **NO_BEAMS))  # type: ignore[arg-type]
    assert scene.spot_points_rack.shape == (num_spots, 3)
    seen = 0
    for y in (1.5, 4.5, 7.5):
        T = se3.make(R_DOWN, [0.6, y, 2.2])
        blobs = _spot_blobs(bare, scene, T, CAM)
        inside = _visible_spots(scene, T, CAM, 6.0)
        maybe = _visible_spots(scene, T, CAM, -6.0)  # spots cut by the border may or may not show
        assert inside.shape[0] <= blobs.shape[0] <= maybe.shape[0]
        for uv in inside:  # every fully visible spot is found where it projects
            assert np.min(np.linalg.norm(blobs - uv, axis=1)) < 2.5
        seen += blobs.shape[0]
    # A few in each view, never dense paint: on average F * (view length / rack length).
    assert seen <= 0.6 * num_spots + 3


def test_none_in_view_outside_the_spot_range() -> None:
    cfg = FieldSceneConfig(num_spots=20, spots_y_m=(6.0, 10.0), **NO_BEAMS)  # type: ignore[arg-type]
    scene = FieldRackScene(MODEL, seed=2, config=cfg)
    bare = FieldRackScene(MODEL, seed=2, config=FieldSceneConfig(num_spots=0, **NO_BEAMS))  # type: ignore[arg-type]
    assert np.all(scene.spot_points_rack[:, 1] >= 6.0)
    assert _spot_blobs(bare, scene, se3.make(R_DOWN, [0.6, 2.0, 2.2]), CAM).shape[0] == 0


def test_distorted_images_match_the_calibration_projection() -> None:
    cam_d = PinholeCamera(width=360, height=240, fx=315.0, fy=315.0, cx=180.0, cy=120.0, dist=(-0.15, 0.02, 0.0, 0.0))
    cfg = FieldSceneConfig(num_spots=600, spot_diameter_m=(0.02, 0.02), **NO_BEAMS)  # type: ignore[arg-type]
    scene = FieldRackScene(MODEL, seed=8, config=cfg)
    bare = FieldRackScene(MODEL, seed=8, config=FieldSceneConfig(num_spots=0, **NO_BEAMS))  # type: ignore[arg-type]
    T = se3.make(R_DOWN, [0.6, 5.0, 1.8])
    blobs = _spot_blobs(bare, scene, T, cam_d)
    uv_cal = _visible_spots(scene, T, cam_d, 10.0)
    # The same spots as an undistorted camera would place them.
    X_cam = se3.act(se3.inverse(T), scene.spot_points_rack)
    uv_all = cam_d.project(X_cam)
    idx = [int(np.argmin(np.linalg.norm(uv_all - uv, axis=1))) for uv in uv_cal]
    uv_pin = CAM.project(X_cam[idx])
    err_cal = np.array([np.linalg.norm(blobs - uv, axis=1).min() for uv in uv_cal])
    err_pin = np.array([np.linalg.norm(blobs - uv, axis=1).min() for uv in uv_pin])
    far = np.linalg.norm(uv_pin - uv_cal, axis=1) > 3.0  # where the distortion moves a spot by > 3 px
    assert uv_cal.shape[0] >= 20 and far.sum() >= 5
    # Blobs sit where the calibration projects the spot centres (a few merge with neighbours: 600 spots).
    assert np.median(err_cal) < 0.5 and np.mean(err_cal < 1.5) > 0.8
    assert np.median(err_cal[far]) < 0.5 and np.median(err_pin[far]) > 2.0


def test_overhead_beam_occludes_the_pipes_and_pipes_shadow_the_ground() -> None:
    beam = FieldRackScene(MODEL, seed=1, config=FieldSceneConfig(overhead_beams_y_m=(5.0,), beam_spacing_m=0.0))
    plain = FieldRackScene(MODEL, seed=1, config=FieldSceneConfig(beam_spacing_m=0.0))
    cfg = beam.config
    T = se3.make(R_DOWN, [0.6, 5.0, 2.6])
    T_cam_rack = se3.inverse(T)
    img_b, img_p = beam.render_float(T, CAM), plain.render_float(T, CAM)
    # Above pipe 2's top at y = 5 the camera sees the beam's top face (painted steel, lit by sky + sun).
    u, v = np.rint(CAM.project(se3.act(T_cam_rack, np.array([0.5, 5.0, cfg.overhead_beam_z_m])))).astype(int)
    L = np.asarray(cfg.light_dir_rack) / np.linalg.norm(cfg.light_dir_rack)
    assert img_b[v, u] == pytest.approx(0.55 * (cfg.sky + cfg.sun * L[2]), abs=1e-4)
    assert abs(img_p[v, u] - img_b[v, u]) > 0.05
    u2, v2 = np.rint(CAM.project(se3.act(T_cam_rack, np.array([0.5, 4.5, 0.4])))).astype(int)
    assert img_b[v2, u2] == img_p[v2, u2]  # away from the beam nothing changes
    # A ground point whose sun ray passes through pipe 1's axis is in shadow: only sky light.
    no_shadow = FieldRackScene(MODEL, seed=1, config=FieldSceneConfig(beam_spacing_m=0.0, shadows=False))
    axis = np.array([0.15, 4.0, 0.15])
    g = axis + (cfg.ground_z_m - axis[2]) / L[2] * L
    T_g = se3.make(R_DOWN, [g[0], g[1], 2.6])
    ug, vg = np.rint(CAM.project(se3.act(se3.inverse(T_g), g))).astype(int)
    ratio = plain.render_float(T_g, CAM)[vg, ug] / no_shadow.render_float(T_g, CAM)[vg, ug]
    assert ratio == pytest.approx(cfg.sky / (cfg.sky + cfg.sun * L[2]), rel=1e-3)


def test_camera_pipeline_gain_motion_blur_and_jpeg() -> None:
    scene = FieldRackScene(MODEL, seed=4, config=FieldSceneConfig(ground="grating"))
    T = se3.make(R_DOWN, [0.6, 4.0, 2.4])
    base = scene.render(T, CAM).astype(float)
    dark = scene.render(T, CAM, gain=0.5).astype(float)
    assert dark.mean() == pytest.approx(0.5 * base.mean(), rel=0.05)
    # A horizontal shutter blur removes horizontal gradients far more than vertical ones.
    h_blur = scene.render(T, CAM, motion_blur_px=(8.0, 0.0)).astype(float)
    v_blur = scene.render(T, CAM, motion_blur_px=(0.0, 8.0)).astype(float)
    gx = lambda im: np.abs(np.diff(im, axis=1)).mean()  # noqa: E731
    gy = lambda im: np.abs(np.diff(im, axis=0)).mean()  # noqa: E731
    assert gx(h_blur) < 0.8 * gx(v_blur) and gy(v_blur) < 0.8 * gy(h_blur)
    data = scene.render_jpeg(T, CAM)
    assert data[:2] == b"\xff\xd8"  # a JPEG stream
    np.testing.assert_array_equal(decode_frame(data), scene.render(T, CAM))
    raw = FieldRackScene(MODEL, seed=4, config=FieldSceneConfig(ground="grating", jpeg_quality=0)).render(T, CAM)
    assert 0.3 < np.abs(raw.astype(float) - base).mean() < 4.0  # q70 artefacts: present, small
    ds = scene.image_motion_px(T, se3.make(R_DOWN, [0.64, 4.0, 2.4]), CAM)
    assert ds[0] == pytest.approx(-0.04 * 315.0 / (2.4 - 0.4), rel=1e-6) and abs(ds[1]) < 1e-9


def test_a_ground_image_replaces_the_procedural_ground() -> None:
    """`ground_albedo` lays an image on the ground plane (one texel `ground_texel_m`, wrapping): a ground seen
    beside the rack shows its stripes (columns = rack x), the pipes do not change; bad images are refused."""
    cfg = FieldSceneConfig(num_spots=0, ground_texel_m=0.01, **NO_BEAMS)
    stripes = np.tile(np.where(np.arange(64) % 16 < 8, 0.1, 0.9), (64, 1))  # 16 cm period along rack x
    T = se3.make(R_DOWN, [-1.6, 4.0, 1.2])  # the camera beside the rack: mostly ground (z = -2 m, 3.2 m away)
    plain = FieldRackScene(MODEL, seed=3, config=cfg).render_float(T, CAM)
    photo = FieldRackScene(MODEL, seed=3, config=cfg, ground_albedo=stripes).render_float(T, CAM)
    row = photo[120, :100]  # ground only at the left of the image
    period_px = 0.16 * CAM.fx / 3.2
    spec = np.abs(np.fft.rfft(row - row.mean()))
    k = int(np.argmax(spec[1:])) + 1
    assert abs(100.0 / k - period_px) < 2.0  # the stripes' period, in pixels at the ground's depth
    assert np.abs(photo[:, 100:] - plain[:, 100:]).max() > 0.1  # different grounds ...
    T_over = se3.make(R_DOWN, [0.6, 4.0, 1.0])
    over_plain = FieldRackScene(MODEL, seed=3, config=cfg).render_float(T_over, CAM)
    over_photo = FieldRackScene(MODEL, seed=3, config=cfg, ground_albedo=stripes).render_float(T_over, CAM)
    assert np.abs(over_plain[110:130, 170:190] - over_photo[110:130, 170:190]).max() < 1e-6  # ... the same pipe
    for bad in (np.zeros((8, 8)), np.zeros((3, 40, 40)), np.full((32, 32), np.nan)):
        with pytest.raises(InputError, match="ground_albedo"):
            FieldRackScene(MODEL, seed=3, config=cfg, ground_albedo=bad)
