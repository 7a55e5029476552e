"""The configuration's sections: one frozen dataclass per TOML table, and `CompanionConfig` holding them all.

Field types and value checks come from `companion.config_fields`; loading a file is
`companion.config`, which re-exports everything here.
"""

from __future__ import annotations

import ipaddress
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np

from companion.checks import FloatArray
from companion.config_fields import (
    _between,
    _check,
    _exposure,
    _finite_items,
    _ge,
    _gt,
    _nonempty,
    _positive_items,
    _Section,
    _url,
    _urls,
)
from companion.geometry.frames import R_NED_RACK_DEFAULT, rotation_from_euler_zyx

__all__ = [
    "ApiConfig",
    "CameraConfig",
    "CompanionConfig",
    "EkfOriginConfig",
    "FilterConfig",
    "LoggingConfig",
    "MavlinkConfig",
    "MissionConfig",
    "MountConfig",
    "RackConfig",
    "SafetyLimits",
    "VideoConfig",
    "VisionConfig",
    "is_loopback_address",
]


# --------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class MavlinkConfig(_Section):
    """MAVLink connection to the autopilot (see DESIGN "MAVLink contract")."""

    SECTION: ClassVar[str] = "mavlink"
    url: str = field(default="serial:/dev/ttyAMA0:921600", metadata=_check(_url))
    system_id: int = field(default=0, metadata=_check(_between(0, 255)))  # 0 = the autopilot's
    component_id: int = field(default=197, metadata=_check(_between(1, 255)))
    profile: Literal["auto", "ardupilot", "px4"] = "auto"
    gcs_forward: tuple[str, ...] = field(default=(), metadata=_check(_urls))
    tlog: bool = True
    # true: ODOMETRY; false: VISION_POSITION_ESTIMATE + VISION_SPEED_ESTIMATE; "auto" (default): what the
    # detected autopilot fuses -- ODOMETRY for PX4 (it ignores VISION_SPEED_ESTIMATE), VISION_* for ArduPilot
    odometry: bool | Literal["auto"] = "auto"
    # time base of the pose stamps (usec): "auto" = "local" for PX4 (its receiver converts usec with its
    # own TIMESYNC estimate), "autopilot" (TIMESYNC-converted) for ArduPilot and others
    pose_stamp_base: Literal["auto", "autopilot", "local"] = "auto"
    heartbeat_timeout_s: float = field(default=3.0, metadata=_check(_gt(0)))
    command_timeout_s: float = field(default=1.5, metadata=_check(_gt(0)))
    command_retries: int = field(default=3, metadata=_check(_ge(0)))


@dataclass(frozen=True)
class CameraConfig(_Section):
    """Camera source, format and calibration."""

    SECTION: ClassVar[str] = "camera"
    kind: Literal["v4l2", "video", "folder", "synthetic"] = "v4l2"
    device: str = field(default="/dev/video0", metadata=_check(_nonempty))  # v4l2: path or index
    path: str = ""  # video file or image folder
    width: int = field(default=720, metadata=_check(_gt(0)))
    height: int = field(default=480, metadata=_check(_gt(0)))
    fps: float = field(default=30.0, metadata=_check(_gt(0), _between(0, 1000)))
    pixel_format: Literal["MJPG", "YUYV", ""] = "MJPG"
    exposure: str | float = field(default="auto", metadata=_check(_exposure))  # V4L2 units of 100 µs
    gain: float | None = field(default=None, metadata=_check(_ge(0)))
    color: Literal["gray", "bgr"] = "gray"
    pacing: Literal["realtime", "consumer"] = "realtime"
    loop: bool = False
    calibration: str = ""  # OpenCV YAML
    intrinsics: tuple[float, float, float, float] | None = field(
        default=None, metadata=_check(_finite_items, _positive_items)
    )  # fx, fy, cx, cy in px
    lost_after_s: float = field(default=0.5, metadata=_check(_gt(0)))
    reopen_backoff_s: float = field(default=0.2, metadata=_check(_gt(0)))
    reopen_backoff_max_s: float = field(default=5.0, metadata=_check(_gt(0)))
    max_pose_age_s: float = field(default=0.5, metadata=_check(_gt(0)))
    # synthetic camera only: NED z (m) of the ground the camera sees when it differs from what the
    # rangefinder measures to (the simulator's deck); the ground odometer then takes its height from
    # the estimate. None: rangefinder (or the filter's ground) as usual.
    sim_ground_z_ned_m: float | None = None

    def _cross_check(self) -> None:
        if self.kind in ("video", "folder") and not self.path:
            raise self._fail("path", f'required when kind = "{self.kind}"')
        if self.sim_ground_z_ned_m is not None and self.kind != "synthetic":
            raise self._fail("sim_ground_z_ned_m", 'only valid with kind = "synthetic" (simulator)')
        if self.reopen_backoff_max_s < self.reopen_backoff_s:
            raise self._fail("reopen_backoff_max_s", "must be >= camera.reopen_backoff_s")


