"""Calibration targets and their corner detection: OpenCV checkerboards and ChArUco boards (pure).

A `BoardSpec` describes the printed target; `detect_corners(image, board)` returns the
`ViewCorners` found in one grayscale or BGR image (pixels in, arrays out; no files, no
clock), or None when the board is not (fully, for a checkerboard) in view. The board frame
`board`: x along the columns, y along the rows, z into the board (OpenCV's convention),
metres; the first inner corner is the origin.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError

__all__ = ["BoardSpec", "ViewCorners", "detect_corners"]

# ChArUco views with fewer interpolated corners than this constrain the intrinsics too little.
_MIN_CHARUCO_CORNERS = 6
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)


@dataclass(frozen=True)
class BoardSpec:
    """A calibration target.

    kind: "checkerboard" (cols x rows INNER corners) or "charuco" (cols x rows SQUARES, ArUco
        markers of `marker_m` in the white squares, from the OpenCV dictionary `dictionary`).
    square_m: side of one square (m); it sets the scale of the board poses only, not the intrinsics.
    """

    kind: Literal["checkerboard", "charuco"]
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_5X5_100"
    _charuco: Any = field(init=False, repr=False, compare=False, default=None)

    def __post_init__(self) -> None:
        if self.kind not in ("checkerboard", "charuco"):
            raise InputError(f'board.kind: "checkerboard" or "charuco", got {self.kind!r}')
        low = 3
        if int(self.cols) != self.cols or int(self.rows) != self.rows or min(self.cols, self.rows) < low:
            raise InputError(f"board.cols/rows: whole numbers >= {low}, got {self.cols}x{self.rows}")
        if not (np.isfinite(self.square_m) and self.square_m > 0):
            raise InputError(f"board.square_m: must be > 0, got {self.square_m}")
        if self.kind == "charuco":
            if not (0 < self.marker_m < self.square_m):
                raise InputError(f"board.marker_m: must be in (0, square_m), got {self.marker_m}")
            code = getattr(cv2.aruco, self.dictionary, None)
            if not self.dictionary.startswith("DICT_") or not isinstance(code, int):
                raise InputError(f"board.dictionary: not an OpenCV ArUco dictionary: {self.dictionary!r}")
            dictionary = cv2.aruco.getPredefinedDictionary(code)
            board = cv2.aruco.CharucoBoard((int(self.cols), int(self.rows)), float(self.square_m),
                                           float(self.marker_m), dictionary)
            object.__setattr__(self, "_charuco", board)

    @property
    def corner_count(self) -> int:
        """Corners of the whole board (inner corners)."""
        if self.kind == "checkerboard":
            return int(self.cols * self.rows)
        return int((self.cols - 1) * (self.rows - 1))

    def object_points(self) -> FloatArray:
        """All inner corners (corner_count, 3) in the board frame (m), in detection id order."""
        if self.kind == "charuco":
            return np.asarray(self._charuco.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        xy = np.stack([i.ravel(), j.ravel()], axis=-1) * self.square_m
        return np.concatenate([xy, np.zeros((xy.shape[0], 1))], axis=-1)

    def image(self, px_per_square: int, margin_squares: float = 1.0) -> np.ndarray[Any, np.dtype[np.uint8]]:
        """The board as a printable uint8 image, `px_per_square` px per square, with a white margin.

        Checkerboard: (cols + 1) x (rows + 1) squares, black at the top-left. Returns the image;
        the first inner corner is at pixel (margin + 1) * px_per_square (- 0.5, pixel centres)."""
        s = int(px_per_square)
        m = round(margin_squares * s)
        if self.kind == "charuco":
            size = (self.cols * s + 2 * m, self.rows * s + 2 * m)
            return np.asarray(self._charuco.generateImage(size, marginSize=m, borderBits=1), dtype=np.uint8)
        nx, ny = self.cols + 1, self.rows + 1
        i, j = np.meshgrid(np.arange(nx * s) // s, np.arange(ny * s) // s)
        squares = np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8)
        return np.pad(squares, m, constant_values=255)


@dataclass(frozen=True)
class ViewCorners:
    """The board corners found in one image: pixels (N, 2) and board-frame points (N, 3, m), row-aligned."""

    image_points: FloatArray
    object_points: FloatArray

    def __post_init__(self) -> None:
        uv = np.asarray(self.image_points, dtype=np.float64).reshape(-1, 2)
        xyz = np.asarray(self.object_points, dtype=np.float64).reshape(-1, 3)
        if uv.shape[0] != xyz.shape[0] or uv.shape[0] < 4:
            raise InputError(f"corners: need >= 4 matching image/object points, got {uv.shape[0]}/{xyz.shape[0]}")
        object.__setattr__(self, "image_points", uv)
        object.__setattr__(self, "object_points", xyz)

    def __len__(self) -> int:
        return int(self.image_points.shape[0])


def _gray(image: Any) -> np.ndarray[Any, np.dtype[np.uint8]]:
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        raise InputError(f"image: expected uint8 pixels, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 3:
        return np.asarray(cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY))
    if arr.ndim != 2:
        raise InputError(f"image: expected (H, W) or (H, W, 3), got shape {arr.shape}")
    return arr


def detect_corners(image: Any, board: BoardSpec) -> ViewCorners | None:
    """Board corners in `image` (uint8 gray or BGR), refined to subpixel; None if not found.

    Checkerboard: every inner corner must be found; ChArUco: any view with at least 6
    interpolated corners.
    """
    gray = _gray(image)
    if board.kind == "checkerboard":
        pattern = (int(board.cols), int(board.rows))
        # the classic detector + cornerSubPix is the more accurate (0.03-0.06 px on rendered views,
        # the sector-based one 0.1-0.4 px); the sector-based one finds boards it misses (blur, glare)
        found, corners = cv2.findChessboardCorners(
            gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        )
        if found:
            corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), _SUBPIX_CRITERIA)
        else:
            found, corners = cv2.findChessboardCornersSB(
                gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            )
            if not found:
                return None
        # a symmetric board may be found in reverse order in some views: that is the same board
        # after an in-plane rotation, which changes the view's pose, not the intrinsics
        return ViewCorners(np.asarray(corners, dtype=np.float64).reshape(-1, 2), board.object_points())
    detector = cv2.aruco.CharucoDetector(board._charuco)
    corners, ids, _marker_corners, _marker_ids = detector.detectBoard(gray)
    if ids is None or len(ids) < _MIN_CHARUCO_CORNERS:
        return None
    ids = np.asarray(ids).ravel()
    return ViewCorners(np.asarray(corners, dtype=np.float64).reshape(-1, 2), board.object_points()[ids])
