"""Everything `companion run` refuses in a configuration, in one place: `validate_for_run(config)`.

`load_config` checks the file itself (types, ranges, cross-field rules). This module checks
what the daemon needs from the machine when it starts, in the order it opens things: the
flight folder root, the MAVLink URL (and the serial device), the camera model (calibration
file or intrinsics), the camera source (video file, image folder), the rack model, the
control API (token rule, token file, upload folder) and the photo folder. `companion
check-config` (systemd's ExecStartPre) and `companion run` both call `validate_for_run`, so
a configuration check-config accepts is one run starts with, and the other way round.

Every failure is one `ConfigError` line starting with the key, e.g.
``camera.calibration: /etc/companion/camera.yaml: calibration file not found``.
Relative paths are relative to the working directory, as the daemon opens them.

This is an edge module (it reads files and stats devices), not part of the pure core; it
imports the driver helpers whose rules it applies (link URL parser, image-folder listing)
lazily so that the rule lives in one place.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from companion.camera import PinholeCamera
from companion.config import ApiConfig, CameraConfig, CompanionConfig, VideoConfig, is_loopback_address
from companion.errors import CameraError, CompanionError, ConfigError, InputError

__all__ = [
    "DEFAULT_FOCAL_PX",
    "DEFAULT_WIDTH_PX",
    "api_token",
    "camera_model_for",
    "default_camera_model",
    "read_token_file",
    "validate_for_run",
    "video_frame_size",
]

# DESIGN's example camera: 720x480 px with fx = fy = 630 px; other sizes scale it.
DEFAULT_WIDTH_PX = 720
DEFAULT_FOCAL_PX = 630.0
_MIN_TOKEN_CHARS = 16


def validate_for_run(config: CompanionConfig) -> None:
    """Raise `ConfigError` (one line, naming the key) for anything `companion run` would refuse.

    Does not open the camera device or the link; a V4L2 device that is missing at start is not
    an error (the camera driver retries it, as after an unplug), a missing serial port is.
    """
    _check_dir_writable("logging.flight_root", config.logging.flight_root)
    _check_mavlink(config)
    camera_model_for(config.camera)
    _check_camera_source(config.camera)
    if config.rack.model:
        _check_rack_model(config.rack.model)
    if config.api.enabled:
        api_token(config.api)
        _check_dir_writable("mission.upload_folder", config.mission.upload_folder)
    _check_dir_writable("mission.photo_folder", config.mission.photo_folder)
    if config.video.enabled:
        video_frame_size(config.video, config.camera)


def video_frame_size(video: VideoConfig, camera: CameraConfig) -> tuple[int, int]:
    """The streamed (width, height) in px: `video.width` x `video.height`, or the camera's size times
    `video.scale` rounded down to even numbers (H.264 4:2:0); `ConfigError` naming the key if too small."""
    if video.width > 0:
        w, h = video.width, video.height
    else:
        w = int(camera.width * video.scale) // 2 * 2
        h = int(camera.height * video.scale) // 2 * 2
    if w < 16 or h < 16:
        key = "video.width" if video.width > 0 else "video.scale"
        raise ConfigError(f"{key}: the stream would be {w}x{h} px; at least 16x16 px is needed")
    return w, h


# --------------------------------------------------------------------------- camera
def default_camera_model(width: int, height: int) -> PinholeCamera:
    """DESIGN's example intrinsics scaled to `width` x `height` px (the synthetic camera's default)."""
    focal_px = DEFAULT_FOCAL_PX * width / DEFAULT_WIDTH_PX
    return PinholeCamera(width=width, height=height, fx=focal_px, fy=focal_px, cx=width / 2.0, cy=height / 2.0)


def camera_model_for(camera: CameraConfig) -> PinholeCamera:
    """The calibrated camera the daemon uses for `camera`; `ConfigError` naming the key otherwise.

    From ``camera.calibration`` (OpenCV or ROS YAML; a calibration made at another size with the
    same aspect ratio is scaled), else ``camera.intrinsics`` (fx, fy, cx, cy px, no distortion),
    else DESIGN's default intrinsics for the synthetic camera. A real camera (v4l2, video,
    folder) without either is refused: vision would run on made-up intrinsics.
    """
    if camera.calibration:
        path = Path(camera.calibration)
        try:
            model = PinholeCamera.from_yaml(path)
        except (OSError, InputError, CameraError) as exc:
            raise ConfigError(f"camera.calibration: {_one_line(exc)}") from exc
        if (model.width, model.height) == (camera.width, camera.height):
            return model
        factor = camera.width / model.width
        if abs(model.height * factor - camera.height) > 0.5:
            raise ConfigError(
                f"camera.calibration: {path} is {model.width}x{model.height}, "
                f"camera is {camera.width}x{camera.height} (different aspect ratio)"
            )
        return model.scaled(factor)
    if camera.intrinsics is not None:
        fx, fy, cx, cy = camera.intrinsics
        try:
            return PinholeCamera(width=camera.width, height=camera.height, fx=fx, fy=fy, cx=cx, cy=cy)
        except InputError as exc:
            raise ConfigError(f"camera.intrinsics: {exc}") from exc
    if camera.kind == "synthetic":
        return default_camera_model(camera.width, camera.height)
    raise ConfigError(
        f'camera.calibration: required for kind = "{camera.kind}" (or set camera.intrinsics); '
        "make one with `companion calibrate`"
    )


def _check_camera_source(camera: CameraConfig) -> None:
    if camera.kind == "video":
        if not Path(camera.path).is_file():
            raise ConfigError(f"camera.path: {camera.path}: no such video file")
    elif camera.kind == "folder":
        from drivers.camera.folder import TIMESTAMPS_FILE, list_images, read_timestamps

        folder = Path(camera.path)
        if not folder.is_dir():
            raise ConfigError(f"camera.path: {folder}: no such image folder")
        files = list_images(folder)
        if not files:
            raise ConfigError(f"camera.path: {folder}: no images")
        stamps = folder / TIMESTAMPS_FILE
        if stamps.is_file():
            try:
                read_timestamps(stamps, files)
            except CameraError as exc:
                raise ConfigError(f"camera.path: {_one_line(exc)}") from exc


# --------------------------------------------------------------------------- link, rack
def _check_mavlink(config: CompanionConfig) -> None:
    from drivers.mavlink.url import parse_url

    for key, url in [("mavlink.url", config.mavlink.url)] + [
        (f"mavlink.gcs_forward[{i}]", u) for i, u in enumerate(config.mavlink.gcs_forward)
    ]:
        try:
            endpoint = parse_url(url)
        except ConfigError as exc:
            raise ConfigError(f"{key}: {_one_line(exc)}") from exc
        if key == "mavlink.url" and endpoint.kind == "serial":
            device = Path(endpoint.device or "")
            if not device.exists():
                raise ConfigError(f"mavlink.url: serial device {device} does not exist")
            if not os.access(device, os.R_OK | os.W_OK):
                raise ConfigError(f"mavlink.url: serial device {device} is not readable and writable by this user")


def _check_rack_model(path: str) -> None:
    from companion.vision.rack import RackModel

    try:
        RackModel.load(path)
    except (OSError, CompanionError, ValueError) as exc:
        raise ConfigError(f"rack.model: {_one_line(exc)}") from exc


# --------------------------------------------------------------------------- api
def read_token_file(path: str | os.PathLike[str]) -> str:
    """The bearer token in `path` (whitespace stripped); `ConfigError` naming `api.token_file` otherwise.

    The file must not be readable or writable by other users (chmod 600 or 640).
    """
    p = Path(path)
    try:
        mode = p.stat().st_mode
        token = p.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"api.token_file: cannot read {p}: {_one_line(exc)}") from exc
    if mode & stat.S_IROTH:
        raise ConfigError(f"api.token_file: {p} is readable by other users (chmod 600)")
    if mode & stat.S_IWOTH:
        raise ConfigError(f"api.token_file: {p} is writable by other users (chmod 600)")
    if len(token) < _MIN_TOKEN_CHARS or any(c.isspace() for c in token):
        raise ConfigError(f"api.token_file: {p} must hold one token of at least {_MIN_TOKEN_CHARS} characters")
    return token


def api_token(api: ApiConfig) -> str | None:
    """The control API's bearer token (None: no token, loopback only); `ConfigError` naming the key.

    A bind address that is not loopback needs ``api.token_file``: anyone on the network could
    otherwise start a mission.
    """
    token = read_token_file(api.token_file) if api.token_file else None
    if token is None and not is_loopback_address(api.bind):
        raise ConfigError(f"api.token_file: required when api.bind is not a loopback address (bind = {api.bind!r})")
    return token


# --------------------------------------------------------------------------- folders
def _check_dir_writable(key: str, folder: str) -> None:
    """`folder` is a writable directory, or can be created (its nearest existing parent is writable)."""
    p = Path(folder)
    probe = p
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        what = "is not a directory" if probe == p else f"cannot be created ({probe} is not a directory)"
        raise ConfigError(f"{key}: {p} {what}")
    if not os.access(probe, os.W_OK | os.X_OK):
        what = "is not writable" if probe == p else f"cannot be created ({probe} is not writable)"
        raise ConfigError(f"{key}: {p} {what} by this user")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())