def _rotation_deg(roll_deg: float, pitch_deg: float, yaw_deg: float) -> FloatArray:
    return rotation_from_euler_zyx(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))


@dataclass(frozen=True)
class MountConfig(_Section):
    """Camera mount on the body: `T_body_cam` from a translation and ZYX Euler angles.

    `translation_m` is the camera's optical centre in body FRD (m);
    `R_body_cam = Rz(yaw) Ry(pitch) Rx(roll) @ R0` where R0 maps the optical
    frame onto body axes (x_cam = x_body, y_cam = y_body, z_cam = z_body); the
    default yaw of 90 deg gives DESIGN's downward camera with the image top
    toward the nose (x_cam = y_body, y_cam = -x_body).
    """

    SECTION: ClassVar[str] = "mount"
    translation_m: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=_check(_finite_items))
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 90.0

    @property
    def T_body_cam(self) -> FloatArray:
        """4x4 pose of the camera optical frame in the body FRD frame (p_body = T_body_cam @ p_cam)."""
        T = np.eye(4)
        T[:3, :3] = _rotation_deg(self.roll_deg, self.pitch_deg, self.yaw_deg)
        T[:3, 3] = self.translation_m
        return T


@dataclass(frozen=True)
class RackConfig(_Section):
    """The inspected rack: model file and its placement `T_ned_rack`.

    `yaw_deg` is the heading of the rack's +y axis (pipe direction) from north,
    clockwise, with the rack's z up (down = rack -z): `R_ned_rack = Rz(yaw) @
    R_NED_RACK_DEFAULT`. `rpy_deg` (roll, pitch, yaw of R_ned_rack, ZYX) gives
    the full rotation instead. `translation_m` is the rack origin in NED (m).
    """

    SECTION: ClassVar[str] = "rack"
    model: str = ""  # "" = the paper's 5-pipe rack shipped with companion
    translation_m: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=_check(_finite_items))
    yaw_deg: float = 0.0
    rpy_deg: tuple[float, float, float] | None = field(default=None, metadata=_check(_finite_items))

    @property
    def T_ned_rack(self) -> FloatArray:
        """4x4 pose of the rack frame in NED (p_ned = T_ned_rack @ p_rack)."""
        T = np.eye(4)
        if self.rpy_deg is not None:
            T[:3, :3] = _rotation_deg(*self.rpy_deg)
        else:
            T[:3, :3] = _rotation_deg(0.0, 0.0, self.yaw_deg) @ R_NED_RACK_DEFAULT
        T[:3, 3] = self.translation_m
        return T


@dataclass(frozen=True)
class EkfOriginConfig(_Section):
    """The EKF origin the daemon sets on the autopilot (SET_GPS_GLOBAL_ORIGIN)."""

    SECTION: ClassVar[str] = "ekf_origin"
    enabled: bool = True
    lat_deg: float = field(default=0.0, metadata=_check(_between(-90, 90)))
    lon_deg: float = field(default=0.0, metadata=_check(_between(-180, 180)))
    alt_m: float = field(default=0.0, metadata=_check(_between(-500, 9000)))


@dataclass(frozen=True)
class VisionConfig(_Section):
    """Vision source selection and pass-through tracker/odometer settings."""

    SECTION: ClassVar[str] = "vision"
    source: Literal["rack", "ground", "auto"] = "auto"
    max_rate_hz: float = field(default=50.0, metadata=_check(_gt(0)))
    rack_tracker: dict[str, Any] = field(default_factory=dict)  # RackTrackerConfig kwargs
    # floor added to the rack pose covariance (standard deviations, camera frame): the tracker's own
    # covariance is tighter than the camera-IMU time alignment, which would gate good poses out
    rack_std_floor_m: float = field(default=0.01, metadata=_check(_ge(0)))
    rack_std_floor_deg: float = field(default=0.5, metadata=_check(_between(0, 45)))
    # standard deviation added along the pipes, which the pipe edges do not observe (0 = trust the tracker)
    rack_along_pipe_std_m: float = field(default=0.0, metadata=_check(_ge(0)))
    # a gap between frames longer than this restarts the rack tracker from the IMU-propagated estimate
    frame_gap_reset_s: float = field(default=0.3, metadata=_check(_gt(0)))
    ground_odometer: dict[str, Any] = field(default_factory=dict)  # GroundOdometerConfig kwargs
    # find the rack in the image when the tracker does not lock from the start pose (a hint, not a survey)
    # or loses the rack (companion.daemon.acquisition); false: only the start pose and the filter re-seed it
    rack_acquire: bool = True
    # the tracker's lock from the start pose is checked against an acquisition on the deck (issue #16,
    # companion.daemon.hint_check): "withhold" its poses until verified (disarmed: no arming on an unverified
    # lock), "report" send them and say they are unverified, "off" no check
    rack_verify_start: Literal["withhold", "report", "off"] = "withhold"
    # the autopilot's roll and pitch as the rack tracker's attitude prior, at this standard deviation
    # (deg; 0 = vision only): it separates a roll about the pipes from a slide across them
    rack_attitude_prior_std_deg: float = field(default=1.0, metadata=_check(_between(0, 45)))


