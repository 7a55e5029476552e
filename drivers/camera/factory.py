"""`open_camera(config, clock)`: the source a `CameraConfig` describes; `load_camera_model(config)`."""

from __future__ import annotations

from pathlib import Path

from companion.camera import PinholeCamera
from companion.clock import Clock
from companion.config import CameraConfig
from companion.errors import CameraError, InputError
from drivers.camera.base import CameraSource
from drivers.camera.folder import ImageFolderCamera
from drivers.camera.opencv import CaptureFactory, V4L2Camera, VideoFileCamera
from drivers.camera.synthetic import PoseSource, Render, SyntheticCamera

# DESIGN's example camera: 720x480 px with fx = fy = 630 px; other sizes scale it.
_DEFAULT_WIDTH_PX = 720
_DEFAULT_FOCAL_PX = 630.0


def open_camera(
    config: CameraConfig,
    clock: Clock,
    *,
    render: Render | None = None,
    pose_source: PoseSource | None = None,
    capture_factory: CaptureFactory | None = None,
) -> CameraSource:
    """The camera source for `config` (not started: use it as an async context manager).

    `render` and `pose_source` are required for `kind = "synthetic"`;
    `capture_factory` replaces `cv2.VideoCapture` for v4l2/video (tests).
    """
    common = {
        "color": config.color,
        "lost_after_s": config.lost_after_s,
        "reopen_backoff_s": config.reopen_backoff_s,
        "reopen_backoff_max_s": config.reopen_backoff_max_s,
    }
    if config.kind == "v4l2":
        return V4L2Camera(
            clock,
            config.device,
            width=config.width,
            height=config.height,
            fps=config.fps,
            pixel_format=config.pixel_format,
            exposure=config.exposure,
            gain=config.gain,
            capture_factory=capture_factory,
            **common,  # type: ignore[arg-type]
        )
    if config.kind == "video":
        return VideoFileCamera(
            clock,
            config.path,
            fps=config.fps,
            pacing=config.pacing,
            loop=config.loop,
            capture_factory=capture_factory,
            **common,  # type: ignore[arg-type]
        )
    if config.kind == "folder":
        return ImageFolderCamera(
            clock, config.path, fps=config.fps, pacing=config.pacing, loop=config.loop, **common  # type: ignore[arg-type]
        )
    if config.kind == "synthetic":
        if render is None or pose_source is None:
            raise CameraError('camera.kind = "synthetic" needs render= and pose_source=')
        return SyntheticCamera(
            clock,
            render,
            pose_source,
            fps=config.fps,
            max_pose_age_s=config.max_pose_age_s,
            **common,  # type: ignore[arg-type]
        )
    raise CameraError(f"camera.kind: unknown kind {config.kind!r}")  # pragma: no cover - config validates


def default_camera_model(width: int, height: int) -> PinholeCamera:
    """DESIGN's example intrinsics scaled to `width` x `height` px (the synthetic camera's default)."""
    focal_px = _DEFAULT_FOCAL_PX * width / _DEFAULT_WIDTH_PX
    return PinholeCamera(width=width, height=height, fx=focal_px, fy=focal_px, cx=width / 2.0, cy=height / 2.0)


def load_camera_model(config: CameraConfig) -> PinholeCamera:
    """The calibrated camera for `config`.

    From `config.calibration` (OpenCV YAML; a calibration made at another size
    with the same aspect ratio is scaled), else from `config.intrinsics`
    (fx, fy, cx, cy px, no distortion), else DESIGN's default intrinsics for
    the synthetic camera. Real cameras without either raise `CameraError`.
    """
    if config.calibration:
        path = Path(config.calibration)
        try:
            camera = PinholeCamera.from_yaml(path)
        except (OSError, InputError, CameraError) as exc:
            raise CameraError(f"camera.calibration: {exc}") from exc
        if (camera.width, camera.height) == (config.width, config.height):
            return camera
        factor = config.width / camera.width
        if abs(camera.height * factor - config.height) > 0.5:
            raise CameraError(
                f"camera.calibration: {path} is {camera.width}x{camera.height}, "
                f"camera is {config.width}x{config.height} (different aspect ratio)"
            )
        return camera.scaled(factor)
    if config.intrinsics is not None:
        fx, fy, cx, cy = config.intrinsics
        return PinholeCamera(width=config.width, height=config.height, fx=fx, fy=fy, cx=cx, cy=cy)
    if config.kind == "synthetic":
        return default_camera_model(config.width, config.height)
    raise CameraError(f'camera.calibration: required for kind = "{config.kind}" (or set camera.intrinsics)')
