"""The daemon's configuration: one TOML file loaded into validated frozen dataclasses.

`load_config(path)` reads the file (default `/etc/companion/companion.toml`)
with `tomllib`; `parse_config(mapping)` builds the same from a dict. Every
section is a frozen dataclass whose fields all have defaults, so a file only
lists what differs from them. Types and values are checked when a section is
constructed (also when code builds one directly), and every error is a
`ConfigError` whose message starts with the key path, e.g.
``safety.battery_low_v: must be > 0, got -3``. Unknown keys are errors too.

Relative paths of the input files a configuration names (``camera.calibration``,
``camera.path``, ``rack.model``, ``api.token_file``) are relative to the file's folder.

Units follow the key names (`_m`, `_s`, `_ms`, `_deg`, `_v`, `_pct`); angles
are degrees here at the edge and become radians in the transforms this module
returns (`MountConfig.T_body_cam`, `RackConfig.T_ned_rack`).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import tomllib
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal, TypeVar

import numpy as np

from companion.checks import FloatArray
from companion.errors import ConfigError
from companion.geometry.frames import R_NED_RACK_DEFAULT, rotation_from_euler_zyx

DEFAULT_CONFIG_PATH = Path("/etc/companion/companion.toml")

_Check = Callable[[Any], str | None]


# --------------------------------------------------------------------------- value checks
def _gt(bound: float) -> _Check:
    return lambda v: None if v > bound else f"must be > {bound:g}, got {v:g}"


def _ge(bound: float) -> _Check:
    return lambda v: None if v >= bound else f"must be >= {bound:g}, got {v:g}"


def _between(lo: float, hi: float) -> _Check:
    return lambda v: None if lo <= v <= hi else f"must be in [{lo:g}, {hi:g}], got {v:g}"


def _nonempty(v: Any) -> str | None:
    return None if v else "must not be empty"


def _exposure(v: Any) -> str | None:
    if isinstance(v, str):
        return None if v == "auto" else f'must be "auto" or a number > 0, got "{v}"'
    return None if v > 0 else f'must be "auto" or a number > 0, got {v:g}'


def _finite_items(v: Any) -> str | None:
    if v is None:
        return None
    return None if all(math.isfinite(x) for x in v) else "must be finite numbers"


def _positive_items(v: Any) -> str | None:
    if v is None:
        return None
    return None if all(x > 0 for x in v) else "must all be > 0"


def _url(v: Any) -> str | None:
    schemes = ("serial:", "udpin:", "udpout:", "udp:", "tcp:", "tcpin:", "udpbcast:")
    if any(v.startswith(s) for s in schemes) or v.startswith("/dev/"):
        return None
    return f"must start with one of {', '.join(schemes)} or be a /dev path, got {v!r}"


def _urls(v: Any) -> str | None:
    for item in v:
        err = _url(item)
        if err is not None:
            return err
    return None


def _check(*checks: _Check) -> dict[str, Any]:
    return {"checks": checks}


# --------------------------------------------------------------------------- generic machinery
def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return " | ".join(f'"{a}"' if isinstance(a, str) else str(a) for a in typing.get_args(tp))
    if origin in (types.UnionType, typing.Union):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        plural = {float: "numbers", int: "integers", str: "strings", bool: "booleans"}.get(args[0], str(args[0]))
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {plural}"
        return f"a list of {len(args)} {plural}"
    if tp is type(None):
        return "absent"
    if origin is dict:
        return "a table"
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}.get(tp, str(tp))


class _Mismatch(Exception):
    pass


def _coerce(value: Any, tp: Any) -> Any:
    """`value` converted to the annotation `tp`, or `_Mismatch`."""
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        if value in typing.get_args(tp) and type(value) in {type(a) for a in typing.get_args(tp)}:
            return value
        raise _Mismatch
    if origin in (types.UnionType, typing.Union):
        for option in typing.get_args(tp):
            if option is type(None):
                if value is None:
                    return None
                continue
            try:
                return _coerce(value, option)
            except _Mismatch:
                continue
        raise _Mismatch
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise _Mismatch
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0]) for v in value)
        if len(value) != len(args):
            raise _Mismatch
        return tuple(_coerce(v, a) for v, a in zip(value, args, strict=True))
    if origin is dict:
        if not isinstance(value, Mapping):
            raise _Mismatch
        return dict(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise _Mismatch
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise _Mismatch
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            out = float(value)
            if not math.isfinite(out):
                raise _Mismatch
            return out
        raise _Mismatch
    if tp is str:
        if isinstance(value, str):
            return value
        raise _Mismatch
    raise TypeError(f"unsupported config annotation {tp!r}")  # pragma: no cover - programming error


class _Section:
    """Mixin: type coercion and value checks of a frozen config dataclass."""

    SECTION: ClassVar[str] = ""

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            key = f"{self.SECTION}.{f.name}"
            value = getattr(self, f.name)
            try:
                value = _coerce(value, hints[f.name])
            except _Mismatch:
                raise ConfigError(f"{key}: must be {_type_name(hints[f.name])}, got {value!r}") from None
            for check in f.metadata.get("checks", ()):
                if value is None:
                    continue
                message = check(value)
                if message is not None:
                    raise ConfigError(f"{key}: {message}")
            object.__setattr__(self, f.name, value)
        self._cross_check()

    def _cross_check(self) -> None:
        """Checks spanning several fields (override)."""

    def _fail(self, name: str, message: str) -> ConfigError:
        return ConfigError(f"{self.SECTION}.{name}: {message}")


_T = TypeVar("_T")


def build_dataclass(cls: type[_T], values: Mapping[str, Any], path: str, **extra: Any) -> _T:
    """`cls(**values, **extra)` with unknown keys reported as ``ConfigError("<path>.<key>: unknown key")``.

    For pass-through tables (`vision.rack_tracker`, `vision.ground_odometer`,
    `filter`) whose target dataclass lives in another module. A sub-table whose
    field is itself a dataclass is built recursively (`[filter.imu]`); lists
    become tuples for tuple fields. `extra` supplies arguments that do not come
    from the file. Errors raised by the class's own validation are re-raised as
    `ConfigError` naming `path`.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # unresolvable annotations: no nested building
        hints = {}
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        if key not in fields:
            raise ConfigError(f"{path}.{key}: unknown key (valid: {', '.join(sorted(fields))})")
        hint = hints.get(key)
        if isinstance(value, Mapping) and isinstance(hint, type) and dataclasses.is_dataclass(hint):
            value = build_dataclass(hint, value, f"{path}.{key}")
        elif isinstance(value, list) and typing.get_origin(hint) is tuple:
            value = tuple(value)
        kwargs[key] = value
    kwargs.update(extra)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from exc


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