@dataclass(frozen=True)
class FilterConfig(_Section):
    """Navigation filter settings: the `[filter]` table, NavFilterConfig kwargs."""

    SECTION: ClassVar[str] = "filter"
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SafetyLimits(_Section):
    """Safety thresholds (mapped onto `companion.safety.SafetyConfig` by the daemon)."""

    SECTION: ClassVar[str] = "safety"
    battery_low_v: float = field(default=14.0, metadata=_check(_gt(0)))
    battery_low_pct: float = field(default=25.0, metadata=_check(_between(0, 100)))
    battery_critical_v: float = field(default=13.2, metadata=_check(_gt(0)))
    battery_critical_pct: float = field(default=10.0, metadata=_check(_between(0, 100)))
    battery_debounce_s: float = field(default=2.0, metadata=_check(_ge(0)))
    ceiling_m: float = field(default=8.0, metadata=_check(_gt(0)))  # max height above takeoff
    ceiling_clearance_m: float = field(default=1.0, metadata=_check(_ge(0)))  # to an overhead structure
    gcs_loss_hover_s: float = field(default=5.0, metadata=_check(_ge(0)))
    gcs_loss_land_s: float = field(default=30.0, metadata=_check(_ge(0)))
    vision_loss_hover_ms: float = field(default=300.0, metadata=_check(_gt(0)))
    vision_loss_land_s: float = field(default=10.0, metadata=_check(_ge(0)))
    # a hold ends by itself (the paused mission resumes) once the cause has been gone this long; 0 = only
    # the operator's `companion mission resume` ends it
    vision_resume_s: float = field(default=1.0, metadata=_check(_ge(0)))
    gcs_resume_s: float = field(default=3.0, metadata=_check(_ge(0)))
    geofence_min_ned_m: tuple[float, float, float] | None = None
    geofence_max_ned_m: tuple[float, float, float] | None = None
    max_speed_m_s: float = field(default=1.0, metadata=_check(_gt(0)))

    def _cross_check(self) -> None:
        if self.battery_critical_v > self.battery_low_v:
            raise self._fail("battery_critical_v", f"must be <= safety.battery_low_v ({self.battery_low_v:g})")
        if self.battery_critical_pct > self.battery_low_pct:
            raise self._fail("battery_critical_pct", f"must be <= safety.battery_low_pct ({self.battery_low_pct:g})")
        if self.gcs_loss_land_s < self.gcs_loss_hover_s:
            raise self._fail("gcs_loss_land_s", f"must be >= safety.gcs_loss_hover_s ({self.gcs_loss_hover_s:g})")
        if 0 < self.vision_loss_land_s * 1000.0 < self.vision_loss_hover_ms:
            raise self._fail(
                "vision_loss_land_s", f"must be >= safety.vision_loss_hover_ms ({self.vision_loss_hover_ms:g} ms)"
            )
        if (self.geofence_min_ned_m is None) != (self.geofence_max_ned_m is None):
            raise self._fail("geofence_max_ned_m", "geofence_min_ned_m and geofence_max_ned_m go together")
        lo_ned, hi_ned = self.geofence_min_ned_m, self.geofence_max_ned_m
        if lo_ned is not None and hi_ned is not None and any(lo >= hi for lo, hi in zip(lo_ned, hi_ned, strict=True)):
            raise self._fail("geofence_max_ned_m", "must be > geofence_min_ned_m on every axis")


