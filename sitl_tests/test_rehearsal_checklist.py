"""docs/deploy.md's rehearsal recipe and its checklist, followed literally from the command line against
`companion fake-autopilot` with the synthetic camera (issue #13 items 3 and the checklist acceptance).

Real processes on loopback in real time (the command line cannot share a fake clock): the test
waits on conditions with deadlines, never on fixed sleeps. Checklist step 2 (moving the drone by
hand) has no counterpart without hardware; step 3 (unplugging the camera) is covered by
sitl_tests/test_daemon_camera_api.py on the injected clock.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _companion(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion.cli", *args], capture_output=True, text=True,
                          timeout=60, cwd=cwd)


def _wait(cond: Callable[[], Any], timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s} s")
        time.sleep(0.2)


@pytest.fixture
def rehearsal(tmp_path: Path) -> Iterator[tuple[Path, list[str]]]:
    """The recipe's two processes, in a copy of the repository layout the rehearsal config refers to."""
    (tmp_path / "systemd").mkdir()
    (tmp_path / "companion").mkdir()
    os.symlink(REPO / "companion" / "data", tmp_path / "companion" / "data")
    udp, api = _free_udp_port(), _free_tcp_port()
    text = (REPO / "systemd" / "rehearsal.toml").read_text()
    text = text.replace("127.0.0.1:14551", f"127.0.0.1:{udp}").replace("port = 8765", f"port = {api}")
    (tmp_path / "systemd" / "rehearsal.toml").write_text(text)
    shutil.copytree(REPO / "missions", tmp_path / "missions")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with open(tmp_path / "fake.log", "wb") as fa_log, open(tmp_path / "run.log", "wb") as run_log:
        fake = subprocess.Popen([sys.executable, "-m", "companion.cli", "fake-autopilot", "--listen",
                                 f"udpin:127.0.0.1:{udp}", "--gcs-heartbeat"], cwd=tmp_path, stdout=fa_log,
                                stderr=subprocess.STDOUT, env=env)
        daemon = subprocess.Popen([sys.executable, "-m", "companion.cli", "run", "--config",
                                   "systemd/rehearsal.toml"], cwd=tmp_path, stdout=run_log,
                                  stderr=subprocess.STDOUT, env=env)
    try:
        yield tmp_path, ["--url", f"http://127.0.0.1:{api}"]
    finally:
        for p in (daemon, fake):
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10.0)
                except subprocess.TimeoutExpired:
                    p.kill()


def _status(cwd: Path, api: list[str]) -> dict[str, Any] | None:
    out = _companion("status", *api, "--json", cwd=cwd)
    return json.loads(out.stdout) if out.returncode == 0 else None


def test_the_deploy_checklist_against_the_fake_autopilot(rehearsal: tuple[Path, list[str]]) -> None:
    cwd, api = rehearsal
    # 1. check-config passes; status: camera streaming, estimator ok with the rack in view, autopilot heard
    ok = _companion("check-config", "systemd/rehearsal.toml", cwd=cwd)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    st = _wait(lambda: (s := _status(cwd, api)) and s["estimator"]["ok"]
               and s["estimator"]["capture_to_send_ms_p50"] is not None and s, 30.0, "estimator ok, poses sent")
    assert st["camera"]["state"] == "streaming" and st["link"]["health"] == "autopilot-ok"
    assert st["link"]["autopilot"] == "ardupilot" and st["estimator"]["source"] == "rack"
    assert st["estimator"]["capture_to_send_ms_p50"] is not None
    # 4. the mission against this vehicle's limits, with the configured ceiling
    valid = _companion("mission", "validate", "missions/examples/paper_sweep.xml", "--config",
                       "systemd/rehearsal.toml", cwd=cwd)
    assert valid.returncode == 0, valid.stdout + valid.stderr
    high = (cwd / "missions" / "high.xml")
    high.write_text((cwd / "missions/examples/paper_sweep.xml").read_text().replace('z="2.5"', 'z="9.5"'))
    refused = _companion("mission", "validate", str(high), "--config", "systemd/rehearsal.toml", cwd=cwd)
    assert refused.returncode == 2 and "ceiling" in (refused.stdout + refused.stderr).lower()
    # 5. upload, start, abort
    up = _companion("mission", "upload", "missions/examples/paper_sweep.xml", *api, cwd=cwd)
    assert up.returncode == 0, up.stdout + up.stderr
    start = _companion("mission", "start", "paper_sweep", *api, cwd=cwd)
    assert start.returncode == 0, start.stdout + start.stderr
    _wait(lambda: (s := _status(cwd, api)) and s["link"]["armed"] and s["mission"].get("done", 0) >= 1, 60.0,
          "take-off done")
    abort = _companion("mission", "abort", *api, cwd=cwd)
    assert abort.returncode == 0, abort.stdout + abort.stderr
    st = _wait(lambda: (s := _status(cwd, api)) and s["mission"]["state"] == "aborted" and s, 10.0, "aborted")
    _wait(lambda: (s := _status(cwd, api)) and s["link"]["mode"] == "BRAKE", 10.0, "holding in BRAKE")
    assert st["link"]["armed"]  # holding in the air, not dropped
