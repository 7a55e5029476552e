"""Renders a downward camera's view of a textured ground plane from any body pose.

The ground is the NED plane z = 0 covered with real photographs (scikit-image's CC0 gravel,
grass and brick textures), tiled with a random dihedral flip/rotation per tile (seeded) so the
floor does not repeat with a short period. A view is the exact plane homography
texture pixels -> ground (N, E) -> image, applied with `cv2.warpPerspective`; lens distortion is
added with a remap when the camera has it. Photometric noise, blur and exposure changes are
arguments of `render`. Everything is deterministic for the scene seed and the render seed.

Pose convention (as `GroundOdometer`): body NED x, y; `height_m` = height of the camera's optical
centre above the ground; R_ned_body = Rz(yaw) Ry(pitch) Rx(roll); p_body = T_body_cam @ p_cam.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError
from companion.geometry import frames

TEXTURES = ("gravel", "grass", "brick", "mixed")

UInt8Image = np.ndarray[Any, np.dtype[np.uint8]]


def load_texture(name: str) -> UInt8Image:
    """One of scikit-image's bundled grayscale textures (512 x 512 uint8)."""
    from skimage import data

    if name not in ("gravel", "grass", "brick"):
        raise InputError(f"texture: expected one of gravel, grass, brick, got {name!r}")
    img = np.asarray(getattr(data, name)(), dtype=np.uint8)
    return img


def _dihedral(tile: UInt8Image, k: int) -> UInt8Image:
    out = np.rot90(tile, k % 4)
    return np.ascontiguousarray(out[:, ::-1] if k >= 4 else out)


def build_floor(
    textures: list[UInt8Image], rows: int, cols: int, rng: np.random.Generator, equalize: bool = True
) -> UInt8Image:
    """A (rows x cols) tiling of square textures, each tile a random texture and dihedral variant."""
    size = min(min(t.shape[0], t.shape[1]) for t in textures)
    tiles = [t[:size, :size] for t in textures]
    if equalize:
        # Same mean/contrast for every source so seams between textures are not edges.
        tiles = [
            np.clip((t.astype(np.float64) - t.mean()) / max(t.std(), 1.0) * 40.0 + 120.0, 0, 255).astype(np.uint8)
            for t in tiles
        ]
    floor = np.empty((rows * size, cols * size), dtype=np.uint8)
    which = rng.integers(0, len(tiles), size=(rows, cols))
    variant = rng.integers(0, 8, size=(rows, cols))
    for r in range(rows):
        for c in range(cols):
            floor[r * size : (r + 1) * size, c * size : (c + 1) * size] = _dihedral(
                tiles[which[r, c]], int(variant[r, c])
            )
    return floor


