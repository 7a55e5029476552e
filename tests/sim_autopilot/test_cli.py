"""`companion fake-autopilot` argument handling (the server itself is exercised in sitl_tests)."""

from __future__ import annotations

import pytest

from companion.sim.autopilot.cli import build_parser, main


def test_parser_defaults_and_faults() -> None:
    args = build_parser().parse_args(["--listen", "tcpin:127.0.0.1:5760", "--fault", "gcs-loss@20:10"])
    assert args.profile == "ardupilot" and args.fault == ["gcs-loss@20:10"] and not args.gps


def test_bad_url_or_fault_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--listen", "serial:/dev/ttyS0:57600"]) == 2
    assert "listen URL" in capsys.readouterr().err
    assert main(["--listen", "udpin:127.0.0.1:0", "--fault", "meteor@3"]) == 2


def test_runs_and_stops_after_duration(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--listen", "udpin:127.0.0.1:0", "--profile", "px4", "--duration", "0.05"]) == 0
    out = capsys.readouterr().out
    assert "connect with udpout:127.0.0.1:" in out and "mode POSCTL" in out
