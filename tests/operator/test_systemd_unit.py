"""The systemd unit: `systemd-analyze security --offline=true` at most 3.0 (OK), checked by .ci/verify_unit."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "systemd" / "companion.service"

pytestmark = pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                                reason="systemd-analyze not installed (apt-get install systemd)")


def _directives() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.lstrip().startswith(("#", "[")):
            key, value = line.split("=", 1)
            out.setdefault(key.strip(), []).append(value.strip())
    return out


def test_unit_has_the_hardening_rules() -> None:
    d = _directives()
    assert d["CapabilityBoundingSet"] == [""] and d["UMask"] == ["0027"]
    for key in ("ProtectClock", "ProtectKernelLogs", "RestrictNamespaces", "NoNewPrivileges"):
        assert d[key] == ["yes"], key
    assert d["ProtectProc"] == ["invisible"]
    assert "@system-service" in d["SystemCallFilter"] and "~@privileged @resources" in d["SystemCallFilter"]


def test_verify_unit_passes_and_reports_the_exposure() -> None:
    env = dict(os.environ, VIRTUAL_ENV=str(Path(sys.executable).parent.parent))
    result = subprocess.run(["bash", str(REPO / ".ci" / "verify_unit")], capture_output=True, text=True,
                            timeout=120, env=env, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    match = re.search(r"security exposure ([0-9.]+) \(at most 3\.0\)", result.stdout)
    assert match is not None and float(match.group(1)) <= 3.0


def test_verify_unit_fails_above_the_threshold() -> None:
    env = dict(os.environ, VIRTUAL_ENV=str(Path(sys.executable).parent.parent), COMPANION_MAX_EXPOSURE="0.5")
    result = subprocess.run(["bash", str(REPO / ".ci" / "verify_unit")], capture_output=True, text=True,
                            timeout=120, env=env, check=False)
    assert result.returncode == 1 and "is above 0.5" in result.stderr
