"""Configuration: every section, defaults, key-naming errors, the shipped example file."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import (
    ApiConfig,
    CameraConfig,
    CompanionConfig,
    MountConfig,
    RackConfig,
    build_dataclass,
    check_config_cli,
    default_config,
    load_config,
    mission_limits,
    parse_config,
)
from companion.errors import ConfigError
from companion.geometry.frames import default_T_body_cam, default_T_ned_rack, rotation_from_euler_zyx

EXAMPLE = Path(__file__).resolve().parents[2] / "systemd" / "companion.toml"

FULL: dict[str, Any] = {
    "mavlink": {
        "url": "udpin:0.0.0.0:14550",
        "system_id": 1,
        "component_id": 191,
        "profile": "px4",
        "gcs_forward": ["udpout:10.0.0.2:14550"],
        "tlog": False,
        "odometry": True,
    },
    "camera": {
        "kind": "video",
        "path": "/data/flight.mp4",
        "width": 640,
        "height": 480,
        "fps": 25,
        "pixel_format": "YUYV",
        "exposure": 40,
        "gain": 2.5,
        "color": "bgr",
        "pacing": "consumer",
        "calibration": "/etc/companion/cam.yaml",
    },
    "mount": {"translation_m": [0.1, 0.0, 0.05], "roll_deg": 1.0, "pitch_deg": -2.0, "yaw_deg": 90},
    "rack": {"model": "/etc/companion/rack.toml", "translation_m": [5, 2, 0], "yaw_deg": 30},
    "ekf_origin": {"lat_deg": 43.6, "lon_deg": 1.44, "alt_m": 150},
    "vision": {"source": "rack", "max_rate_hz": 30},
    "filter": {"source_timeout_s": 0.4},
    "safety": {
        "battery_low_v": 14.4,
        "battery_critical_v": 13.6,
        "ceiling_m": 6,
        "gcs_loss_hover_s": 3,
        "gcs_loss_land_s": 20,
        "vision_loss_hover_ms": 200,
        "geofence_min_ned_m": [-5, -5, -4],
        "geofence_max_ned_m": [5, 5, 0],
    },
    "mission": {"photo_folder": "/tmp/p", "default_timeout_s": 30, "speed_limit_m_s": 0.5},
    "api": {"bind": "0.0.0.0", "port": 9000, "token_file": "/etc/companion/token", "max_upload_bytes": 100000},
    "logging": {"flight_root": "/tmp/flights", "level": "debug"},
}


def test_default_config_is_valid_and_matches_design_frames() -> None:
    config = default_config()
    assert config == CompanionConfig()
    assert config.mavlink.component_id == 197 and config.mavlink.system_id == 0
    assert config.api.bind == "127.0.0.1" and config.api.is_loopback
    np.testing.assert_allclose(config.mount.T_body_cam, default_T_body_cam(), atol=1e-12)
    np.testing.assert_allclose(config.rack.T_ned_rack, default_T_ned_rack(), atol=1e-12)


def test_every_section_parses_into_typed_frozen_values() -> None:
    config = parse_config(FULL)
    assert config.mavlink.profile == "px4" and config.mavlink.gcs_forward == ("udpout:10.0.0.2:14550",)
    assert config.camera.fps == 25.0 and isinstance(config.camera.fps, float)
    assert config.camera.exposure == 40.0 and config.camera.pacing == "consumer"
    assert config.mount.translation_m == (0.1, 0.0, 0.05)
    assert config.ekf_origin.lat_deg == 43.6
    assert config.vision.source == "rack" and config.filter.params == {"source_timeout_s": 0.4}
    assert config.safety.geofence_min_ned_m == (-5.0, -5.0, -4.0)
    assert config.mission.speed_limit_m_s == 0.5 and config.api.port == 9000 and not config.api.is_loopback
    assert config.logging.level == "debug"
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.camera.fps = 10.0  # type: ignore[misc]
    assert dataclasses.replace(config.camera, kind="synthetic").kind == "synthetic"


def test_mount_and_rack_transforms() -> None:
    mount = MountConfig(translation_m=(0.1, 0.2, 0.3), roll_deg=10.0, pitch_deg=-5.0, yaw_deg=90.0)
    T = mount.T_body_cam
    np.testing.assert_allclose(T[:3, :3], rotation_from_euler_zyx(np.radians(10), np.radians(-5), np.radians(90)))
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, 0.3])
    rack = RackConfig(translation_m=(1.0, 2.0, 0.0), yaw_deg=90.0)
    # pipes (+y of the rack) heading east: rack +y maps to NED +y
    np.testing.assert_allclose(rack.T_ned_rack[:3, :3] @ [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rack.T_ned_rack[:3, :3] @ [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], atol=1e-12)
    full = RackConfig(rpy_deg=(180.0, 0.0, 90.0))
    np.testing.assert_allclose(full.T_ned_rack, default_T_ned_rack(), atol=1e-12)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"safety": {"battery_low_v": -3}}, "safety.battery_low_v: must be > 0, got -3"),
        ({"camera": {"colour": "gray"}}, "camera.colour: unknown key"),
        ({"cameras": {}}, "cameras: unknown section"),
        ({"camera": {"fps": "fast"}}, "camera.fps: must be a number"),
        ({"camera": {"kind": "usb"}}, 'camera.kind: must be "v4l2" | "video" | "folder" | "synthetic"'),
        ({"camera": {"kind": "folder"}}, 'camera.path: required when kind = "folder"'),
        ({"camera": {"exposure": "manual"}}, 'camera.exposure: must be "auto" or a number'),
        ({"camera": {"intrinsics": [1, 2, 3]}}, "camera.intrinsics: must be a list of 4 numbers or absent"),
        ({"camera": "v4l2"}, "camera: must be a table"),
        ({"mavlink": {"url": "http://x"}}, "mavlink.url: must start with"),
        ({"mavlink": {"component_id": 300}}, "mavlink.component_id: must be in [1, 255], got 300"),
        ({"mavlink": {"system_id": True}}, "mavlink.system_id: must be an integer"),
        ({"mavlink": {"gcs_forward": ["bogus"]}}, "mavlink.gcs_forward: must start with"),
        ({"mount": {"translation_m": [0, 0]}}, "mount.translation_m: must be a list of 3"),
        ({"rack": {"yaw_deg": "north"}}, "rack.yaw_deg: must be a number"),
        ({"ekf_origin": {"lat_deg": 91}}, "ekf_origin.lat_deg: must be in [-90, 90], got 91"),
        ({"vision": {"source": "lidar"}}, "vision.source: must be"),
        ({"safety": {"battery_critical_v": 15}}, "safety.battery_critical_v: must be <= safety.battery_low_v"),
        ({"safety": {"gcs_loss_land_s": 1}}, "safety.gcs_loss_land_s: must be >= safety.gcs_loss_hover_s"),
        ({"safety": {"vision_loss_land_s": 0.2}}, "safety.vision_loss_land_s: must be >= safety.vision_loss_hover_ms"),
        ({"safety": {"geofence_min_ned_m": [0, 0, 0]}}, "safety.geofence_max_ned_m: geofence_min_ned_m and"),
        (
            {"safety": {"geofence_min_ned_m": [0, 0, 0], "geofence_max_ned_m": [1, -1, 1]}},
            "safety.geofence_max_ned_m: must be > geofence_min_ned_m",
        ),
        ({"mission": {"default_timeout_s": 0}}, "mission.default_timeout_s: must be > 0, got 0"),
        ({"api": {"port": 70000}}, "api.port: must be in [0, 65535], got 70000"),
        ({"api": {"max_upload_bytes": 0}}, "api.max_upload_bytes: must be > 0, got 0"),
        ({"logging": {"level": "verbose"}}, "logging.level: must be"),
        ({"filter": {"no_such_param": 1}}, "filter.no_such_param: unknown key"),
        ({"vision": {"rack_tracker": {"no_such": 1}}}, "vision.rack_tracker.no_such: unknown key"),
        ({"mavlink": {"pose_stamp_base": "gps"}}, "mavlink.pose_stamp_base: must be"),
        ({"camera": {"sim_ground_z_ned_m": 4.0}}, "camera.sim_ground_z_ned_m: only valid with kind"),
        ({"vision": {"rack_std_floor_m": -0.01}}, "vision.rack_std_floor_m: must be >= 0"),
        ({"vision": {"rack_std_floor_deg": 90}}, "vision.rack_std_floor_deg: must be in [0, 45], got 90"),
        ({"vision": {"rack_along_pipe_std_m": -1}}, "vision.rack_along_pipe_std_m: must be >= 0"),
        ({"vision": {"frame_gap_reset_s": 0}}, "vision.frame_gap_reset_s: must be > 0"),
        ({"mission": {"turn_first_deg": 200}}, "mission.turn_first_deg: must be in [0, 180], got 200"),
        ({"mission": {"along_pipe_search_speed_m_s": 0}}, "mission.along_pipe_search_speed_m_s: must be > 0"),
        ({"mission": {"along_pipe_search_speed_m_s": 1.0}},
         "mission.along_pipe_search_speed_m_s: must be in [0, 0.5], got 1"),
        ({"mission": {"along_pipe_search_margin_m": -0.1}}, "mission.along_pipe_search_margin_m: must be in [0, 2]"),
        ({"mission": {"along_pipe_search": "on"}}, "mission.along_pipe_search: must be a boolean"),
        ({"logging": {"record_frames": "yes"}}, "logging.record_frames: must be a boolean"),
        ({"safety": {"ceiling_m": 0.1}}, "safety.ceiling_m: MissionLimits.min_height_m must be below ceiling_m"),
    ],
)
def test_bad_values_and_unknown_keys_name_the_key(data: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(data)
    assert str(err.value).startswith(message), str(err.value)


def test_sections_validate_when_built_in_code() -> None:
    with pytest.raises(ConfigError, match=r"^camera\.width: must be > 0"):
        CameraConfig(width=0)
    with pytest.raises(ConfigError, match=r"^api\.bind: must not be empty"):
        ApiConfig(bind="")


@dataclasses.dataclass(frozen=True)
class Inner:
    a: int = 1


@dataclasses.dataclass(frozen=True)
class Outer:
    inner: Inner = dataclasses.field(default_factory=Inner)
    values: tuple[float, ...] = ()
    required: str = "x"


def test_build_dataclass_reports_unknown_keys_and_builds_nested_tables() -> None:
    built = build_dataclass(Outer, {"inner": {"a": 5}, "values": [1.0, 2.0]}, "vision.thing", required="y")
    assert built == Outer(inner=Inner(a=5), values=(1.0, 2.0), required="y")
    with pytest.raises(ConfigError, match=r"^vision\.thing\.inner\.b: unknown key"):
        build_dataclass(Outer, {"inner": {"b": 1}}, "vision.thing")


def test_example_file_is_valid(tmp_path: Path) -> None:
    config = load_config(EXAMPLE)
    assert config.camera.kind == "v4l2" and config.api.bind == "127.0.0.1"
    defaults = default_config()
    assert config.mavlink.pose_stamp_base == defaults.mavlink.pose_stamp_base == "auto"
    for key in ("rack_std_floor_m", "rack_std_floor_deg", "rack_along_pipe_std_m", "frame_gap_reset_s"):
        assert getattr(config.vision, key) == getattr(defaults.vision, key), key  # documented with its default
    assert config.mission.turn_first_deg == defaults.mission.turn_first_deg
    assert config.logging.record_frames is defaults.logging.record_frames is False
    code, message = check_config_cli(EXAMPLE, offline=True)  # its devices and files are the drone's
    assert code == 0 and message.splitlines()[0].endswith("api 127.0.0.1:8765)")


def test_offline_check_config_warns_about_missing_files(tmp_path: Path) -> None:
    calibration = tmp_path / "cam.yaml"
    calibration.write_text("%YAML:1.0\n")
    path = tmp_path / "c.toml"
    path.write_text(f'[camera]\ncalibration = "{calibration}"\n[rack]\nmodel = "{tmp_path / "rack.toml"}"\n')
    code, message = check_config_cli(path, offline=True)
    assert code == 0
    warnings = [line for line in message.splitlines() if line.startswith("warning:")]
    assert any(w.startswith("warning: rack.model:") for w in warnings)
    assert not any("camera.calibration" in w for w in warnings)


def test_check_config_cli_exit_2_names_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[safety]\nbattery_low_v = -3\n")
    code, message = check_config_cli(bad)
    assert code == 2 and "safety.battery_low_v: must be > 0, got -3" in message
    syntax = tmp_path / "syntax.toml"
    syntax.write_text("[camera\nfps = 3\n")
    code, message = check_config_cli(syntax)
    assert code == 2 and "TOML syntax error" in message
    code, message = check_config_cli(tmp_path / "missing.toml")
    assert code == 2 and "cannot read" in message


def test_partial_file_keeps_defaults(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('[mavlink]\nurl = "udpin:127.0.0.1:14550"\n[camera]\nkind = "synthetic"\n')
    config = load_config(path)
    assert config.mavlink.url == "udpin:127.0.0.1:14550" and config.camera.kind == "synthetic"
    assert config.safety == default_config().safety


def test_mission_limits_follow_the_safety_and_mission_sections() -> None:
    limits = mission_limits(parse_config({"safety": {"ceiling_m": 3.5, "max_speed_m_s": 0.8},
                                          "mission": {"speed_limit_m_s": 0.6}}))
    assert limits.ceiling_m == 3.5 and limits.max_speed_m_s == 0.6
    limits = mission_limits(parse_config({"safety": {"max_speed_m_s": 0.4}}))
    assert limits.ceiling_m == 8.0 and limits.max_speed_m_s == 0.4


def test_mission_above_the_configured_ceiling_is_rejected(tmp_path: Path) -> None:
    from companion.mission import MissionError, load_mission

    path = tmp_path / "high.xml"
    path.write_text("""<?xml version="1.0" encoding="UTF-8"?>
