"""Camera sources: V4L2 (OpenCV), video file, image folder and the synthetic renderer.

All share `CameraSource`: an async context manager whose capture thread stamps
frames at capture and hands over only the newest one; see `docs/drivers.md`.
"""

from drivers.camera.base import CameraSource, CameraState, CameraStats, Capture, EndOfStream, Frame, convert_color
from drivers.camera.factory import default_camera_model, load_camera_model, open_camera
from drivers.camera.folder import ImageFolderCamera, list_images, read_timestamps
from drivers.camera.opencv import CaptureFactory, CaptureLike, V4L2Camera, VideoFileCamera, opencv_capture
from drivers.camera.synthetic import PoseSource, Render, SyntheticCamera

__all__ = [
    "CameraSource",
    "CameraState",
    "CameraStats",
    "Capture",
    "CaptureFactory",
    "CaptureLike",
    "EndOfStream",
    "Frame",
    "ImageFolderCamera",
    "PoseSource",
    "Render",
    "SyntheticCamera",
    "V4L2Camera",
    "VideoFileCamera",
    "convert_color",
    "default_camera_model",
    "list_images",
    "load_camera_model",
    "open_camera",
    "opencv_capture",
    "read_timestamps",
]