@dataclass(frozen=True)
class MissionConfig(_Section):
    """Mission storage and defaults."""

    SECTION: ClassVar[str] = "mission"
    photo_folder: str = field(default="/var/lib/companion/photos", metadata=_check(_nonempty))
    upload_folder: str = field(default="/var/lib/companion/missions", metadata=_check(_nonempty))
    default_timeout_s: float = field(default=60.0, metadata=_check(_gt(0)))
    speed_limit_m_s: float = field(default=1.0, metadata=_check(_gt(0)))
    # heading errors above this are turned out in place before moving (0 = off)
    turn_first_deg: float = field(default=20.0, metadata=_check(_between(0, 180)))
    # how long the take-off waits for the autopilot's pre-arm checks (ArduCopter's EKF aligns on the
    # vision poses for ~14 s after they start) before the action fails with the autopilot's reason
    arm_ready_timeout_s: float = field(default=40.0, metadata=_check(_gt(0)))
    # before a servo / gotoxy waypoint, while the position along the pipes is still the configured start's
    # (acquired on the deck, no rack end seen yet): fly a bounded leg toward the nearest rack end at this
    # speed, at most this far past the end in the estimate, until the end is seen; else hold and pause
    # (companion.mission.along_pipe; false: fly the waypoints with the start's along-pipe position)
    along_pipe_search: bool = True
    along_pipe_search_speed_m_s: float = field(default=0.2, metadata=_check(_gt(0), _between(0, 0.5)))
    along_pipe_search_margin_m: float = field(default=0.5, metadata=_check(_between(0, 2)))


@dataclass(frozen=True)
class ApiConfig(_Section):
    """The control API (HTTP): bind address, port, bearer token file, upload size limit."""

    SECTION: ClassVar[str] = "api"
    enabled: bool = True
    bind: str = field(default="127.0.0.1", metadata=_check(_nonempty))
    port: int = field(default=8765, metadata=_check(_between(0, 65535)))  # 0 = ephemeral
    token_file: str = ""
    max_upload_bytes: int = field(default=262144, metadata=_check(_gt(0), _between(1, 64 * 1024 * 1024)))

    @property
    def is_loopback(self) -> bool:
        """True when the bind address only accepts local connections."""
        return is_loopback_address(self.bind)


def is_loopback_address(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and "localhost"."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _even(v: Any) -> str | None:
    return None if v % 2 == 0 else f"must be even (H.264 4:2:0), got {v}"


@dataclass(frozen=True)
class VideoConfig(_Section):
    """Video to the ground station (H.264 over RTP/UDP, QGroundControl's default port) and the status page's image.

    width/height 0: the camera's size times `scale`; `fps` caps the stream (newer frames replace older ones
    while the encoder is busy: frames are dropped, never queued); `stamp` draws the capture time as a block
    code in the top-left corner (latency measurements)."""

    SECTION: ClassVar[str] = "video"
    enabled: bool = False
    host: str = field(default="127.0.0.1", metadata=_check(_nonempty))
    port: int = field(default=5600, metadata=_check(_between(1, 65535)))
    width: int = field(default=0, metadata=_check(_between(0, 4096), _even))
    height: int = field(default=0, metadata=_check(_between(0, 4096), _even))
    scale: float = field(default=1.0, metadata=_check(_gt(0), _between(0, 4)))
    fps: float = field(default=15.0, metadata=_check(_gt(0), _between(0, 60)))
    bitrate_kbps: int = field(default=1500, metadata=_check(_between(50, 50000)))
    keyframe_interval_s: float = field(default=1.0, metadata=_check(_gt(0)))
    stamp: bool = False
    mjpeg_fps: float = field(default=10.0, metadata=_check(_gt(0), _between(0, 60)))
    jpeg_quality: int = field(default=70, metadata=_check(_between(10, 100)))
    sdp_path: str = ""  # where the SDP file for VLC / ffplay goes ("": the flight folder's stream.sdp)
    camera_component_id: int = field(default=100, metadata=_check(_between(100, 105)))  # MAV_COMP_ID_CAMERA..6

    def _cross_check(self) -> None:
        if (self.width == 0) != (self.height == 0):
            raise self._fail("height" if self.height == 0 else "width", "video.width and video.height go together "
                             "(both 0: the camera's size times video.scale)")


@dataclass(frozen=True)
class LoggingConfig(_Section):
    """Flight folders and log level."""

    SECTION: ClassVar[str] = "logging"
    flight_root: str = field(default="/var/log/companion/flights", metadata=_check(_nonempty))
    level: Literal["debug", "info", "warning", "error"] = "info"
    health_period_s: float = field(default=5.0, metadata=_check(_gt(0)))
    record_frames: bool = False  # keep every processed frame in the flight folder (for `companion replay`)


@dataclass(frozen=True)
class CompanionConfig:
    """The whole configuration, one field per TOML table."""

    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    mount: MountConfig = field(default_factory=MountConfig)
    rack: RackConfig = field(default_factory=RackConfig)
    ekf_origin: EkfOriginConfig = field(default_factory=EkfOriginConfig)
    vision: VisionConfig = field(default_factory=VisionConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    safety: SafetyLimits = field(default_factory=SafetyLimits)
    mission: MissionConfig = field(default_factory=MissionConfig)
    api: ApiConfig = field(default_factory=ApiConfig)
    video: VideoConfig = field(default_factory=VideoConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)