@dataclass(frozen=True)
class GroundScene:
    """A textured ground plane z = 0 in NED and a camera mount to view it with.

    texture:            "gravel", "grass", "brick" or "mixed" (random per tile), or a (H, W)
                        uint8 array used as the tile.
    metres_per_pixel:   ground size of one texture pixel, metres.
    north_range_m / east_range_m: the textured area (outside it the ground is black).
    seed:               seed of the tiling.
    """

    cam: PinholeCamera
    texture: str | UInt8Image = "gravel"
    metres_per_pixel: float = 0.0025
    north_range_m: tuple[float, float] = (-6.0, 6.0)
    east_range_m: tuple[float, float] = (-6.0, 6.0)
    T_body_cam: FloatArray | None = None
    seed: int = 0
    _floor: UInt8Image = field(init=False, repr=False, compare=False)
    _T_body_cam: FloatArray = field(init=False, repr=False, compare=False)
    _undistort_map: tuple[Any, Any] | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.metres_per_pixel > 0:
            raise InputError(f"metres_per_pixel: must be positive, got {self.metres_per_pixel}")
        n0, n1 = self.north_range_m
        e0, e1 = self.east_range_m
        if not (n1 > n0 and e1 > e0):
            raise InputError("north_range_m / east_range_m: must be increasing (min, max) pairs")
        if isinstance(self.texture, str):
            names = ["gravel", "grass", "brick"] if self.texture == "mixed" else [self.texture]
            if self.texture not in TEXTURES:
                raise InputError(f"texture: expected one of {TEXTURES}, got {self.texture!r}")
            sources = [load_texture(n) for n in names]
        else:
            arr = np.asarray(self.texture)
            if arr.ndim != 2 or arr.dtype != np.uint8 or min(arr.shape) < 16:
                raise InputError(f"texture: expected a (H, W) uint8 array, got {arr.shape} {arr.dtype}")
            sources = [arr]
        size = min(min(t.shape) for t in sources)
        rows = int(np.ceil((n1 - n0) / self.metres_per_pixel / size))
        cols = int(np.ceil((e1 - e0) / self.metres_per_pixel / size))
        floor = build_floor(sources, rows, cols, np.random.default_rng(self.seed))
        T = frames.default_T_body_cam() if self.T_body_cam is None else check_transform(self.T_body_cam, "T_body_cam")
        object.__setattr__(self, "_floor", floor)
        object.__setattr__(self, "_T_body_cam", np.array(T, dtype=np.float64))
        object.__setattr__(self, "_undistort_map", self._make_distortion_map() if self.cam.has_distortion else None)

    @property
    def floor(self) -> UInt8Image:
        """The texture image covering the ground (row = north, column = east)."""
        return self._floor

    def texture_to_ned(self) -> FloatArray:
        """3x3 affine map from texture pixels (u = column, v = row, 1) to ground (north, east, 1)."""
        m = self.metres_per_pixel
        return np.array([[0.0, m, self.north_range_m[0]], [m, 0.0, self.east_range_m[0]], [0.0, 0.0, 1.0]])

    def T_ned_cam(
        self, x_m: float, y_m: float, height_m: float, roll_rad: float, pitch_rad: float, yaw_rad: float
    ) -> FloatArray:
        """The camera pose in NED for a body pose (ground at z = 0, camera centre at z = -height)."""
        R_ned_body = frames.rotation_from_euler_zyx(roll_rad, pitch_rad, yaw_rad)
        lever = R_ned_body @ self._T_body_cam[:3, 3]
        T = np.eye(4)
        T[:3, :3] = R_ned_body @ self._T_body_cam[:3, :3]
        T[:3, 3] = [x_m + lever[0], y_m + lever[1], -height_m]
        return T

    def homography(
        self, x_m: float, y_m: float, height_m: float, roll_rad: float, pitch_rad: float, yaw_rad: float
    ) -> FloatArray:
        """3x3 homography from ground (north, east, 1) to (undistorted) image pixels."""
        T = self.T_ned_cam(x_m, y_m, height_m, roll_rad, pitch_rad, yaw_rad)
        R_cam_ned = T[:3, :3].T
        t = -R_cam_ned @ T[:3, 3]
        G = np.column_stack([R_cam_ned[:, 0], R_cam_ned[:, 1], t])
        H: FloatArray = self.cam.K @ G
        return H

    def _make_distortion_map(self) -> tuple[Any, Any]:
        cam = self.cam
        u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
        uv = np.stack([u.ravel(), v.ravel()], axis=-1)
        xn = cam.normalized(uv)
        pin = xn @ cam.K[:2, :2].T + cam.K[:2, 2]
        map_x = pin[:, 0].reshape(cam.height, cam.width).astype(np.float32)
        map_y = pin[:, 1].reshape(cam.height, cam.width).astype(np.float32)
        return map_x, map_y

    def render(
        self,
        x_m: float,
        y_m: float,
        height_m: float,
        roll_rad: float = 0.0,
        pitch_rad: float = 0.0,
        yaw_rad: float = 0.0,
        *,
        noise_std: float = 0.0,
        blur_sigma_px: float = 0.0,
        gain: float = 1.0,
        offset: float = 0.0,
        seed: int | None = None,
    ) -> UInt8Image:
        """The (H, W) uint8 grayscale image seen from the body pose.

        `gain`, `offset`: exposure change applied as gain * I + offset (intensity levels).
        `blur_sigma_px`: Gaussian blur (defocus / motion) standard deviation, pixels.
        `noise_std`: additive Gaussian noise, intensity levels, drawn from `seed`.
        """
        if not height_m > 0:
            raise InputError(f"height_m: must be positive, got {height_m}")
        cam = self.cam
        H = self.homography(x_m, y_m, height_m, roll_rad, pitch_rad, yaw_rad) @ self.texture_to_ned()
        img = cv2.warpPerspective(
            self._floor, H, (cam.width, cam.height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )
        if self._undistort_map is not None:
            img = cv2.remap(img, self._undistort_map[0], self._undistort_map[1], cv2.INTER_LINEAR)
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
        if noise_std > 0 or gain != 1.0 or offset != 0.0:
            out = img.astype(np.float32) * np.float32(gain) + np.float32(offset)
            if noise_std > 0:
                rng = np.random.default_rng(seed)
                out += rng.standard_normal(out.shape, dtype=np.float32) * np.float32(noise_std)
            img = np.clip(np.rint(out), 0, 255).astype(np.uint8)
        return np.ascontiguousarray(img)


@dataclass(frozen=True)
class GroundTrajectory:
    """Sampled body poses over a ground plane (all arrays (N,)): NED x, y (m), camera height above
    the ground (m), roll, pitch, yaw (rad, R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)), stamps (s)."""

    name: str
    stamp_s: FloatArray
    x_m: FloatArray
    y_m: FloatArray
    height_m: FloatArray
    roll_rad: FloatArray
    pitch_rad: FloatArray
    yaw_rad: FloatArray

    def __len__(self) -> int:
        return int(self.stamp_s.size)


def _smooth_noise(n: int, rate_hz: float, corner_hz: float, std: float, rng: np.random.Generator) -> FloatArray:
    """Low-pass Gaussian noise (N,) with standard deviation `std` and bandwidth ~`corner_hz`."""
    from scipy.signal import lfilter

    pad = int(4 * rate_hz / corner_hz)
    alpha = 1.0 - np.exp(-2.0 * np.pi * corner_hz / rate_hz)
    out = rng.standard_normal(n + pad)
    for _ in range(3):  # third-order low-pass: smooth up to the acceleration
        out = lfilter([alpha], [1.0, alpha - 1.0], out)
    out = out[pad:]
    s = out.std()
    return np.asarray(out / s * std if s > 0 else out, dtype=np.float64)


def _attitude_from_acceleration(acc_ned: FloatArray, yaw_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Roll and pitch of a multirotor whose thrust (-z body) produces `acc_ned` (N, 3) at `yaw`."""
    g = np.array([0.0, 0.0, 9.81])
    v = g[None, :] - acc_ned
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    # v_yawfree = Rz(-yaw) v = (cos r sin p, -sin r, cos r cos p)
    vx = c * v[:, 0] + s * v[:, 1]
    vy = -s * v[:, 0] + c * v[:, 1]
    roll = np.arcsin(np.clip(-vy, -1.0, 1.0))
    pitch = np.arctan2(vx, v[:, 2])
    return roll, pitch


def loop_trajectory(
    loops: int,
    rate_hz: float = 20.0,
    seconds_per_loop: float = 30.0,
    size_m: tuple[float, float] = (5.6, 2.8),
    height_range_m: tuple[float, float] = (1.0, 1.5),
    yaw_amplitude_rad: float = 0.6,
    tilt_jitter_rad: float = 0.01,
    hover_s: float = 2.0,
    seed: int = 0,
) -> GroundTrajectory:
    """sFly-like flight: `loops` laps of an elliptic loop of `size_m` (north x east extent), or
    hovering when `loops` is 0, at 1-1.5 m; roll/pitch follow the accelerations like a multirotor,
    plus smooth jitter (turbulence); yaw swings by `yaw_amplitude_rad`."""
    rng = np.random.default_rng(seed)
    a_n, a_e = 0.5 * size_m[0], 0.5 * size_m[1]
    h0, h1 = height_range_m
    if loops > 0:
        move_s = loops * seconds_per_loop
        total_s = move_s + 2 * hover_s
        t = np.arange(round(total_s * rate_hz)) / rate_hz
        u = np.clip((t - hover_s) / move_s, 0.0, 1.0)
        # Smooth 0 -> 1 progress (zero speed and acceleration at both ends).
        s = u**3 * (10.0 - 15.0 * u + 6.0 * u * u)
        phi = 2.0 * np.pi * loops * s
        x = a_n * np.sin(phi)
        y = a_e * (1.0 - np.cos(phi))
        yaw = yaw_amplitude_rad * np.sin(0.5 * phi) + _smooth_noise(t.size, rate_hz, 0.1, 0.05, rng)
        height = 0.5 * (h0 + h1) + 0.5 * (h1 - h0) * np.sin(phi + 0.7) * np.sin(np.pi * s)
    else:
        total_s = seconds_per_loop
        t = np.arange(round(total_s * rate_hz)) / rate_hz
        x = _smooth_noise(t.size, rate_hz, 0.15, 0.08, rng)
        y = _smooth_noise(t.size, rate_hz, 0.15, 0.08, rng)
        yaw = _smooth_noise(t.size, rate_hz, 0.1, 0.05, rng)
        height = 0.5 * (h0 + h1) + _smooth_noise(t.size, rate_hz, 0.1, 0.05, rng)
    dt = 1.0 / rate_hz
    pos = np.stack([x, y, -height], axis=1)
    acc = np.gradient(np.gradient(pos, dt, axis=0), dt, axis=0)
    roll, pitch = _attitude_from_acceleration(acc, yaw)
    roll = roll + _smooth_noise(t.size, rate_hz, 1.0, tilt_jitter_rad, rng)
    pitch = pitch + _smooth_noise(t.size, rate_hz, 1.0, tilt_jitter_rad, rng)
    name = f"{loops}loop" if loops > 0 else "hover"
    return GroundTrajectory(name, t, x, y, height, roll, pitch, yaw)
