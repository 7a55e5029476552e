"""`companion check-config` checks what `companion run` refuses, through `validate_for_run` (issue 13 item 2)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from companion.camera import PinholeCamera
from companion.config import load_config
from companion.config_checks import validate_for_run
from companion.errors import ConfigError

ROS_YAML = """image_width: 720
image_height: 480
camera_name: downward
camera_matrix:
  rows: 3
  cols: 3
  data: [630.0, 0.0, 360.0, 0.0, 631.0, 240.0, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.2, 0.04, 0.0, 0.0, 0.0]
"""

RACK_TOML = """length_m = 10.0
[[pipes]]
radius_m = 0.1
gap_m = 0.3
[[pipes]]
radius_m = 0.15
"""


def _write_config(tmp_path: Path, extra: dict[str, str] | None = None, camera: str = "") -> Path:
    """A configuration `companion run` accepts on this machine, with `extra` lines appended per table."""
    tables = {
        "mavlink": 'url = "udpin:127.0.0.1:0"',
        "camera": camera or 'kind = "synthetic"',
        "logging": f'flight_root = "{tmp_path / "flights"}"',
        "mission": f'upload_folder = "{tmp_path / "missions"}"\nphoto_folder = "{tmp_path / "photos"}"',
        "api": 'bind = "127.0.0.1"\nport = 0',
    }
    for table, lines in (extra or {}).items():
        tables[table] = tables.get(table, "") + "\n" + lines
    path = tmp_path / "companion.toml"
    path.write_text("".join(f"[{name}]\n{body.strip()}\n" for name, body in tables.items()))
    return path


def _check_config(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "companion.cli", "check-config", *args],
        capture_output=True, text=True, timeout=120, check=False,
    )


def _calibration(tmp_path: Path) -> Path:
    path = tmp_path / "camera.yaml"
    PinholeCamera(720, 480, 630.0, 631.0, 360.0, 240.0, dist=(-0.2, 0.04, 0.0, 0.0, 0.0)).to_yaml(path)
    return path


def test_good_config_passes_and_is_what_run_validates(tmp_path: Path) -> None:
    path = _write_config(tmp_path)
    validate_for_run(load_config(path))
    result = _check_config(str(path))
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"{path}: ok (") and result.stderr == ""
    assert not (tmp_path / "flights").exists()  # checking creates nothing


def test_v4l2_with_a_calibration_and_ros_calibration_are_accepted(tmp_path: Path) -> None:
    cv_yaml = _calibration(tmp_path)
    validate_for_run(load_config(_write_config(tmp_path, camera=f'kind = "v4l2"\ncalibration = "{cv_yaml}"')))
    ros_yaml = tmp_path / "ost.yaml"
    ros_yaml.write_text(ROS_YAML)
    path = _write_config(tmp_path, camera=f'kind = "v4l2"\ncalibration = "{ros_yaml}"')
    result = _check_config(str(path))
    assert result.returncode == 0, result.stderr


# (what is wrong, the config change, the key the one-line error must start with)
BAD_CASES: list[tuple[str, dict[str, str], str, str]] = [
    ("v4l2 camera, no calibration", {}, 'kind = "v4l2"', "camera.calibration: required for kind = \"v4l2\""),
    ("calibration file missing", {}, 'kind = "v4l2"\ncalibration = "{tmp}/nope.yaml"',
     "camera.calibration: {tmp}/nope.yaml: calibration file not found"),
    ("malformed ROS calibration YAML", {}, 'kind = "v4l2"\ncalibration = "{tmp}/broken.yaml"',
     "camera.calibration: {tmp}/broken.yaml: not an OpenCV or ROS calibration YAML"),
    ("calibration of another aspect ratio", {}, 'kind = "v4l2"\nwidth = 640\ncalibration = "{tmp}/camera.yaml"',
     "camera.calibration: {tmp}/camera.yaml is 720x480, camera is 640x480"),
    ("API on all interfaces, no token", {"api": 'bind = "0.0.0.0"'}, "",
     "api.token_file: required when api.bind is not a loopback address"),
    ("token file readable by others", {"api": 'bind = "0.0.0.0"\ntoken_file = "{tmp}/token-644"'}, "",
     "api.token_file: {tmp}/token-644 is readable by other users"),
    ("token file missing", {"api": 'token_file = "{tmp}/no-token"'}, "", "api.token_file: cannot read {tmp}/no-token"),
    ("rack model missing", {"rack": 'model = "{tmp}/rack-missing.toml"'}, "", "rack.model: {tmp}/rack-missing.toml"),
    ("rack model invalid", {"rack": 'model = "{tmp}/rack-bad.toml"'}, "", "rack.model: {tmp}/rack-bad.toml: pipes"),
    ("video file missing", {}, 'kind = "video"\npath = "{tmp}/v.mp4"\nintrinsics = [600.0, 600.0, 360.0, 240.0]',
     "camera.path: {tmp}/v.mp4: no such video file"),
    ("image folder empty", {}, 'kind = "folder"\npath = "{tmp}/empty"\nintrinsics = [600.0, 600.0, 360.0, 240.0]',
     "camera.path: {tmp}/empty: no images"),
    ("serial port missing", {"mavlink": 'url = "serial:{tmp}/ttyNOPE:921600"'}, "",
     "mavlink.url: serial device {tmp}/ttyNOPE does not exist"),
    ("link url the link refuses", {"mavlink": 'url = "udpin:127.0.0.1"'}, "", "mavlink.url: link url"),
    ("flight root is a file", {"logging": 'flight_root = "{tmp}/token-644/flights"'}, "",
     "logging.flight_root: {tmp}/token-644/flights cannot be created ({tmp}/token-644 is not a directory)"),
    ("upload folder is a file", {"mission": 'upload_folder = "{tmp}/token-644"'}, "",
     "mission.upload_folder: {tmp}/token-644 is not a directory"),
]


@pytest.fixture
def files(tmp_path: Path) -> Path:
    _calibration(tmp_path)
    (tmp_path / "broken.yaml").write_text(ROS_YAML.replace("  data: [630.0", "  data: [630.0,,"))
    token = tmp_path / "token-644"
    token.write_text("0123456789abcdef0123\n")
    token.chmod(0o644)
    (tmp_path / "rack-bad.toml").write_text("length_m = 3.0\n")
    (tmp_path / "empty").mkdir()
    return tmp_path


def _bad_config(tmp: Path, extra: dict[str, str], camera: str) -> Path:
    fill = {k: v.replace("{tmp}", str(tmp)) for k, v in extra.items()}
    # each table appears once in TOML: a replaced key is removed from the base config, then the new lines added
    path = _write_config(tmp, camera=camera.replace("{tmp}", str(tmp)))
    text = path.read_text()
    for table, lines in fill.items():
        for line in lines.splitlines():
            key = line.split("=", 1)[0].strip()
            body = [row for row in text.split("\n") if not (row.startswith(f"{key} =") and _in_table(text, row, table))]
            text = "\n".join(body)
        if f"[{table}]\n" in text:
            text = text.replace(f"[{table}]\n", f"[{table}]\n{lines}\n", 1)
        else:
            text += f"[{table}]\n{lines}\n"
    path.write_text(text)
    return path


def _in_table(text: str, row: str, table: str) -> bool:
    current = ""
    for line in text.split("\n"):
        if line.startswith("["):
            current = line.strip("[]")
        if line == row:
            return current == table
    return False


@pytest.mark.parametrize(("what", "extra", "camera", "expected"), BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_config_is_one_line_naming_the_key(
    files: Path, what: str, extra: dict[str, str], camera: str, expected: str
) -> None:
    path = _bad_config(files, extra, camera)
    expected = expected.replace("{tmp}", str(files))
    with pytest.raises(ConfigError) as info:
        validate_for_run(load_config(path))
    assert str(info.value).startswith(expected), what
    result = _check_config(str(path))
    assert result.returncode == 2, what
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr  # no traceback
    assert lines[0].startswith(f"{path}: invalid: {expected}"), lines[0]


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_unwritable_photo_folder(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    path = _write_config(tmp_path, {"mission": f'photo_folder = "{locked / "photos"}"'})
    with pytest.raises(ConfigError, match=r"^mission\.photo_folder: .* cannot be created \(.* is not writable\)"):
        validate_for_run(load_config(path))


def test_run_refuses_with_the_same_line_and_makes_no_flight_folder(files: Path) -> None:
    path = _bad_config(files, {}, 'kind = "v4l2"')
    check = _check_config(str(path))
    run = subprocess.run([sys.executable, "-m", "companion.cli", "run", "--config", str(path)],
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == check.returncode == 2
    assert run.stderr.splitlines() == [check.stderr.strip().replace(f"{path}: invalid: ", "companion: error: ")]
    assert not (files / "flights").exists()


def test_offline_mode_checks_the_file_alone(files: Path) -> None:
    path = _bad_config(files, {}, 'kind = "v4l2"\ncalibration = "{tmp}/nope.yaml"')
    result = _check_config("--offline", str(path))
    assert result.returncode == 0
    assert result.stdout.splitlines()[1] == f"warning: camera.calibration: {files}/nope.yaml does not exist"


def test_relative_files_are_relative_to_the_config(files: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    path = _bad_config(files, {"rack": 'model = "rack.toml"'}, 'kind = "v4l2"\ncalibration = "camera.yaml"')
    (files / "rack.toml").write_text(RACK_TOML)
    elsewhere = tmp_path_factory.mktemp("cwd")
    result = subprocess.run([sys.executable, "-m", "companion.cli", "check-config", str(path)], cwd=elsewhere,
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    config = load_config(path)
    assert config.camera.calibration == str(files / "camera.yaml") and config.rack.model == str(files / "rack.toml")
    (files / "rack.toml").unlink()
    with pytest.raises(ConfigError, match=rf"^rack\.model: {files}/rack\.toml: file not found"):
        validate_for_run(load_config(path))