<mission version="1" name="high" frame="ned" timeout="30" speed="0.5" threshold="0.1" yaw-threshold="5">
  <takeoff id="takeoff" height="5.0"/>
  <land id="land"/>
</mission>
""")
    assert load_mission(path).name == "high"  # the parser's default ceiling is 10 m
    with pytest.raises(MissionError, match="height"):
        load_mission(path, limits=mission_limits(parse_config({"safety": {"ceiling_m": 4.0}})))


def test_daemon_only_options_have_config_keys() -> None:
    config = parse_config({
        "camera": {"kind": "synthetic", "sim_ground_z_ned_m": 4.0},
        "vision": {"rack_std_floor_m": 0.02, "rack_std_floor_deg": 1.0, "rack_along_pipe_std_m": 0.05,
                   "frame_gap_reset_s": 0.5},
        "mission": {"turn_first_deg": 0},
        "logging": {"record_frames": True},
        "mavlink": {"pose_stamp_base": "local"},
    })
    assert config.camera.sim_ground_z_ned_m == 4.0 and config.vision.rack_along_pipe_std_m == 0.05
    assert config.vision.rack_std_floor_deg == 1.0 and config.vision.frame_gap_reset_s == 0.5
    assert config.mission.turn_first_deg == 0.0 and config.logging.record_frames
    assert config.mavlink.pose_stamp_base == "local"
