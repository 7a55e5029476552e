"""The field scene's configuration and its static world: ground albedo textures, beams as boxes, ray-box hits.

Split out of `rack_scene_field` (which renders with them and re-exports `GROUND_KINDS` and
`FieldSceneConfig`); rack frame, z up, metres, intensities 0..1 as there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError
from companion.sim.rack_scene import _smooth_noise
from companion.vision.rack.model import RackModel

__all__ = ["GROUND_KINDS", "FieldSceneConfig"]

GROUND_KINDS = ("grating", "concrete", "natural")
IntArray = np.ndarray[Any, np.dtype[np.intp]]
F32 = np.ndarray[Any, np.dtype[np.float32]]


@dataclass(frozen=True)
class FieldSceneConfig:
    """Appearance of the field scene (metres, radians, intensities 0..1).

    `num_spots`: F, dark spots in total over the parallel pipes; `spots_y_m`: axial (rack y)
    range they are drawn in (None: the whole length); `spot_diameter_m`: size range. `ground`:
    one of GROUND_KINDS; `ground_z_m`: ground plane height; `shadows`: cast sun shadows on the
    ground. `beam_spacing_m`: support beams under the pipes every that many metres along y (0:
    none); `overhead_beams_y_m`: y of beams crossing above the pipes at `overhead_beam_z_m`
    (occluders not in the tracker's model). `light_dir_rack`: towards the sun; `sun`, `sky`:
    their intensities; `limb_darkening`: depth of the shading dip at the limb (0..1);
    `specular`, `shininess`: the highlight; `dirt`: depth of the smooth dirt on the cladding;
    `jpeg_quality`: 0 disables compression.
    """

    num_spots: int = 30
    spots_y_m: tuple[float, float] | None = None
    spot_diameter_m: tuple[float, float] = (0.025, 0.06)
    ground: str = "concrete"
    ground_z_m: float = -2.0
    ground_texel_m: float = 0.008
    shadows: bool = True
    beam_spacing_m: float = 3.0
    overhead_beams_y_m: tuple[float, ...] = ()
    overhead_beam_z_m: float = 1.0
    texel_m: float = 0.004
    light_dir_rack: tuple[float, float, float] = (0.55, 0.2, 0.8)
    sun: float = 0.62
    sky: float = 0.42
    limb_darkening: float = 0.55
    specular: float = 0.35
    shininess: float = 30.0
    dirt: float = 0.12
    sky_level: float = 0.85
    jpeg_quality: int = 70

    def __post_init__(self) -> None:
        if self.ground not in GROUND_KINDS:
            raise InputError(f"ground: expected one of {GROUND_KINDS}, got {self.ground!r}")
        if self.num_spots < 0:
            raise InputError(f"num_spots: must be >= 0, got {self.num_spots}")
        if not 0 <= self.jpeg_quality <= 100:
            raise InputError(f"jpeg_quality: must be in 0..100, got {self.jpeg_quality}")


def _ground_albedo(rng: np.random.Generator, kind: str, size: int, texel_m: float) -> FloatArray:
    """Wrapping ground albedo (size x size texels of `texel_m`), high contrast, of the given kind."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) * np.float32(texel_m)
    if kind == "grating":
        # Bearing bars (3 cm pitch, 5 mm wide) nearly parallel to the pipes, cross bars every 10 cm,
        # dark holes: a periodic, very high-contrast pattern right under the limbs.
        ang = float(rng.uniform(-0.15, 0.15))
        u = np.cos(ang) * xx - np.sin(ang) * yy
        w = np.sin(ang) * xx + np.cos(ang) * yy
        bars = (np.mod(u, 0.03) < 0.006) | (np.mod(w, 0.10) < 0.008)
        metal = 0.5 + 0.08 * _smooth_noise(rng, (size, size), 6.0) + 0.04 * _smooth_noise(rng, (size, size), 1.0)
        hole = 0.07 + 0.04 * _smooth_noise(rng, (size, size), 20.0)
        g = np.where(bars, metal, hole)
    elif kind == "concrete":
        g = 0.5 + 0.07 * _smooth_noise(rng, (size, size), 1.0) + 0.08 * _smooth_noise(rng, (size, size), 30.0)
        g = np.asarray(g, dtype=np.float32)
        paint = np.zeros((size, size), dtype=np.uint8)
        px_m = 1.0 / texel_m
        for _ in range(int(rng.integers(5, 9))):  # painted lines, half of them parallel to the pipes
            along = rng.uniform() < 0.5
            width = int(rng.uniform(0.05, 0.15) * px_m)
            c = int(rng.uniform(0, size))
            p0, p1 = ((c, 0), (c, size)) if along else ((0, c), (size, c))
            cv2.line(paint, p0, p1, 1, max(width, 2))
        for _ in range(int(rng.integers(2, 5))):  # hatched boxes
            x0, y0 = (int(v) for v in rng.uniform(0, size - 200, 2))
            for k in range(0, 160, 24):
                cv2.line(paint, (x0 + k, y0), (x0 + k + 40, y0 + 40), 1, 6)
        g = np.where(paint > 0, 0.92 - 0.08 * np.abs(_smooth_noise(rng, (size, size), 3.0)), g)
        cracks = np.zeros((size, size), dtype=np.uint8)
        for _ in range(40):
            pts = np.cumsum(rng.normal(0, 6, (30, 2)), axis=0) + rng.uniform(0, size, 2)
            cv2.polylines(cracks, [pts.astype(np.int32)], False, 1, 1)
        g = np.where(cracks > 0, 0.12, g)
        for _ in range(6):  # oil stains
            cx, cy = (int(v) for v in rng.uniform(0, size, 2))
            stain = np.zeros((size, size), dtype=np.float32)
            cv2.circle(stain, (cx, cy), int(rng.uniform(20, 60)), 1.0, -1)
            g = g * (1.0 - 0.6 * cv2.GaussianBlur(stain, (0, 0), 8.0))
    else:  # natural: gravel, grass and soil, 1/f over six octaves
        g = np.full((size, size), 0.4, dtype=np.float32)
        for sigma, amp in ((0.7, 0.07), (1.5, 0.07), (3.0, 0.06), (8.0, 0.05), (24.0, 0.06), (64.0, 0.05)):
            g = g + amp * _smooth_noise(rng, (size, size), sigma)
        pebbles = _smooth_noise(rng, (size, size), 2.0)
        g = np.where(pebbles > 1.6, 0.85, np.where(pebbles < -1.8, 0.08, g))
    return np.clip(np.asarray(g, dtype=np.float32), 0.02, 1.0)


def _boxes(model: RackModel, cfg: FieldSceneConfig, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Axis-aligned beams (rack frame): (B, 3) minimum and maximum corners."""
    arr = model.pipe_arrays()
    x0 = float(np.min(arr.starts[:, 0] - arr.radii)) - 0.4
    x1 = float(np.max(arr.starts[:, 0] + arr.radii)) + 0.4
    length = float(np.max(arr.lengths[: model.num_parallel]))
    lo: list[list[float]] = []
    hi: list[list[float]] = []
    if cfg.beam_spacing_m > 0:
        for y in np.arange(float(rng.uniform(0.3, cfg.beam_spacing_m)), length, cfg.beam_spacing_m):
            lo.append([x0, y - 0.1, -0.3])  # an I-beam's top flange seen from above: 20 cm wide
            hi.append([x1, y + 0.1, 0.0])
    for y in cfg.overhead_beams_y_m:
        lo.append([x0, y - 0.07, cfg.overhead_beam_z_m - 0.15])
        hi.append([x1, y + 0.07, cfg.overhead_beam_z_m])
    return np.array(lo, dtype=np.float64).reshape(-1, 3), np.array(hi, dtype=np.float64).reshape(-1, 3)


def _box_hits(o: FloatArray, d: F32, lo: FloatArray, hi: FloatArray) -> tuple[F32, IntArray, IntArray]:
    """Nearest entry distance (P,) (inf: none), box id and entry axis of rays o + t d through boxes."""
    P = d.shape[0]
    t_best = np.full(P, np.inf, dtype=np.float32)
    which = np.full(P, -1, dtype=np.intp)
    axis = np.zeros(P, dtype=np.intp)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = [np.float32(1.0) / np.ascontiguousarray(d[:, a]) for a in range(3)]
        for b in range(lo.shape[0]):
            t_in = np.full(P, -np.inf, dtype=np.float32)
            t_out = np.full(P, np.inf, dtype=np.float32)
            ax = np.zeros(P, dtype=np.intp)
            for a in range(3):  # slab method, one 1-D pass per axis (fmin/fmax skip 0 * inf)
                t1 = np.float32(lo[b, a] - o[a]) * inv[a]
                t2 = np.float32(hi[b, a] - o[a]) * inv[a]
                near = np.fmin(t1, t2)
                ax = np.where(near > t_in, a, ax)
                t_in = np.fmax(t_in, near)
                t_out = np.fmin(t_out, np.fmax(t1, t2))
            hit = (t_in <= t_out) & (t_in > 0) & (t_in < t_best)
            t_best = np.where(hit, t_in, t_best)
            which = np.where(hit, b, which)
            axis = np.where(hit, ax, axis)
    return t_best, which, axis
