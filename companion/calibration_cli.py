"""`companion calibrate`: collect board views from a folder, a video or the live camera, calibrate, write the YAML.

The I/O side of `companion.calibration` (the math) and `companion.calibration_boards`
(detection): images come from a folder (every image is a view), or from a video file or the
configured camera through `drivers.camera` (a frame becomes a view when its board position,
size or tilt differs from every view kept so far). Progress (one line per view, with the
coverage still missing) goes to stderr; the result (intrinsics, RMS, coverage) to stdout;
the calibration is written as OpenCV YAML that `PinholeCamera.from_yaml` and
``camera.calibration`` read.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np

from companion.calibration import CalibrationResult, calibrate, coverage, view_tilts_deg
from companion.calibration_boards import BoardSpec, ViewCorners, detect_corners
from companion.camera import PinholeCamera
from companion.errors import CompanionError, InputError

__all__ = ["run_calibrate_cli"]

# A frame of a video or the live camera is a new view when its board signature (centre, size,
# tilt; see `_signature`) is at least this far from every kept view's.
_NOVELTY = 0.08
_FRAME_TIMEOUT_S = 5.0  # a source silent this long has ended (video) or is not delivering (camera)


@dataclass
class _Collector:
    """Views kept so far and the one-line progress they give."""

    board: BoardSpec
    out: TextIO
    views: list[ViewCorners]
    names: list[str]
    size: tuple[int, int] | None = None
    signatures: list[np.ndarray[Any, np.dtype[np.float64]]] | None = None

    def _check_size(self, image: np.ndarray[Any, Any], name: str) -> tuple[int, int]:
        size = (int(image.shape[1]), int(image.shape[0]))
        if self.size is None:
            self.size = size
        elif size != self.size:
            raise InputError(f"{name}: image is {size[0]}x{size[1]}, the first one was {self.size[0]}x{self.size[1]}")
        return size

    def _signature(self, view: ViewCorners, size: tuple[int, int]) -> np.ndarray[Any, np.dtype[np.float64]]:
        w, h = size
        uv = view.image_points
        span = (uv.max(axis=0) - uv.min(axis=0)) / np.array([w, h])
        nominal = PinholeCamera(w, h, float(w), float(w), (w - 1) / 2.0, (h - 1) / 2.0)
        yaw_deg, pitch_deg = view_tilts_deg(view, nominal)
        return np.array([uv[:, 0].mean() / w, uv[:, 1].mean() / h, math.sqrt(span[0] * span[1]),
                         yaw_deg / 60.0, pitch_deg / 60.0])

    def offer(self, image: np.ndarray[Any, Any], name: str, every: bool) -> bool:
        """Detect the board in `image`; keep it (every=True: always, else when novel). True if kept."""
        size = self._check_size(image, name)
        view = detect_corners(image, self.board)
        if view is None:
            if every:
                print(f"{name}: no board found", file=self.out, flush=True)
            return False
        if not every:
            sig = self._signature(view, size)
            sigs = self.signatures if self.signatures is not None else []
            if sigs and min(float(np.linalg.norm(sig - s)) for s in sigs) < _NOVELTY:
                return False
            self.signatures = [*sigs, sig]
        self.views.append(view)
        self.names.append(name)
        cov = coverage(self.views, *size)
        print(f"view {len(self.views)} ({name}): {len(view)} corners; {cov.summary()}", file=self.out, flush=True)
        return True


def _board(args: argparse.Namespace) -> BoardSpec:
    marker_m = args.marker_m if args.marker_m > 0 else 0.75 * args.square_m
    return BoardSpec(args.board, args.cols, args.rows, args.square_m,
                     marker_m=marker_m if args.board == "charuco" else 0.0, dictionary=args.dictionary)


def _from_folder(folder: Path, pattern: str, collector: _Collector) -> None:
    from drivers.camera.folder import list_images

    if not folder.is_dir():
        raise InputError(f"--images: {folder}: no such folder")
    files = [f for f in list_images(folder) if f.match(pattern)]
    if not files:
        raise InputError(f"--images: {folder}: no images matching {pattern!r}")
    for path in files:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise InputError(f"{path}: cannot read image")
        collector.offer(image, path.name, every=True)


async def _from_source(config: Any, collector: _Collector, views: int, max_seconds: float, step: int) -> None:
    """Frames of a `drivers.camera` source until `views` views, the end of a video, or `max_seconds`."""
    from companion.clock import SystemClock
    from drivers.camera import open_camera

    clock = SystemClock()
    loop = asyncio.get_running_loop()
    deadline = clock.now() + max_seconds
    seen = 0
    async with open_camera(config, clock) as camera:
        async for frame in camera.frames(timeout_s=_FRAME_TIMEOUT_S):
            seen += 1
            if frame.seq % max(1, step):
                continue
            name = f"frame {frame.seq}"
            # detection takes tens of ms: keep it off the event loop that feeds the capture thread
            await loop.run_in_executor(None, collector.offer, np.asarray(frame.image), name, False)
            if len(collector.views) >= views or clock.now() > deadline:
                break
    if seen == 0:
        where = config.device if config.kind == "v4l2" else config.path
        raise CompanionError(f"camera: no frame from {config.kind} {where} within {_FRAME_TIMEOUT_S:g} s")


def _write_yaml(path: Path, result: CalibrationResult, board: BoardSpec, names: list[str]) -> None:
    n_dist = len(result.camera.dist_coeffs)
    result.camera.to_yaml(path, extra={
        "distortion_model": "rational_polynomial" if n_dist == 8 else "plumb_bob",
        "avg_reprojection_error": result.rms_px,
        "nr_of_frames": len(result.kept_views),
        "board": f"{board.kind} {board.cols}x{board.rows} square {board.square_m:g} m",
        "calibration_time": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "views": ", ".join(names[i] for i in result.kept_views),
    })


def _report(result: CalibrationResult, names: list[str], out_path: Path) -> str:
    cam = result.camera
    dist = " ".join(f"{d:.5g}" for d in cam.dist_coeffs)
    worst = int(np.argmax(result.view_rms_px))
    lines = [
        f"wrote {out_path}: {cam.width}x{cam.height} "
        f"fx {cam.fx:.2f} fy {cam.fy:.2f} cx {cam.cx:.2f} cy {cam.cy:.2f} px "
        f"(1-sigma {result.std_fx_px:.2f} {result.std_fy_px:.2f} {result.std_cx_px:.2f} {result.std_cy_px:.2f}); "
        f"dist {dist}",
        f"RMS reprojection error {result.rms_px:.3f} px over {len(result.kept_views)} views "
        f"(worst {names[result.kept_views[worst]]} {result.view_rms_px[worst]:.3f} px)"
        + (f"; dropped {', '.join(names[i] for i in result.rejected_views)}" if result.rejected_views else ""),
        f"coverage: {result.coverage.summary()}",
    ]
    if not result.coverage.complete:
        lines.append("warning: coverage incomplete: add views with the board in the missing cells/tilts "
                     "(the distortion there is extrapolated)")
    return "\n".join(lines)


def run_calibrate_cli(args: argparse.Namespace) -> int:
    """`companion calibrate` (options: `companion.calibration_args`): 0 with the YAML written, 1 when too
    few views were found, 2 on bad input."""
    board = _board(args)
    collector = _Collector(board, sys.stderr, [], [])
    out_path = Path(args.out)
    if not out_path.parent.is_dir():
        raise InputError(f"--out: {out_path.parent} is not a folder")
    if args.images:
        _from_folder(Path(args.images), args.pattern, collector)
    else:
        from companion.config import CameraConfig, load_config

        if args.video:
            if not Path(args.video).is_file():
                raise InputError(f"--video: {args.video}: no such file")
            config = CameraConfig(kind="video", path=args.video, pacing="consumer", color="gray")
            step, max_seconds = args.step, math.inf
        else:
            config = load_config(args.camera).camera
            if config.kind == "synthetic":
                raise InputError('--camera: camera.kind = "synthetic" has no real images to calibrate')
            step, max_seconds = 1, args.max_seconds
        try:
            asyncio.run(_from_source(config, collector, args.views, max_seconds, step))
        except KeyboardInterrupt:
            print("interrupted: calibrating with the views so far", file=sys.stderr)
    if collector.size is None or len(collector.views) < 4:
        raise CompanionError(f"only {len(collector.views)} board views found (need at least 4): check --board, "
                             f"--cols and --rows (inner corners for a checkerboard)")
    result = calibrate(collector.views, *collector.size, model=args.model)
    _write_yaml(out_path, result, board, collector.names)
    PinholeCamera.from_yaml(out_path)  # what `camera.calibration` will read
    print(_report(result, collector.names, out_path))
    return 0
