"""`open_camera(config, clock)`: the source a `CameraConfig` describes; `load_camera_model(config)`."""

from __future__ import annotations

from companion.camera import PinholeCamera
from companion.clock import Clock
from companion.config import CameraConfig
from companion.config_checks import camera_model_for, default_camera_model
from companion.errors import CameraError, ConfigError
from drivers.camera.base import CameraSource
from drivers.camera.folder import ImageFolderCamera
from drivers.camera.opencv import CaptureFactory, V4L2Camera, VideoFileCamera
from drivers.camera.synthetic import PoseSource, Render, SyntheticCamera

__all__ = ["default_camera_model", "load_camera_model", "open_camera"]


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


def load_camera_model(config: CameraConfig) -> PinholeCamera:
    """The calibrated camera for `config` (`companion.config_checks.camera_model_for`), `CameraError` if none.

    From `config.calibration` (OpenCV or ROS YAML; a calibration made at another size with the
    same aspect ratio is scaled), else from `config.intrinsics` (fx, fy, cx, cy px, no
    distortion), else DESIGN's default intrinsics for the synthetic camera. Real cameras
    without either raise `CameraError` naming ``camera.calibration``.
    """
    try:
        return camera_model_for(config)
    except ConfigError as exc:
        raise CameraError(str(exc)) from exc
