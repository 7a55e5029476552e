"""Camera calibration from board views (pure): corners in, intrinsics, per-view errors and coverage out.

`calibrate(views, width, height)` runs OpenCV's planar calibration (Zhang) on the corners
of `companion.calibration_boards.detect_corners`, drops views that do not fit the others
(per-view RMS above `reject_factor` x the median), and returns a `CalibrationResult`: the
`PinholeCamera` (OpenCV distortion, written with `PinholeCamera.to_yaml`), the RMS
reprojection error (px), per-view errors, the standard deviation of every intrinsic, and
the `Coverage` of the image and of the board tilts.

`coverage(views, width, height)` is the operator's feedback while collecting views: which
cells of a 3x3 grid over the image have corners in them, and how many views tilt the board
left/right/up/down by more than `TILT_MIN_DEG` (board poses from a nominal camera before
calibration, from the calibrated one after). Without tilted views fx, fy and the principal
point are poorly separated from the board distance; without corners near the image corners
the distortion is extrapolated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from companion.calibration_boards import ViewCorners
from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.errors import InputError

__all__ = ["GRID_NAMES", "TILT_MIN_DEG", "CalibrationResult", "Coverage", "calibrate", "coverage", "view_tilts_deg"]

GRID_ROWS = 3
GRID_COLS = 3
GRID_NAMES = (
    ("top-left", "top", "top-right"),
    ("left", "centre", "right"),
    ("bottom-left", "bottom", "bottom-right"),
)
TILT_MIN_DEG = 15.0  # a view counts as tilted in a direction beyond this
TILT_DIRECTIONS = ("left", "right", "up", "down")
MIN_VIEWS = 4
# nominal focal length (x image width) for board poses before any calibration: a 53 deg lens
_NOMINAL_FOCAL_PER_WIDTH = 1.0


@dataclass(frozen=True)
class Coverage:
    """Where the views put corners in the image and how they tilt the board.

    cells: (3, 3) number of views with a corner in each cell of a 3x3 grid (row 0 = image top).
    tilts: views tilted by more than TILT_MIN_DEG toward each of left, right, up, down.
    """

    cells: tuple[tuple[int, int, int], ...]
    tilts: tuple[tuple[str, int], ...]

    @property
    def cells_covered(self) -> int:
        return sum(1 for row in self.cells for n in row if n > 0)

    @property
    def missing_cells(self) -> tuple[str, ...]:
        return tuple(GRID_NAMES[r][c] for r in range(GRID_ROWS) for c in range(GRID_COLS) if self.cells[r][c] == 0)

    @property
    def missing_tilts(self) -> tuple[str, ...]:
        return tuple(name for name, n in self.tilts if n == 0)

    @property
    def complete(self) -> bool:
        """Every image cell has corners and the board was tilted every way."""
        return not self.missing_cells and not self.missing_tilts

    def summary(self) -> str:
        """One line: "cells 7/9 (missing top-left, bottom-right); tilts left 2 right 0 up 1 down 3 (missing right)"."""
        cells = f"cells {self.cells_covered}/{GRID_ROWS * GRID_COLS}"
        if self.missing_cells:
            cells += f" (missing {', '.join(self.missing_cells)})"
        tilts = "tilts " + " ".join(f"{name} {n}" for name, n in self.tilts)
        if self.missing_tilts:
            tilts += f" (missing {', '.join(self.missing_tilts)})"
        return f"{cells}; {tilts}"


@dataclass(frozen=True)
class CalibrationResult:
    """A calibration: camera, errors (px), intrinsic standard deviations and coverage.

    rms_px: RMS reprojection error over all corners of the kept views.
    view_rms_px: per-view RMS (px) of the kept views, in `kept_views` order.
    kept_views, rejected_views: indices into the views passed to `calibrate`.
    std_fx_px ... : one-sigma uncertainty of fx, fy, cx, cy (px) from OpenCV's covariance.
    std_dist: one-sigma uncertainty of each distortion coefficient.
    """

    camera: PinholeCamera
    rms_px: float
    view_rms_px: tuple[float, ...]
    kept_views: tuple[int, ...]
    rejected_views: tuple[int, ...]
    std_fx_px: float
    std_fy_px: float
    std_cx_px: float
    std_cy_px: float
    std_dist: tuple[float, ...]
    coverage: Coverage


def _nominal_camera(width: int, height: int) -> PinholeCamera:
    f = _NOMINAL_FOCAL_PER_WIDTH * width
    return PinholeCamera(width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0)


def view_tilts_deg(view: ViewCorners, camera: PinholeCamera) -> tuple[float, float]:
    """Board tilt of one view (deg): (about the image y axis: + = turned right, about x: + = turned down).

    From the board pose solved with `camera` (IPPE, planar); the board normal's angle from the
    optical axis split into its horizontal and vertical parts.
    """
    ok, rvec, _tvec = cv2.solvePnP(view.object_points, view.image_points, camera.K, camera.dist_coeffs,
                                   flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return 0.0, 0.0
    R_cam_board, _ = cv2.Rodrigues(rvec)
    n_cam = R_cam_board[:, 2]  # board z (into the board) in the camera frame
    if n_cam[2] < 0:
        n_cam = -n_cam
    yaw_deg = math.degrees(math.atan2(n_cam[0], n_cam[2]))
    pitch_deg = math.degrees(math.atan2(n_cam[1], n_cam[2]))
    return yaw_deg, pitch_deg


def coverage(views: Sequence[ViewCorners], width: int, height: int, camera: PinholeCamera | None = None) -> Coverage:
    """Image-cell and tilt coverage of `views` (see module doc); `camera` None = a nominal 53 deg lens."""
    cam = camera if camera is not None else _nominal_camera(width, height)
    cells = np.zeros((GRID_ROWS, GRID_COLS), dtype=np.int64)
    tilts = dict.fromkeys(TILT_DIRECTIONS, 0)
    for view in views:
        uv = view.image_points
        col = np.clip((uv[:, 0] * GRID_COLS / width).astype(np.int64), 0, GRID_COLS - 1)
        row = np.clip((uv[:, 1] * GRID_ROWS / height).astype(np.int64), 0, GRID_ROWS - 1)
        hit = np.zeros_like(cells, dtype=bool)
        hit[row, col] = True
        cells += hit
        yaw_deg, pitch_deg = view_tilts_deg(view, cam)
        if yaw_deg > TILT_MIN_DEG:
            tilts["right"] += 1
        elif yaw_deg < -TILT_MIN_DEG:
            tilts["left"] += 1
        if pitch_deg > TILT_MIN_DEG:
            tilts["down"] += 1
        elif pitch_deg < -TILT_MIN_DEG:
            tilts["up"] += 1
    return Coverage(
        cells=tuple((int(r[0]), int(r[1]), int(r[2])) for r in cells),
        tilts=tuple((name, tilts[name]) for name in TILT_DIRECTIONS),
    )


def _run(views: Sequence[ViewCorners], width: int, height: int, flags: int) -> tuple[
    float, FloatArray, FloatArray, FloatArray, FloatArray
]:
    obj = [v.object_points.astype(np.float32) for v in views]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in views]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    K0 = np.eye(3)
    d0 = np.zeros(8 if flags & cv2.CALIB_RATIONAL_MODEL else 5)
    rms, K, dist, _rvecs, _tvecs, std_intr, _std_extr, per_view = cv2.calibrateCameraExtended(
        obj, img, (int(width), int(height)), K0, d0, flags=flags, criteria=criteria
    )
    def f64(a: object) -> FloatArray:
        return np.asarray(a, dtype=np.float64).ravel()

    return float(rms), np.asarray(K, dtype=np.float64), f64(dist), f64(std_intr), f64(per_view)


def calibrate(
    views: Sequence[ViewCorners],
    width: int,
    height: int,
    *,
    model: Literal["plumb_bob", "rational"] = "plumb_bob",
    reject_factor: float = 3.0,
) -> CalibrationResult:
    """Intrinsics and OpenCV distortion of a `width` x `height` px camera from board views.

    model: "plumb_bob" (k1, k2, p1, p2, k3) or "rational" (adds k4, k5, k6, for wide lenses).
    reject_factor: views whose RMS exceeds this x the median view RMS (and 1 px) are dropped
        once and the calibration re-run (a blurred or misdetected view); 0 keeps all.
    Raises `InputError` with fewer than MIN_VIEWS views or when OpenCV cannot solve.
    """
    if int(width) != width or int(height) != height or width <= 0 or height <= 0:
        raise InputError(f"width/height: positive whole pixels, got {width}x{height}")
    if len(views) < MIN_VIEWS:
        raise InputError(f"views: need at least {MIN_VIEWS} board views, got {len(views)}")
    flags = cv2.CALIB_RATIONAL_MODEL if model == "rational" else 0
    kept = list(range(len(views)))
    try:
        rms, K, dist, std, per_view = _run(views, width, height, flags)
        if reject_factor > 0:
            limit = max(reject_factor * float(np.median(per_view)), 1.0)
            bad = [i for i, e in zip(kept, per_view, strict=True) if e > limit]
            if bad and len(views) - len(bad) >= MIN_VIEWS:
                kept = [i for i in kept if i not in bad]
                rms, K, dist, std, per_view = _run([views[i] for i in kept], width, height, flags)
    except cv2.error as exc:
        raise InputError(f"views: OpenCV could not calibrate ({' '.join(str(exc.msg).split())})") from None
    n_dist = 8 if model == "rational" else 5
    dist = dist[:n_dist]
    camera = PinholeCamera(width=int(width), height=int(height), fx=float(K[0, 0]), fy=float(K[1, 1]),
                           cx=float(K[0, 2]), cy=float(K[1, 2]), dist=tuple(float(d) for d in dist))
    kept_views = [views[i] for i in kept]
    return CalibrationResult(
        camera=camera,
        rms_px=rms,
        view_rms_px=tuple(float(e) for e in per_view),
        kept_views=tuple(kept),
        rejected_views=tuple(i for i in range(len(views)) if i not in kept),
        std_fx_px=float(std[0]),
        std_fy_px=float(std[1]),
        std_cx_px=float(std[2]),
        std_cy_px=float(std[3]),
        std_dist=tuple(float(s) for s in std[4:4 + n_dist]),
        coverage=coverage(kept_views, int(width), int(height), camera),
    )
