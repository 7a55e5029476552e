"""Pinhole camera with OpenCV lens distortion, vectorized over points.

Intrinsics follow Lippiello & Cacace: K = [[f, s, u0], [0, r f, v0], [0, 0, 1]]
with fx = f, fy = r f, skew s, principal point (cx, cy) = (u0, v0). Distortion is
OpenCV's model: (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4]]]).
Pixel coordinates follow OpenCV: integer coordinates are pixel centres.
Points are in the `cam` frame (OpenCV optical: x right, y down, z forward), metres.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.camera_jit import kernels as jit_kernels
from companion.checks import FloatArray, as_float_array, check_last_dim
from companion.errors import CameraError, InputError

_VALID_DIST_LENGTHS = (0, 4, 5, 8, 12)
# Points closer than this to the z = 0 plane of the camera cannot be projected.
_MIN_DEPTH_M = 1e-9


def _pad_distortion(dist: FloatArray) -> FloatArray:
    """Distortion coefficients padded to the 12-term OpenCV model."""
    out = np.zeros(12)
    out[: dist.size] = dist
    return out


def _cv_error_detail(exc: BaseException | None) -> str:
    """The useful tail of an OpenCV error ("(3): Incorrect indentation"), one line."""
    msg = " ".join(str(getattr(exc, "msg", "") or exc or "").split())
    if "in function" in msg:
        msg = msg.split("in function", 1)[1].strip(" '")
    return msg or "syntax error"


def _number_node(node: Any) -> float | None:
    """A FileNode's number, or None when it is missing or not a number."""
    return float(node.real()) if node.isInt() or node.isReal() else None


def _matrix_node(node: Any, path: Path, key: str) -> FloatArray | None:
    """A matrix FileNode as float64: an !!opencv-matrix, or a ROS ``{rows, cols, data}`` map.

    None when the key is absent; `CameraError` naming `key` when it is there but unreadable.
    """
    if node.empty() or node.isNone():
        return None
    if node.isMap() and node.getNode("data").isSeq() and not node.getNode("dt").isString():
        data = node.getNode("data")
        values = [_number_node(data.at(i)) for i in range(data.size())]
        rows, cols = _number_node(node.getNode("rows")), _number_node(node.getNode("cols"))
        if any(v is None for v in values) or rows is None or cols is None or rows * cols != len(values):
            raise CameraError(f"{path}: {key}: data must hold rows x cols numbers")
        return np.array(values, dtype=np.float64).reshape(int(rows), int(cols))
    if node.isSeq():  # a plain list of numbers (distortion written by hand)
        values = [_number_node(node.at(i)) for i in range(node.size())]
        if any(v is None for v in values):
            raise CameraError(f"{path}: {key}: must be numbers")
        return np.array(values, dtype=np.float64)
    mat = node.mat()
    if mat is None:
        raise CameraError(f"{path}: {key}: not a matrix (!!opencv-matrix or rows/cols/data)")
    return np.asarray(mat, dtype=np.float64)


