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
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from companion.config_fields import _Section, build_dataclass
from companion.config_sections import (
    ApiConfig,
    CameraConfig,
    CompanionConfig,
    EkfOriginConfig,
    FilterConfig,
    LoggingConfig,
    MavlinkConfig,
    MissionConfig,
    MountConfig,
    RackConfig,
    SafetyLimits,
    VideoConfig,
    VisionConfig,
    is_loopback_address,
)
from companion.errors import ConfigError

__all__ = [
    "DEFAULT_CONFIG_PATH",
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
    "build_dataclass",
    "check_config_cli",
    "default_config",
    "is_loopback_address",
    "load_config",
    "missing_files",
    "mission_limits",
    "parse_config",
]

DEFAULT_CONFIG_PATH = Path("/etc/companion/companion.toml")


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
