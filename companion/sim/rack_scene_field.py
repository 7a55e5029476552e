"""A second, harsher appearance model of a pipe-rack: what a field camera sees, by per-pixel ray casting.

Same geometry and ray caster conventions as `rack_scene` (rack frame, z up; OpenCV pixel
centres), different appearance, chosen to stress a model-based tracker the way real images do:

- the texture "features" are the paper's F: `num_spots` dark spots in total over all parallel
  pipes (10 m each), so only a handful is in view, sometimes none; the cladding between them is
  pale and smooth (low-gradient dirt only, no corners);
- cladding shading: sky + sun Lambert, a smooth darkening towards the limb (the intensity rises
  from the silhouette inwards instead of stepping) and a Blinn-Phong specular highlight;
- ground of high contrast, procedural and photographic-like: a steel bar grating, concrete
  with painted markings and cracks, or a natural multi-scale (1/f) texture; the pipes, the
  crossing pipe and the beams cast sun shadows on it;
- support beams under the pipes (seen in the gaps) and optional overhead beams crossing above
  the pipes, which occlude them and are not in the tracker's model;
- a camera pipeline: per-frame gain (exposure steps, with saturation), optical blur, linear
  motion blur along the image motion, Gaussian noise, JPEG compression; lens distortion comes
  from the `PinholeCamera` given (rays are cast through its undistortion), so the images match
  the calibration's projection exactly.

Textures, spots and beams come from `seed`; image noise from the caller's generator. Pure: no
I/O, no clock. `FieldRackScene` has the constructor shape and the `render` / `render_float`
signatures of `RackScene` (with extra keyword-only options), so either can be swapped in.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.sim.rack_scene import _lookup, _rotate, _smooth_noise, supersample_silhouettes
from companion.sim.rack_scene_field_world import (
    F32,
    GROUND_KINDS,
    FieldSceneConfig,
    IntArray,
    _box_hits,
    _boxes,
    _ground_albedo,
)
from companion.vision.rack.model import RackModel

__all__ = ["GROUND_KINDS", "FieldRackScene", "FieldSceneConfig", "decode_frame"]


class FieldRackScene:
    """A renderable rack with field-like appearance; `render(T_rack_cam, camera)` -> (H, W) uint8.

    `model` is the TRUE geometry; `seed` fixes textures, spots and beams.
    """

    def __init__(self, model: RackModel, seed: int = 0, config: FieldSceneConfig | None = None,
                 ground_albedo: FloatArray | None = None) -> None:
        """`ground_albedo` (H, W), values in 0..1, replaces the procedural ground (`config.ground`): an image (a
        photograph of gravel, grass, paving) tiled over the ground plane, one texel `config.ground_texel_m`."""
        self.model = model
        self.config = cfg = config or FieldSceneConfig()
        rng = np.random.default_rng([seed, 7])
        self._pipes = p = model.pipe_arrays()
        v = p.directions
        helper = np.where(np.abs(v[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
        e1 = np.cross(helper, v)
        self._e1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
        self._e2 = np.cross(v, self._e1)
        light = np.asarray(cfg.light_dir_rack, dtype=np.float64)
        self._light = light / np.linalg.norm(light)
        self._textures = [self._cladding(rng, float(r), float(L)) for r, L in zip(p.radii, p.lengths, strict=True)]
        self._spots = self._draw_spots(np.random.default_rng([seed, 11]))
        if ground_albedo is None:
            self._ground = _ground_albedo(np.random.default_rng([seed, 13]), cfg.ground, 2048, cfg.ground_texel_m)
        else:
            g = np.asarray(ground_albedo, dtype=np.float32)
            if g.ndim != 2 or min(g.shape) < 16 or not np.all(np.isfinite(g)):
                raise InputError(f"ground_albedo: expected a finite (H, W) image of at least 16x16, got {g.shape}")
            self._ground = np.ascontiguousarray(np.clip(g, 0.02, 1.0))
        self._box_lo, self._box_hi = _boxes(model, cfg, np.random.default_rng([seed, 17]))
        self._ray_cache: dict[PinholeCamera, F32] = {}

    # ------------------------------------------------------------------ appearance set-up
    def _cladding(self, rng: np.random.Generator, radius_m: float, length_m: float) -> FloatArray:
        """Pale cladding albedo (rows: axial position, cols: arc length) with smooth dirt only."""
        cfg = self.config
        shape = (max(int(np.ceil(length_m / cfg.texel_m)), 2), max(int(np.ceil(2 * np.pi * radius_m / cfg.texel_m)), 8))
        tex = np.full(shape, rng.uniform(0.74, 0.86), dtype=np.float32)
        tex += 0.02 * _smooth_noise(rng, shape, 40.0)
        dirt = np.maximum(_smooth_noise(rng, shape, 25.0), 0.0)  # broad stains: no corners
        return np.asarray(np.clip(tex - cfg.dirt * 0.5 * dirt, 0.05, 1.0), dtype=np.float32)

    def _draw_spots(self, rng: np.random.Generator) -> FloatArray:
        """Paint F dark spots over the parallel pipes (upper 120 deg of arc); returns their centres (F, 3)."""
        cfg = self.config
        n_par = self.model.num_parallel
        p = self._pipes
        centres = np.zeros((cfg.num_spots, 3))
        for k in range(cfg.num_spots):
            m = int(rng.integers(0, n_par))
            lo, hi = cfg.spots_y_m if cfg.spots_y_m is not None else (0.0, float(p.lengths[m]))
            s_ax = float(rng.uniform(max(lo, 0.05), min(hi, float(p.lengths[m]) - 0.05)))
            # Arc angle from the top (+z); e1/e2 span the cross-section, atan2(e2, e1) is the texture angle.
            top = np.arctan2(self._e2[m, 2], self._e1[m, 2])
            ang = float(top + rng.uniform(-np.pi / 3, np.pi / 3))
            radial = np.cos(ang) * self._e1[m] + np.sin(ang) * self._e2[m]
            centres[k] = p.starts[m] + s_ax * p.directions[m] + p.radii[m] * radial
            tex = self._textures[m]
            r = float(p.radii[m])
            diam = rng.uniform(*cfg.spot_diameter_m)
            axes = (max(int(diam / 2 / cfg.texel_m), 1), max(int(diam / 2 * rng.uniform(0.6, 1.4) / cfg.texel_m), 1))
            mask = np.zeros(tex.shape, dtype=np.float32)
            col = (np.mod(ang, 2 * np.pi) * r) / cfg.texel_m
            centre = (round(16 * col), round(16 * s_ax / cfg.texel_m))  # 4 fractional bits: sub-texel centre
            axes = (16 * axes[0], 16 * axes[1])
            cv2.ellipse(mask, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1.0, -1, cv2.LINE_AA, 4)
            tex *= 1.0 - cv2.GaussianBlur(mask, (0, 0), 1.0) * float(rng.uniform(0.6, 0.75))
        return centres

    @property
    def cumulative_gaps(self) -> FloatArray:
        """True cumulative gaps d̄_1 ... d̄_{n-1} (m) of the rendered rack."""
        return self.model.cumulative_gaps

    @property
    def spot_points_rack(self) -> FloatArray:
        """Centres (F, 3) of the texture spots on the pipe surfaces (rack frame, m)."""
        return self._spots.copy()

    # ------------------------------------------------------------------ ray casting
    def _rays(self, camera: PinholeCamera) -> F32:
        rays = self._ray_cache.get(camera)
        if rays is None:
            vv, uu = np.mgrid[0 : camera.height, 0 : camera.width]
            rays = camera.unproject(np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)).astype(np.float32)
            if len(self._ray_cache) > 4:
                self._ray_cache.clear()
            self._ray_cache[camera] = rays
        return rays

    def _pipe_hits(self, o: FloatArray, d: F32, t_best: F32) -> tuple[F32, IntArray]:
        """Nearest pipe hit distance (P,) below `t_best` and pipe id (-1: none)."""
        p = self._pipes
        best = np.full(d.shape[0], -1, dtype=np.intp)
        for m in range(p.radii.size):
            w = (o - p.starts[m]).astype(np.float32)
            vm = p.directions[m].astype(np.float32)
            wv = float(w @ vm)
            dv = d @ vm
            B = d @ w - dv * wv
            A = 1.0 - dv * dv
            C = float(w @ w) - wv * wv - float(p.radii[m]) ** 2
            disc = B * B - A * C
            with np.errstate(invalid="ignore", divide="ignore"):
                t = (-B - np.sqrt(disc)) / A
            s = wv + t * dv
            closer = (disc > 0) & (t > 0) & (s >= 0) & (s <= float(p.lengths[m])) & (t < t_best)
            t_best = np.where(closer, t, t_best)
            best = np.where(closer, m, best)
        return t_best, best

    def _in_shadow(self, h: FloatArray) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """Whether ground points h (N, 3) see the sun blocked by a pipe or a beam."""
        out = np.zeros(h.shape[0], dtype=bool)
        p = self._pipes
        L = self._light
        hx, hy, hz = (np.ascontiguousarray(h[:, a], dtype=np.float32) for a in range(3))
        for m in range(p.radii.size):  # the cylinder test of `_pipe_hits`, one origin per point
            c, vm = p.starts[m], p.directions[m]
            wx, wy, wz = hx - np.float32(c[0]), hy - np.float32(c[1]), hz - np.float32(c[2])
            wv = wx * np.float32(vm[0]) + wy * np.float32(vm[1]) + wz * np.float32(vm[2])
            lv = float(L @ vm)
            B = wx * np.float32(L[0]) + wy * np.float32(L[1]) + wz * np.float32(L[2]) - np.float32(lv) * wv
            C = wx * wx + wy * wy + wz * wz - wv * wv - np.float32(p.radii[m] ** 2)
            disc = B * B - np.float32(1.0 - lv * lv) * C
            with np.errstate(invalid="ignore", divide="ignore"):
                t = (-B - np.sqrt(disc)) / np.float32(1.0 - lv * lv)
            s = wv + t * np.float32(lv)
            out |= (disc > 0) & (t > 0) & (s >= 0) & (s <= np.float32(p.lengths[m]))
        with np.errstate(divide="ignore", invalid="ignore"):
            for b in range(self._box_lo.shape[0]):  # slab test, one origin per point
                t_in = np.full(h.shape[0], -np.inf, dtype=np.float32)
                t_out = np.full(h.shape[0], np.inf, dtype=np.float32)
                for a, col in enumerate((hx, hy, hz)):
                    inv = np.float32(1.0 / L[a]) if L[a] != 0 else np.float32(np.inf)
                    t1 = (np.float32(self._box_lo[b, a]) - col) * inv
                    t2 = (np.float32(self._box_hi[b, a]) - col) * inv
                    t_in = np.fmax(t_in, np.fmin(t1, t2))
                    t_out = np.fmin(t_out, np.fmax(t1, t2))
                out |= (t_in <= t_out) & (t_out > 0)
        return out

    def _shade(self, o: FloatArray, d: F32) -> tuple[F32, IntArray]:
        """Radiance (P,) and hit id (pipe index, -1 ground, -2 sky, -3 - b beam b) of unit rays o + t d."""
        cfg = self.config
        t_box, box, box_axis = _box_hits(o, d, self._box_lo, self._box_hi)
        t_best, pipe = self._pipe_hits(o, d, t_box)
        out = np.full(d.shape[0], cfg.sky_level, dtype=np.float32)
        ids = np.where(pipe >= 0, pipe, np.where(box >= 0, -3 - box, -2))
        with np.errstate(invalid="ignore", divide="ignore"):
            t_g = (cfg.ground_z_m - o[2]) / d[:, 2]
        ground = (d[:, 2] < -1e-6) & (t_g > 0) & (t_g < t_best)
        ids[ground] = -1
        gi = np.flatnonzero(ground)
        if gi.size:
            h = o[None, :] + t_g[gi, None].astype(np.float64) * d[gi].astype(np.float64)
            alb = _lookup(self._ground, h[:, 0] / cfg.ground_texel_m, h[:, 1] / cfg.ground_texel_m)
            lit = np.ones(gi.size, dtype=np.float32)
            if cfg.shadows:
                lit[self._in_shadow(h)] = 0.0
            out[gi] = alb * (cfg.sky + cfg.sun * float(self._light[2]) * lit)
        bi = np.flatnonzero(ids <= -3)
        if bi.size:  # painted steel, Lambert on the face entered
            n = np.zeros((bi.size, 3))
            n[np.arange(bi.size), box_axis[bi]] = -np.sign(d[bi, box_axis[bi]])
            out[bi] = 0.55 * (cfg.sky + cfg.sun * np.maximum(n @ self._light, 0.0))
        p = self._pipes
        for m in range(p.radii.size):
            pi = np.flatnonzero(pipe == m)
            if pi.size == 0:
                continue
            dd = d[pi].astype(np.float64)
            rel = (o - p.starts[m])[None, :] + t_best[pi, None].astype(np.float64) * dd
            s_ax = rel @ p.directions[m]
            n = (rel - s_ax[:, None] * p.directions[m]) * (1.0 / p.radii[m])
            ang = np.arctan2(n @ self._e2[m], n @ self._e1[m])
            alb = _lookup(self._textures[m], np.mod(ang, 2 * np.pi) * p.radii[m] / cfg.texel_m, s_ax / cfg.texel_m)
            nd = n[:, 0] * dd[:, 0] + n[:, 1] * dd[:, 1] + n[:, 2] * dd[:, 2]
            nv = np.clip(-nd, 0.0, 1.0)
            nl = np.maximum(n @ self._light, 0.0)
            diffuse = cfg.sky * (0.6 + 0.4 * n[:, 2]) + cfg.sun * nl
            limb = 1.0 - cfg.limb_darkening * (1.0 - nv) ** 2  # smooth rise inside the silhouette
            # Blinn-Phong: n . h with h = (l - d) / |l - d|, |l - d|^2 = 2 - 2 l . d.
            ld = dd @ self._light
            nh = (nl - nd) / np.sqrt(np.maximum(2.0 - 2.0 * ld, 1e-12))  # nl = n . l where it matters (nl > 0)
            spec = cfg.specular * np.maximum(nh, 0.0) ** cfg.shininess * (nl > 0)
            out[pi] = alb * diffuse * limb + spec
        return out, ids

    def render_float(self, T_rack_cam: Any, camera: PinholeCamera, antialias: int = 3) -> F32:
        """Noise-free radiance image (H, W) float32 (about 0..1, highlights may exceed 1).

        Silhouette pixels (a neighbour sees another surface) average `antialias`^2 sub-pixel rays.
        """
        T = check_transform(T_rack_cam, "T_rack_cam")
        R = T[:3, :3].astype(np.float32)
        o = T[:3, 3]
        out, ids = self._shade(o, _rotate(self._rays(camera), R))
        H, W = camera.height, camera.width
        img = out.reshape(H, W)
        if antialias > 1:
            supersample_silhouettes(img, ids.reshape(H, W), camera, R, lambda rays: self._shade(o, rays)[0],
                                    int(antialias))
        return img

    def image_motion_px(self, T_rack_cam: Any, T_rack_cam_end: Any, camera: PinholeCamera) -> tuple[float, float]:
        """Image motion (px) of the pipes' top plane point under the image centre between two poses."""
        T0 = check_transform(T_rack_cam, "T_rack_cam")
        T1 = check_transform(T_rack_cam_end, "T_rack_cam_end")
        ray = T0[:3, :3] @ camera.unproject(np.array([camera.cx, camera.cy]))
        top = float(2.0 * np.max(self._pipes.radii[: self.model.num_parallel]))
        t = (top - T0[2, 3]) / ray[2] if ray[2] < -1e-3 else 3.0
        X = T0[:3, 3] + max(float(t), 0.3) * ray
        uv0 = camera.project((X - T0[:3, 3]) @ T0[:3, :3])
        uv1 = camera.project((X - T1[:3, 3]) @ T1[:3, :3])
        return float(uv1[0] - uv0[0]), float(uv1[1] - uv0[1])

    def render_jpeg(
        self, T_rack_cam: Any, camera: PinholeCamera, noise_std: float = 0.0, blur_sigma_px: float = 0.6,
        rng: np.random.Generator | None = None, supersample: int = 1, antialias: int = 3, *,
        gain: float = 1.0, motion_blur_px: tuple[float, float] = (0.0, 0.0),
    ) -> bytes:
        """The camera's encoded frame (JPEG at `config.jpeg_quality`; PNG when it is 0); see `render`."""
        if supersample < 1:
            raise InputError(f"supersample: must be >= 1, got {supersample}")
        if supersample > 1:
            big = self.render_float(T_rack_cam, camera.scaled(float(supersample)), antialias)
            img = cv2.resize(big, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        else:
            img = self.render_float(T_rack_cam, camera, antialias)
        img = img * np.float32(255.0 * gain)
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
        length = float(np.hypot(*motion_blur_px))
        if length >= 0.5:  # linear shutter blur along the image motion
            k = int(np.ceil(length)) | 1
            kernel = np.zeros((k, k), dtype=np.float32)
            c = (k - 1) / 2.0
            ux, uy = motion_blur_px[0] / length, motion_blur_px[1] / length
            for s in np.linspace(-length / 2, length / 2, 4 * k):
                kernel[round(c + s * uy), round(c + s * ux)] += 1.0
            img = cv2.filter2D(img, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REPLICATE)
        if noise_std > 0:
            if rng is None:
                raise InputError("rng: required when noise_std > 0")
            img = img + rng.standard_normal(img.shape).astype(np.float32) * np.float32(noise_std)
        u8 = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        q = self.config.jpeg_quality
        ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, q]) if q > 0 else cv2.imencode(".png", u8)
        if not ok:
            raise InputError("image: encoding failed")
        return bytes(buf.tobytes())

    def render(
        self, T_rack_cam: Any, camera: PinholeCamera, noise_std: float = 0.0, blur_sigma_px: float = 0.6,
        rng: np.random.Generator | None = None, supersample: int = 1, antialias: int = 3, *,
        gain: float = 1.0, motion_blur_px: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray[Any, np.dtype[np.uint8]]:
        """Grayscale uint8 image (H, W) at pose `T_rack_cam`, through the camera pipeline.

        Arguments as `RackScene.render`; `gain` scales the exposure (values clip at 255),
        `motion_blur_px` the image motion (du, dv) during the exposure (see `image_motion_px`).
        """
        data = self.render_jpeg(T_rack_cam, camera, noise_std, blur_sigma_px, rng, supersample, antialias,
                                gain=gain, motion_blur_px=motion_blur_px)
        return decode_frame(data)


def decode_frame(data: bytes) -> np.ndarray[Any, np.dtype[np.uint8]]:
    """Decode a frame made by `FieldRackScene.render_jpeg` into (H, W) uint8."""
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError("data: not an encoded image")
    return np.asarray(img, dtype=np.uint8)
