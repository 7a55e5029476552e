"""Synthetic grayscale images of a pipe-rack over textured ground, by per-pixel ray casting.

Every pixel centre's ray (OpenCV convention: integer coordinates are pixel centres) is
intersected analytically with each finite cylinder of the rack and with the ground plane
z = `ground_z_m` (rack frame, z up); the nearest hit is shaded (Lambert, one directional
light plus ambient) with a texture attached to the 3-D surface: the pipes carry paint with
rust-like spots in cylinder coordinates (axial position, arc length), the ground a gravel-like
pattern. Pixels on a silhouette are re-rendered with sub-pixel rays and averaged (area
integration, so edges are not quantized to pixel centres); each cylinder is only intersected
with the rays inside its projected bounding rectangle. Textures come from `seed`, so the same
scene renders the same images from the same poses; image noise has its own generator. Pure:
no I/O, no clock. A 720x480 frame takes a few tens of ms on one core.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.vision.rack.model import RackModel


def _rotate(rays: np.ndarray[Any, Any], R: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.float32]]:
    """`rays @ R.T` for (P, 3) float32 rays, through OpenCV.

    numpy's matmul hands large products to the BLAS thread pool, which on a loaded 2-core
    companion computer (capture thread, vision worker, asyncio loop) made a 360x240 frame take
    40 ms instead of 11 ms; `cv2.transform` follows `cv2.setNumThreads`.
    """
    r = np.ascontiguousarray(rays, dtype=np.float32).reshape(-1, 1, 3)
    return np.asarray(cv2.transform(r, np.asarray(R, dtype=np.float32)), dtype=np.float32).reshape(-1, 3)


def supersample_silhouettes(img: Any, ids: Any, camera: PinholeCamera, R: Any, shade: Any, k: int) -> None:
    """Anti-alias in place: pixels where a neighbour sees another surface (`ids` differ) become the mean of
    k x k sub-pixel rays; `shade(rays_rack)` returns their grey levels, `R` rotates camera rays to the rack."""
    H, W = ids.shape
    edge = np.zeros((H, W), dtype=bool)
    dif_x = ids[:, 1:] != ids[:, :-1]
    dif_y = ids[1:, :] != ids[:-1, :]
    edge[:, 1:] |= dif_x
    edge[:, :-1] |= dif_x
    edge[1:, :] |= dif_y
    edge[:-1, :] |= dif_y
    vv, uu = np.nonzero(edge)
    if vv.size == 0:
        return
    off = (np.arange(k) + 0.5) / k - 0.5
    ox, oy = np.meshgrid(off, off)
    uv = np.stack([uu[:, None] + ox.ravel()[None, :], vv[:, None] + oy.ravel()[None, :]], axis=-1)
    rays = _rotate(camera.unproject(uv.reshape(-1, 2)).astype(np.float32), R)
    img[vv, uu] = np.asarray(shade(rays)).reshape(-1, k * k).mean(axis=1)


@dataclass(frozen=True)
class RackSceneConfig:
    """Appearance of the synthetic scene.

    `ground_z_m`: height of the ground plane in the rack frame (m, below the support plane);
    `texel_m`: pipe texture resolution (m); `spots_per_m2`: rust spots per square metre of pipe
    surface; `light_dir_rack`: direction towards the light (rack frame); `ambient`: ambient
    fraction; `sky_level`: intensity (0..1) of rays that hit nothing. `total_spots`, when set,
    replaces `spots_per_m2`: exactly that many spots over all pipes, shared in proportion to
    their surface (the paper's F features in total).
    """

    ground_z_m: float = -3.0
    texel_m: float = 0.004
    spots_per_m2: float = 30.0
    total_spots: int | None = None
    ground_texel_m: float = 0.01
    ground_level: float = 0.22
    ground_contrast: float = 0.035
    light_dir_rack: tuple[float, float, float] = (0.35, -0.25, 1.0)
    ambient: float = 0.5
    sky_level: float = 0.8


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> FloatArray:
    """Zero-mean, unit-std Gaussian-filtered white noise; large sigmas are made at low resolution."""
    if sigma >= 4.0:
        f = sigma / 2.0
        small = (max(int(shape[0] / f), 4), max(int(shape[1] / f), 4))
        n = cv2.GaussianBlur(rng.standard_normal(small).astype(np.float32), (0, 0), 2.0,
                             borderType=cv2.BORDER_REFLECT)
        n = cv2.resize(n, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    else:
        n = rng.standard_normal(shape).astype(np.float32)
        if sigma > 0:
            n = cv2.GaussianBlur(n, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    n = n - float(n.mean())
    std = float(n.std())
    return np.asarray(n / (std if std > 0 else 1.0), dtype=np.float32)


def _pipe_texture(
    rng: np.random.Generator, radius_m: float, length_m: float, cfg: RackSceneConfig, n_spots: int | None = None
) -> FloatArray:
    """Albedo (rows: axial position, cols: arc length) of one pipe, values in [0, 1]."""
    n_ax = max(int(np.ceil(length_m / cfg.texel_m)), 2)
    n_arc = max(int(np.ceil(2.0 * np.pi * radius_m / cfg.texel_m)), 8)
    paint = rng.uniform(0.62, 0.8)
    tex = np.full((n_ax, n_arc), paint, dtype=np.float32)
    tex += 0.04 * _smooth_noise(rng, (n_ax, n_arc), 12.0)
    tex += 0.015 * _smooth_noise(rng, (n_ax, n_arc), 0.7)
    # Rust spots: dark blotches of random size, shape and darkness, soft-edged.
    area = length_m * 2.0 * np.pi * radius_m
    if n_spots is None:
        n_spots = int(rng.poisson(cfg.spots_per_m2 * area))
    alpha = np.zeros((n_ax, n_arc), dtype=np.float32)
    level = np.zeros((n_ax, n_arc), dtype=np.float32)
    for _ in range(int(n_spots)):
        cy, cx = rng.uniform(0, n_ax), rng.uniform(0, n_arc)
        ax = max(int(rng.uniform(0.008, 0.04) / cfg.texel_m), 1)
        ay = max(int(ax * rng.uniform(0.4, 1.6)), 1)
        ang = float(rng.uniform(0, 180))
        val = float(rng.uniform(0.18, 0.42))
        center = (int(cx), int(cy))
        cv2.ellipse(alpha, center, (ax, ay), ang, 0, 360, 1.0, -1)
        cv2.ellipse(level, center, (ax, ay), ang, 0, 360, val, -1)
    alpha_s = np.asarray(cv2.GaussianBlur(alpha, (0, 0), 1.2), dtype=np.float32)
    rough = 1.0 + 0.25 * _smooth_noise(rng, (n_ax, n_arc), 2.0)
    out = tex * (1.0 - alpha_s) + level * rough * alpha_s
    return np.asarray(np.clip(out, 0.02, 1.0), dtype=np.float32)


def _ground_texture(rng: np.random.Generator, cfg: RackSceneConfig, size: int = 2048) -> FloatArray:
    g = np.full((size, size), cfg.ground_level, dtype=np.float32)
    for sigma, amp in ((1.0, 1.0), (4.0, 1.2), (24.0, 1.2)):
        g += cfg.ground_contrast * amp * _smooth_noise(rng, (size, size), sigma)
    return np.clip(g, 0.02, 1.0).astype(np.float32)


def _lookup(tex: FloatArray, x: FloatArray, y: FloatArray) -> FloatArray:
    """Bilinear, wrapping texture lookup at texel coordinates (x: column, y: row), any length."""
    n = x.size
    cols = 1024
    rows = max((n + cols - 1) // cols, 1)
    mx = np.zeros(rows * cols, dtype=np.float32)
    my = np.zeros(rows * cols, dtype=np.float32)
    mx[:n] = x
    my[:n] = y
    out = cv2.remap(tex, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return np.asarray(out.ravel()[:n], dtype=np.float32)


class RackScene:
    """A renderable rack: `render(T_rack_cam, camera)` returns a (H, W) uint8 image.

    `model` is the TRUE geometry (true gaps); `seed` fixes every texture.
    """

    def __init__(self, model: RackModel, seed: int = 0, config: RackSceneConfig | None = None) -> None:
        self.model = model
        self.config = config or RackSceneConfig()
        rng = np.random.default_rng(seed)
        self._pipes = model.pipe_arrays()
        counts: list[int | None] = [None] * self._pipes.radii.size
        if self.config.total_spots is not None:
            area = self._pipes.radii * self._pipes.lengths
            drawn = np.random.default_rng([seed, 5]).multinomial(int(self.config.total_spots), area / area.sum())
            counts = [int(c) for c in drawn]
        self._textures = [
            _pipe_texture(rng, float(r), float(L), self.config, n)
            for r, L, n in zip(self._pipes.radii, self._pipes.lengths, counts, strict=True)
        ]
        self._ground = _ground_texture(rng, self.config)
        # Orthonormal basis (e1, e2) perpendicular to each pipe axis for the arc coordinate.
        v = self._pipes.directions
        helper = np.where(np.abs(v[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
        e1 = np.cross(helper, v)
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        self._e1 = e1
        self._e2 = np.cross(v, e1)
        light = np.asarray(self.config.light_dir_rack, dtype=np.float64)
        self._light = light / np.linalg.norm(light)
        self._ray_cache: dict[PinholeCamera, FloatArray] = {}

    @property
    def cumulative_gaps(self) -> FloatArray:
        """True cumulative gaps d̄_1 ... d̄_{n-1} (m) of the rendered rack."""
        return self.model.cumulative_gaps

    def _rays(self, camera: PinholeCamera) -> FloatArray:
        rays = self._ray_cache.get(camera)
        if rays is None:
            vv, uu = np.mgrid[0 : camera.height, 0 : camera.width]
            uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
            rays = camera.unproject(uv).astype(np.float32)
            if len(self._ray_cache) > 4:
                self._ray_cache.clear()
            self._ray_cache[camera] = rays
        return rays

    def _pipe_pixels(self, T: FloatArray, camera: PinholeCamera) -> list[np.ndarray[Any, np.dtype[np.intp]] | None]:
        """Per pipe, the flat indices of the image rectangle bounding its projection (None = all)."""
        pipes = self._pipes
        T_cam_rack = np.linalg.inv(T)
        out: list[np.ndarray[Any, np.dtype[np.intp]] | None] = []
        W, H = camera.width, camera.height
        for m in range(pipes.radii.size):
            c, v, r, L = pipes.starts[m], pipes.directions[m], float(pipes.radii[m]), float(pipes.lengths[m])
            corners = np.array([c + a * L * v + r * (sx * self._e1[m] + sy * self._e2[m])
                                for a in (0.0, 1.0) for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)])
            p = corners @ T_cam_rack[:3, :3].T + T_cam_rack[:3, 3]
            if np.any(p[:, 2] < 0.05) or camera.has_distortion:
                out.append(None)
                continue
            uv = camera.project(p)
            u0, v0 = (max(int(np.floor(x)) - 2, 0) for x in uv.min(axis=0))
            u1, v1 = min(int(np.ceil(uv[:, 0].max())) + 3, W), min(int(np.ceil(uv[:, 1].max())) + 3, H)
            if u1 <= u0 or v1 <= v0:
                out.append(np.zeros(0, dtype=np.intp))
                continue
            out.append((np.arange(v0, v1)[:, None] * W + np.arange(u0, u1)[None, :]).ravel())
        return out

    def _shade(
        self,
        o: FloatArray,
        d: np.ndarray[Any, np.dtype[np.float32]],
        subsets: list[np.ndarray[Any, np.dtype[np.intp]] | None] | None = None,
    ) -> tuple[np.ndarray[Any, np.dtype[np.float32]], np.ndarray[Any, np.dtype[np.intp]]]:
        """Radiance (P,) and hit id (P,) (pipe index, -1 ground, -2 sky) of unit rays o + t d (rack frame).

        `subsets[m]`, when given, lists the only rays that can hit pipe m.
        """
        P = d.shape[0]
        pipes = self._pipes
        c, v, r, L = pipes.starts, pipes.directions, pipes.radii, pipes.lengths
        t_best = np.full(P, np.inf, dtype=np.float32)
        best = np.zeros(P, dtype=np.intp)
        for m in range(c.shape[0]):
            idx = None if subsets is None else subsets[m]
            dm = d if idx is None else d[idx]
            if dm.shape[0] == 0:
                continue
            w = (o - c[m]).astype(np.float32)
            vm = v[m].astype(np.float32)
            wv = float(w @ vm)
            dv = dm @ vm
            B = dm @ w - dv * wv
            A = 1.0 - dv * dv
            C = float(w @ w) - wv * wv - float(r[m]) ** 2
            disc = B * B - A * C
            with np.errstate(invalid="ignore", divide="ignore"):
                t = (-B - np.sqrt(disc)) / A
            s = wv + t * dv
            ok = (disc > 0) & (t > 0) & (s >= 0) & (s <= float(L[m]))
            t = np.where(ok, t, np.float32(np.inf))
            if idx is None:
                closer = t < t_best
                t_best = np.where(closer, t, t_best)
                best = np.where(closer, m, best)
            else:
                closer = t < t_best[idx]
                sel = idx[closer]
                t_best[sel] = t[closer]
                best[sel] = m
        out = np.full(P, self.config.sky_level, dtype=np.float32)
        ids = np.full(P, -2, dtype=np.intp)
        # Ground plane.
        dz = d[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            t_g = (self.config.ground_z_m - o[2]) / dz
        ground = (dz < -1e-6) & (t_g > 0) & (t_g < t_best)
        if np.any(ground):
            gi = np.flatnonzero(ground)
            hx = o[0] + t_g[gi] * d[gi, 0]
            hy = o[1] + t_g[gi] * d[gi, 1]
            alb = _lookup(self._ground, hx / self.config.ground_texel_m, hy / self.config.ground_texel_m)
            shade = self.config.ambient + (1.0 - self.config.ambient) * max(float(self._light[2]), 0.0)
            out[gi] = alb * shade
            ids[gi] = -1
        hit_pipe = np.isfinite(t_best)
        for m in range(c.shape[0]):
            pi = np.flatnonzero(hit_pipe & (best == m))
            if pi.size == 0:
                continue
            h = o[None, :] + t_best[pi, None].astype(np.float64) * d[pi].astype(np.float64)
            rel = h - c[m]
            s_ax = rel @ v[m]
            radial = rel - s_ax[:, None] * v[m]
            n = radial / r[m]
            ang = np.arctan2(radial @ self._e2[m], radial @ self._e1[m])
            arc = np.mod(ang, 2.0 * np.pi) * r[m]
            tex = self._textures[m]
            alb = _lookup(tex, arc / self.config.texel_m, s_ax / self.config.texel_m)
            lam = np.maximum(n @ self._light, 0.0)
            out[pi] = alb * (self.config.ambient + (1.0 - self.config.ambient) * lam)
            ids[pi] = m
        return out, ids

    def render_float(
        self, T_rack_cam: Any, camera: PinholeCamera, antialias: int = 3
    ) -> np.ndarray[Any, np.dtype[np.float32]]:
        """Noise-free radiance image (H, W) float32 in [0, 1].

        Pixels on a silhouette (a neighbour sees another surface) are re-rendered with
        `antialias` x `antialias` sub-pixel rays and averaged: the pixel integrates its area as a
        real sensor does, so edges are not quantized to pixel centres (0 or 1 disables).
        """
        T = check_transform(T_rack_cam, "T_rack_cam")
        R = T[:3, :3].astype(np.float32)
        o = T[:3, 3]
        d = _rotate(self._rays(camera), R)  # (P, 3) rack frame, unit
        out, ids = self._shade(o, d, self._pipe_pixels(T, camera))
        H, W = camera.height, camera.width
        img = out.reshape(H, W)
        if antialias > 1:
            supersample_silhouettes(img, ids.reshape(H, W), camera, R, lambda rays: self._shade(o, rays)[0],
                                    int(antialias))
        return img

    def render(
        self,
        T_rack_cam: Any,
        camera: PinholeCamera,
        noise_std: float = 0.0,
        blur_sigma_px: float = 0.6,
        rng: np.random.Generator | None = None,
        supersample: int = 1,
        antialias: int = 3,
    ) -> np.ndarray[Any, np.dtype[np.uint8]]:
        """Grayscale uint8 image (H, W) seen by `camera` at pose `T_rack_cam` (camera in rack frame).

        `noise_std` is the standard deviation of additive Gaussian noise in grey levels (0..255),
        drawn from `rng` (required when noise_std > 0); `blur_sigma_px` a Gaussian optical blur;
        `supersample` renders the whole image at that factor and averages down; `antialias`
        sub-pixel rays per axis on silhouette pixels (see `render_float`).
        """
        if supersample < 1:
            raise InputError(f"supersample: must be >= 1, got {supersample}")
        if supersample > 1:
            big = self.render_float(T_rack_cam, camera.scaled(float(supersample)), antialias)
            img = cv2.resize(big, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        else:
            img = self.render_float(T_rack_cam, camera, antialias)
        img = img * 255.0
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
        if noise_std > 0:
            if rng is None:
                raise InputError("rng: required when noise_std > 0")
            img = img + rng.standard_normal(img.shape).astype(np.float32) * np.float32(noise_std)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
