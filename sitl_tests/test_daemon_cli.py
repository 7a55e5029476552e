"""The `companion` command line, the sim fault specs, the flight-folder writers and the report maths."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.daemon.flight import FlightFolder, read_tum
from companion.errors import InputError
from companion.geometry import se3
from companion.sim.report import SimRecord, build_report
from companion.sim.run import FaultSpec, parse_fault_spec, sim_config


@pytest.mark.parametrize(
    "argv",
    [[], ["bogus"], ["sim", "--fault", "nope@3"], ["sim", "--fault", "gcs-loss@x"], ["sim", "--autopilot", "inav"],
     ["mission"], ["mission", "validate"], ["run", "--config", "/nonexistent/companion.toml"]],
)
def test_bad_input_exits_2_with_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err and "\n" not in err and "Traceback" not in err


def test_mission_validate_and_check_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from companion.data import data_path

    assert main(["mission", "validate", str(data_path("missions/rack_sweep.xml"))]) == 0
    bad = tmp_path / "bad.xml"
    bad.write_text('<mission version="1" name="x" frame="ned"><takeoff height="lots"/></mission>')
    assert main(["mission", "validate", str(bad)]) == 2
    assert "bad.xml:1" in capsys.readouterr().err
    assert main(["check-config", str(data_path("sim_default.toml"))]) == 0
    broken = tmp_path / "c.toml"
    broken.write_text("[camera]\nfps = -3\n")
    assert main(["check-config", str(broken)]) == 2
    assert "camera.fps" in capsys.readouterr().err


def test_fault_specs() -> None:
    assert parse_fault_spec("gcs-loss@20:10") == FaultSpec("gcs-loss", 20.0, 10.0)
    assert parse_fault_spec("battery-sag@30s") == FaultSpec("battery-sag", 30.0, None)
    for bad in ("gcs-loss", "gcs-loss@-1", "gcs-loss@3:0", "warp@1", "ceiling@1:x"):
        with pytest.raises(InputError):
            parse_fault_spec(bad)


def test_packaged_sim_config_is_valid(tmp_path: Path) -> None:
    cfg = sim_config(tmp_path)
    assert cfg.camera.kind == "synthetic"
    assert Path(cfg.logging.flight_root).parent == tmp_path


def test_flight_folder_writers_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    folder = FlightFolder.create(tmp_path, lambda: 12.5, name="f")
    Ts = se3.exp(rng.normal(size=(5, 6)))
    for k, T in enumerate(Ts):
        folder.tum.write(100.0 + 0.1 * k, T)
    folder.log.event("hello", value=np.float64(1.5), arr=np.arange(3))
    folder.save_photo(np.zeros((4, 6), np.uint8), {"pose": Ts[0]})
    folder.close()
    stamps, T_read = read_tum(folder.path / "trajectory.tum")
    np.testing.assert_allclose(stamps, 100.0 + 0.1 * np.arange(5))
    np.testing.assert_allclose(T_read, Ts, atol=1e-6)
    rec = json.loads((folder.path / "log.jsonl").read_text().splitlines()[0])
    assert rec["event"] == "hello" and rec["arr"] == [0, 1, 2] and rec["t_s"] == 12.5
    assert json.loads((folder.path / "photos" / "photo-0001.json").read_text())["image"] == "photo-0001.png"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_report_figures() -> None:
    rec = SimRecord(start_s=0.0, end_s=10.0)
    t = np.linspace(0.0, 10.0, 101)
    for tk in t:
        rec.truth_stamps_s.append(float(tk))
        rec.truth_positions_ned_m.append(np.array([tk, 0.0, -1.0]))
        rec.truth_rotations.append(np.eye(3))
    for tk in t[::2]:
        rec.est_stamps_s.append(float(tk))
        rec.est_positions_ned_m.append(np.array([tk + 0.03, 0.04, -1.0]))
        rec.est_rotations.append(np.eye(3))
    rec.latencies_ms.extend([5.0] * 98 + [30.0, 60.0])
    rec.pose_message_stamps_s.extend(float(x) for x in t[::2])
    rep = build_report(rec)
    assert rep["estimation"]["rms_position_m"] == pytest.approx(0.05, abs=1e-9)
    assert rep["estimation"]["rms_orientation_deg"] == pytest.approx(0.0, abs=1e-6)
    assert rep["pose_messages"]["rate_hz"] == pytest.approx(5.0)
    assert rep["latency_ms"]["p50"] == pytest.approx(5.0)
    assert 30.0 <= rep["latency_ms"]["p99"] <= 60.0
    assert rep["mission"]["completed"] is False
