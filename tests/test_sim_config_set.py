"""`companion sim --set SECTION.KEY=VALUE`: parsing, merging, and the configuration's own checks."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from companion.cli import build_parser
from companion.errors import ConfigError
from companion.sim.config_set import merge_overrides, parse_config_sets
from companion.sim.ground_station import ground_station_overrides
from companion.sim.run import sim_config


def test_values_are_toml_and_bare_words_are_strings() -> None:
    got = parse_config_sets([
        "vision.rack_verify_start=report",
        "vision.rack_tracker.ground_points=0",
        "vision.rack_tracker.robust=\"paper\"",
        "vision.rack_tracker.along_pipe_widen_covariance=false",
        "safety.ceiling_m=5.5",
        "rack.translation_m=[0.0, -1.0, 1.0]",
    ])
    assert got == {
        "vision": {"rack_verify_start": "report",
                   "rack_tracker": {"ground_points": 0, "robust": "paper", "along_pipe_widen_covariance": False}},
        "safety": {"ceiling_m": 5.5},
        "rack": {"translation_m": [0.0, -1.0, 1.0]},
    }


@pytest.mark.parametrize("spec", ["novalue", "ceiling_m=5", ".x=1", "safety..x=1", "safety.x=[1,", "safety.x="])
def test_malformed_items_are_refused(spec: str) -> None:
    with pytest.raises(ConfigError, match="--set"):
        parse_config_sets([spec])


def test_a_value_and_a_table_at_the_same_name_are_refused() -> None:
    with pytest.raises(ConfigError, match="another --set"):
        parse_config_sets(["vision.rack_tracker=1", "vision.rack_tracker.ground_points=0"])
    with pytest.raises(ConfigError, match="another --set"):
        parse_config_sets(["vision.rack_tracker.ground_points=0", "vision.rack_tracker=1"])


def test_merge_keeps_both_sides_tables_and_modifies_neither() -> None:
    base = {"api": {"enabled": True, "port": 0}, "vision": {"rack_tracker": {"a": 1}}}
    extra = {"api": {"port": 9}, "vision": {"rack_tracker": {"b": 2}}}
    got = merge_overrides(base, extra)
    assert got == {"api": {"enabled": True, "port": 9}, "vision": {"rack_tracker": {"a": 1, "b": 2}}}
    assert base == {"api": {"enabled": True, "port": 0}, "vision": {"rack_tracker": {"a": 1}}}
    assert extra == {"api": {"port": 9}, "vision": {"rack_tracker": {"b": 2}}}


def test_the_sim_configuration_takes_the_sets_beside_the_ground_station_options(tmp_path: Path) -> None:
    args = build_parser().parse_args(["sim", "--no-video", "--set", "vision.rack_verify_start=report",
                                      "--set", "vision.rack_tracker.ground_points=0", "--set", "api.port=0"])
    overrides = merge_overrides(ground_station_overrides(args), parse_config_sets(args.set))
    cfg = sim_config(tmp_path, overrides)
    assert cfg.vision.rack_verify_start == "report"
    assert dict(cfg.vision.rack_tracker) == {"ground_points": 0}
    assert cfg.api.enabled and cfg.api.port == 0  # the ground station's table kept, one key replaced
    assert not cfg.video.enabled
    assert cfg.safety.ceiling_m == 8.0  # untouched sections keep the embedded defaults


def test_an_unknown_key_is_a_config_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"vision\.nosuchkey: unknown key"):
        sim_config(tmp_path, parse_config_sets(["vision.nosuchkey=1"]))


def test_the_command_line_exits_2_before_flying(tmp_path: Path) -> None:
    for spec, says in (("vision.nosuchkey=1", "vision.nosuchkey"), ("novalue", "SECTION.KEY=VALUE")):
        r = subprocess.run([sys.executable, "-m", "companion.cli", "sim", "--headless", "--no-video",
                            "--out", str(tmp_path / "out"), "--set", spec],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, r.stderr
        assert says in r.stderr
        assert not (tmp_path / "out" / "report.json").exists()