_SECTIONS: dict[str, type[_Section]] = {
    f.name: f.default_factory  # type: ignore[misc]
    for f in dataclasses.fields(CompanionConfig)
}


def default_config() -> CompanionConfig:
    """Every default (a valid configuration: serial autopilot, V4L2 camera, API on loopback)."""
    return CompanionConfig()


def _section_from_table(name: str, table: Any) -> _Section:
    cls = _SECTIONS[name]
    if not isinstance(table, Mapping):
        raise ConfigError(f"{name}: must be a table, got {table!r}")
    if name == "filter":
        return FilterConfig(params=dict(table))
    known = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for key in table:
        if key not in known:
            raise ConfigError(f"{name}.{key}: unknown key (valid: {', '.join(sorted(known))})")
    return cls(**table)


def _check_passthrough(config: CompanionConfig) -> None:
    """Check pass-through tables against their target dataclasses when those modules exist."""
    targets: list[tuple[str, str, str, dict[str, Any]]] = [
        ("companion.vision.rack", "RackTrackerConfig", "vision.rack_tracker", config.vision.rack_tracker),
        ("companion.vision.ground", "GroundOdometerConfig", "vision.ground_odometer", config.vision.ground_odometer),
        ("companion.estimation", "NavFilterConfig", "filter", config.filter.params),
    ]
    import importlib

    for module_name, class_name, path, values in targets:
        try:
            module = importlib.import_module(module_name)
            cls = getattr(module, class_name)
        except (ImportError, AttributeError):
            continue
        build_dataclass(cls, values, path)


def parse_config(data: Mapping[str, Any], source: str = "<config>") -> CompanionConfig:
    """A validated `CompanionConfig` from a mapping of TOML tables (missing tables take defaults)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: top level must be a table")
    sections: dict[str, Any] = {}
    for name, table in data.items():
        if name not in _SECTIONS:
            raise ConfigError(f"{name}: unknown section (valid: {', '.join(sorted(_SECTIONS))})")
        sections[name] = _section_from_table(name, table)
    config = CompanionConfig(**sections)
    _check_passthrough(config)
    mission_limits(config)  # the mission limits the safety section implies must be consistent
    return config


def load_config(path: str | Path = DEFAULT_CONFIG_PATH) -> CompanionConfig:
    """Read and validate a TOML configuration file; `ConfigError` names the file or the key."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read ({exc.strerror or exc})") from exc
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not UTF-8 text") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: TOML syntax error: {exc}") from exc
    return _relative_to(parse_config(data, source=str(p)), p.parent)