@dataclass(frozen=True)
class PinholeCamera:
    """A calibrated camera: image size (px), intrinsics (px) and OpenCV distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    dist: tuple[float, ...] | None = None
    _d: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if int(self.width) != self.width or int(self.height) != self.height:
            raise InputError("width/height: must be whole numbers of pixels")
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"width/height: must be positive, got {self.width}x{self.height}")
        for name in ("fx", "fy", "cx", "cy", "skew"):
            value = getattr(self, name)
            if not np.isfinite(value):
                raise InputError(f"{name}: must be finite, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(f"fx/fy: focal lengths must be positive, got {self.fx}, {self.fy}")
        d = np.zeros(0) if self.dist is None else as_float_array(self.dist, "dist").ravel()
        if d.size not in _VALID_DIST_LENGTHS:
            raise InputError(f"dist: expected 0, 4, 5, 8 or 12 coefficients, got {d.size}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "dist", None if d.size == 0 or not np.any(d) else tuple(float(x) for x in d))
        object.__setattr__(self, "_d", _pad_distortion(d))

    # ------------------------------------------------------------------ matrices
    @property
    def K(self) -> FloatArray:
        """The 3x3 camera matrix."""
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> FloatArray:
        """Distortion coefficients as given (possibly empty), for OpenCV calls."""
        return np.zeros(0) if self.dist is None else np.asarray(self.dist, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return self.dist is not None

    # ------------------------------------------------------------------ distortion
    def _distort(self, xn: FloatArray, with_jacobian: bool) -> tuple[FloatArray, FloatArray | None]:
        """Distorted normalized coordinates (N, 2) and d(xd)/d(xn) (N, 2, 2)."""
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = self._d
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        num = 1.0 + k1 * r2 + k2 * r4 + k3 * r6
        den = 1.0 + k4 * r2 + k5 * r4 + k6 * r6
        radial = num / den
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4
        out = np.stack([xd, yd], axis=-1)
        if not with_jacobian:
            return out, None
        dnum = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4  # d num / d r2
        dden = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4
        drad = (dnum * den - num * dden) / (den * den)  # d radial / d r2
        # d r2 / dx = 2x, d r2 / dy = 2y
        J = np.empty((xn.shape[0], 2, 2))
        J[:, 0, 0] = radial + x * drad * 2 * x + 2 * p1 * y + p2 * 6 * x + (s1 + 2 * s2 * r2) * 2 * x
        J[:, 0, 1] = x * drad * 2 * y + 2 * p1 * x + p2 * 2 * y + (s1 + 2 * s2 * r2) * 2 * y
        J[:, 1, 0] = y * drad * 2 * x + p1 * 2 * x + 2 * p2 * y + (s3 + 2 * s4 * r2) * 2 * x
        J[:, 1, 1] = radial + y * drad * 2 * y + p1 * 6 * y + 2 * p2 * x + (s3 + 2 * s4 * r2) * 2 * y
        return out, J

    def _undistort(self, xd: FloatArray, iterations: int = 20) -> FloatArray:
        """Normalized undistorted coordinates of distorted ones (N, 2), by Newton's method."""
        xn = xd.copy()
        for _ in range(iterations):
            f, J = self._distort(xn, with_jacobian=True)
            assert J is not None
            r = f - xd
            if np.abs(r).max(initial=0.0) < 1e-15:
                break
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
            dy = (-J[:, 1, 0] * r[:, 0] + J[:, 0, 0] * r[:, 1]) / det
            xn = xn - np.stack([dx, dy], axis=-1)
        return xn

    # ------------------------------------------------------------------ projection
    def project(self, p_cam: Any) -> FloatArray:
        """Pixels (N, 2) of points (N, 3) or (3,) in `cam`; NaN for points with z <= 0."""
        uv, _ = self._project(p_cam, with_jacobian=False)
        return uv

    def project_with_jacobian(self, p_cam: Any) -> tuple[FloatArray, FloatArray]:
        """Pixels (N, 2) and Jacobians d(u, v)/d(p_cam) (N, 2, 3); NaN where z <= 0."""
        uv, J = self._project(p_cam, with_jacobian=True)
        assert J is not None
        return uv, J

    def _project(self, p_cam: Any, with_jacobian: bool) -> tuple[FloatArray, FloatArray | None]:
        p = check_last_dim(p_cam, 3, "p_cam")
        single = p.ndim == 1
        p = p.reshape(-1, 3)
        ks = jit_kernels() if self.dist is None else None
        if ks is not None:
            # The same arithmetic in one compiled call (`camera_jit.py`).
            uv_k, J_k = ks.pinhole(np.ascontiguousarray(p), self.fx, self.fy, self.skew, self.cx, self.cy,
                                   _MIN_DEPTH_M, with_jacobian)
            J_out: FloatArray | None = J_k if with_jacobian else None
            if single:
                return uv_k[0], (None if J_out is None else J_out[0])
            return uv_k, J_out
        z = p[:, 2]
        front = z > _MIN_DEPTH_M
        all_front = bool(front.all())  # the usual case: skip the masking (trackers call this per iteration)
        zs = z if all_front else np.where(front, z, 1.0)
        xn = p[:, :2] / zs[:, None]
        if self.dist is None:
            xd, Jd = xn, None
        else:
            xd, Jd = self._distort(xn, with_jacobian)
        fx, fy, sk = self.fx, self.fy, self.skew
        uv = np.empty_like(xd)
        uv[:, 0] = fx * xd[:, 0] + sk * xd[:, 1] + self.cx
        uv[:, 1] = fy * xd[:, 1] + self.cy
        if not all_front:
            uv[~front] = np.nan
        J: FloatArray | None = None
        if with_jacobian:
            # d xn / d p = [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]; J = K_2x2 (Jd) d xn / d p, written out.
            inv_z = 1.0 / zs
            j02 = -xn[:, 0] / zs
            j12 = -xn[:, 1] / zs
            if Jd is None:
                J = np.empty((p.shape[0], 2, 3))
                J[:, 0, 0] = fx * inv_z
                J[:, 0, 1] = sk * inv_z
                J[:, 0, 2] = fx * j02 + sk * j12
                J[:, 1, 0] = 0.0
                J[:, 1, 1] = fy * inv_z
                J[:, 1, 2] = fy * j12
            else:
                Jn = np.zeros((p.shape[0], 2, 3))
                Jn[:, 0, 0] = inv_z
                Jn[:, 1, 1] = inv_z
                Jn[:, 0, 2] = j02
                Jn[:, 1, 2] = j12
                Kp = np.array([[fx, sk], [0.0, fy]])
                J = np.einsum("ij,njk->nik", Kp, Jd @ Jn)
            if not all_front:
                J[~front] = np.nan
        if single:
            return uv[0], (None if J is None else J[0])
        return uv, J

    def unproject(self, uv: Any) -> FloatArray:
        """Unit rays (N, 3) in `cam` (z > 0) through pixels (N, 2) or (2,), undistorting."""
        q = check_last_dim(uv, 2, "uv")
        single = q.ndim == 1
        q = q.reshape(-1, 2)
        yd = (q[:, 1] - self.cy) / self.fy
        xd = (q[:, 0] - self.cx - self.skew * yd) / self.fx
        xn = np.stack([xd, yd], axis=-1)
        if self.dist is not None:
            xn = self._undistort(xn)
        rays = np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=-1)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        return rays[0] if single else rays

    def normalized(self, uv: Any) -> FloatArray:
        """Undistorted normalized coordinates (x/z, y/z) (N, 2) of pixels (N, 2)."""
        rays = self.unproject(uv)
        return rays[..., :2] / rays[..., 2:3]

    def in_image(self, uv: Any, margin_px: float = 0.0) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """True where pixels (N, 2) lie inside the image, `margin_px` away from its border."""
        q = np.asarray(uv, dtype=np.float64)
        if q.shape[-1:] != (2,):
            raise InputError(f"uv: expected shape (..., 2), got {q.shape}")
        u, v = q[..., 0], q[..., 1]
        lo = -0.5 + margin_px
        with np.errstate(invalid="ignore"):
            return (u >= lo) & (v >= lo) & (u <= self.width - 0.5 - margin_px) & (v <= self.height - 0.5 - margin_px)

    def scaled(self, factor: float) -> PinholeCamera:
        """The same camera at `factor` times the resolution (image pyramid level)."""
        s = float(factor)
        return PinholeCamera(
            width=max(1, round(self.width * s)),
            height=max(1, round(self.height * s)),
            fx=self.fx * s,
            fy=self.fy * s,
            cx=(self.cx + 0.5) * s - 0.5,
            cy=(self.cy + 0.5) * s - 0.5,
            skew=self.skew * s,
            dist=self.dist,
        )

    # ------------------------------------------------------------------ files
    @classmethod
    def from_yaml(cls, path: str | os.PathLike[str]) -> PinholeCamera:
        """Load a calibration file: OpenCV FileStorage YAML/XML or ROS `camera_info` YAML.

        OpenCV: ``camera_matrix`` (3x3 !!opencv-matrix), ``distortion_coefficients``,
        ``image_width``, ``image_height`` (what `to_yaml` and OpenCV's calibration sample
        write). ROS (camera_calibration's ost.yaml): the same keys with ``rows``/``cols``/
        ``data`` maps and ``distortion_model`` plumb_bob or rational_polynomial, whose
        coefficients are OpenCV's (k1, k2, p1, p2, k3[, k4, k5, k6]). Anything else raises
        one-line `CameraError` naming the file and the key.
        """
        p = Path(path)
        if not p.is_file():
            raise CameraError(f"{p}: calibration file not found")
        try:
            raw = p.read_bytes()
        except OSError as exc:
            raise CameraError(f"{p}: cannot read ({exc.strerror or exc})") from exc
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise CameraError(f"{p}: not a calibration file (not UTF-8 text)") from None
        stripped = text.lstrip()
        if not stripped:
            raise CameraError(f"{p}: empty calibration file")
        if not stripped.startswith(("%YAML", "<?xml", "<opencv_storage")):
            # ROS and hand-written YAML have no "%YAML:1.0" directive; OpenCV's parser needs one.
            text = "%YAML:1.0\n" + text
        try:
            # cv2 reports some syntax errors as SystemError (an exception set inside the binding).
            fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        except (cv2.error, SystemError) as exc:
            cause = exc if isinstance(exc, cv2.error) else exc.__cause__
            detail = _cv_error_detail(cause)
            raise CameraError(f"{p}: not an OpenCV or ROS calibration YAML ({detail})") from None
        try:
            if not fs.isOpened():
                raise CameraError(f"{p}: cannot be opened as an OpenCV or ROS calibration YAML")
            K = _matrix_node(fs.getNode("camera_matrix"), p, "camera_matrix")
            if K is None or K.shape != (3, 3):
                raise CameraError(f"{p}: camera_matrix: required, a 3x3 matrix")
            width = _number_node(fs.getNode("image_width"))
            height = _number_node(fs.getNode("image_height"))
            if width is None or height is None or width != int(width) or height != int(height):
                raise CameraError(f"{p}: image_width and image_height: required (whole numbers of pixels)")
            model_node = fs.getNode("distortion_model")
            model = model_node.string() if model_node.isString() else ""
            if model not in ("", "plumb_bob", "rational_polynomial"):
                raise CameraError(
                    f"{p}: distortion_model: {model!r} is not supported (plumb_bob or rational_polynomial)"
                )
            d = _matrix_node(fs.getNode("distortion_coefficients"), p, "distortion_coefficients")
        finally:
            fs.release()
        if not np.all(np.isfinite(K)):
            raise CameraError(f"{p}: camera_matrix: must be finite numbers")
        if abs(K[1, 0]) > 1e-12 or abs(K[2, 0]) > 1e-12 or abs(K[2, 1]) > 1e-12 or abs(K[2, 2] - 1) > 1e-12:
            raise CameraError(f"{p}: camera_matrix must be upper triangular with K[2,2] = 1")
        try:
            return cls(
                width=int(width),
                height=int(height),
                fx=float(K[0, 0]),
                fy=float(K[1, 1]),
                cx=float(K[0, 2]),
                cy=float(K[1, 2]),
                skew=float(K[0, 1]),
                dist=None if d is None else tuple(float(x) for x in np.asarray(d).ravel()),
            )
        except InputError as exc:
            raise CameraError(f"{p}: {exc}") from exc

    def to_yaml(self, path: str | os.PathLike[str], extra: dict[str, str | int | float] | None = None) -> None:
        """Write the OpenCV calibration-file format that `from_yaml` and OpenCV read.

        `extra`: more top-level keys written after the camera (how it was calibrated, ...).
        """
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        try:
            fs.write("image_width", self.width)
            fs.write("image_height", self.height)
            fs.write("camera_matrix", self.K)
            d = self.dist_coeffs if self.dist is not None else np.zeros(5)
            fs.write("distortion_coefficients", d.reshape(1, -1))
            for key, value in (extra or {}).items():
                fs.write(key, value)
        finally:
            fs.release()
