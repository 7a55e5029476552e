"""The options of `companion calibrate` (argparse only: importing it loads no OpenCV or numpy)."""

from __future__ import annotations

import argparse

__all__ = ["add_calibrate_arguments"]


def add_calibrate_arguments(p: argparse.ArgumentParser) -> None:
    """The `companion calibrate` options."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", metavar="DIR", help="a folder of board images (every image is a view)")
    src.add_argument("--video", metavar="FILE", help="a video of the board moved in front of the camera")
    src.add_argument("--camera", metavar="CONFIG", help="the live camera of this configuration's [camera] table")
    p.add_argument("--pattern", metavar="GLOB", default="*",
                   help="--images: only the files matching (e.g. 'left*.jpg')")
    p.add_argument("--board", choices=("checkerboard", "charuco"), default="checkerboard")
    p.add_argument("--cols", type=int, required=True,
                   help="checkerboard: inner corners along a row (9 for OpenCV's 10x7-square sample); charuco: squares")
    p.add_argument("--rows", type=int, required=True,
                   help="checkerboard: inner corners along a column; charuco: squares")
    p.add_argument("--square-m", type=float, default=0.025, help="square side (m; sets the pose scale only)")
    p.add_argument("--marker-m", type=float, default=0.0, help="charuco: marker side (m), default 0.75 x square")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="charuco: OpenCV ArUco dictionary")
    p.add_argument("--model", choices=("plumb_bob", "rational"), default="plumb_bob",
                   help="distortion: k1 k2 p1 p2 k3, or rational (+ k4 k5 k6) for wide lenses")
    p.add_argument("--views", type=int, default=25, help="video/camera: stop after this many views (default 25)")
    p.add_argument("--max-seconds", type=float, default=300.0, help="camera: give up collecting after this long")
    p.add_argument("--step", type=int, default=3, help="video: look at every STEP-th frame (default 3)")
    p.add_argument("--out", metavar="FILE.yaml", required=True, help="where to write the calibration")