# Input files a configuration names: relative paths are relative to the configuration file's folder.
_FILE_KEYS = (("camera", "calibration"), ("camera", "path"), ("rack", "model"), ("api", "token_file"))


def _relative_to(config: CompanionConfig, folder: Path) -> CompanionConfig:
    """`config` with the relative input-file paths of `_FILE_KEYS` made relative to `folder`.

    So `camera.calibration = "camera.yaml"` next to the configuration is found whatever the
    working directory (systemd starts the daemon in /var/lib/companion); the folders the daemon
    writes (flight root, photos, uploads) stay relative to the working directory.
    """
    sections: dict[str, Any] = {}
    for section_name, key in _FILE_KEYS:
        section = sections.get(section_name, getattr(config, section_name))
        value = getattr(section, key)
        if value and not Path(value).is_absolute():
            sections[section_name] = dataclasses.replace(section, **{key: str(folder / value)})
    return dataclasses.replace(config, **sections) if sections else config


def mission_limits(config: CompanionConfig) -> Any:
    """The `companion.mission.MissionLimits` a mission is validated against on this vehicle.

    ceiling_m = ``safety.ceiling_m``; max_speed_m_s = the lower of ``safety.max_speed_m_s`` and
    ``mission.speed_limit_m_s``; the geofence box = ``safety.geofence_min_ned_m/max_ned_m``, with
    rack-frame goals placed by ``rack`` (`RackConfig.T_ned_rack`); every other limit keeps the
    parser's default. `companion mission validate --config` and the control API's upload check
    both validate against this.
    """
    from companion.errors import InputError
    from companion.mission import MissionLimits

    try:
        return MissionLimits(
            ceiling_m=config.safety.ceiling_m,
            max_speed_m_s=min(config.safety.max_speed_m_s, config.mission.speed_limit_m_s),
            geofence_min_ned_m=config.safety.geofence_min_ned_m,
            geofence_max_ned_m=config.safety.geofence_max_ned_m,
            T_ned_rack=tuple(float(v) for v in config.rack.T_ned_rack.ravel()),
        )
    except InputError as exc:
        raise ConfigError(f"safety.ceiling_m: {exc}") from exc


def missing_files(config: CompanionConfig) -> list[str]:
    """Warnings for files the configuration names that do not exist on this machine ("key: path")."""
    named = [
        ("camera.calibration", config.camera.calibration),
        ("camera.path", config.camera.path if config.camera.kind in ("video", "folder") else ""),
        ("rack.model", config.rack.model),
        ("api.token_file", config.api.token_file),
    ]
    if config.camera.kind == "v4l2" and config.camera.device.startswith("/"):
        named.append(("camera.device", config.camera.device))
    return [f"{key}: {value} does not exist" for key, value in named if value and not Path(value).exists()]


def check_config_cli(path: str | Path, offline: bool = False) -> tuple[int, str]:
    """For `companion check-config FILE`: (0, summary) if `companion run` would accept it, else (2, one line).

    The check is `companion.config_checks.validate_for_run`, the one `companion run` makes
    before it starts (camera calibration parses, a real camera has one, a non-loopback API has
    a token, the rack model loads, folders are writable, ...). `offline` (a configuration
    checked away from the drone) checks the file alone and lists the files it names that are
    not on this machine as warnings.
    """
    from companion.config_checks import validate_for_run

    try:
        config = load_config(path)
        if not offline:
            validate_for_run(config)
    except ConfigError as exc:
        return 2, f"{path}: invalid: {' '.join(str(exc).split())}"
    summary = (
        f"{path}: ok{' (offline)' if offline else ''} (mavlink {config.mavlink.url}, profile {config.mavlink.profile}; "
        f"camera {config.camera.kind} {config.camera.width}x{config.camera.height}@{config.camera.fps:g}; "
        f"vision {config.vision.source}; api {config.api.bind}:{config.api.port})"
    )
    warnings = [f"warning: {w}" for w in missing_files(config)] if offline else []
    return 0, "\n".join([summary, *warnings])
