"""`bench/rack_gap_scan.py` runs from a fresh cache and prints one JSON object with a count per ground."""

import json
import subprocess
import sys
from pathlib import Path


def test_gap_scan_bench_prints_one_json_object(tmp_path: Path) -> None:
    script = Path(__file__).resolve().parents[2] / "bench" / "rack_gap_scan.py"
    out = subprocess.run([sys.executable, str(script), "--grounds", "concrete", "--seeds", "100:101",
                          "--cache", str(tmp_path)], capture_output=True, text=True, timeout=300, check=True)
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1
    report = json.loads(lines[0])
    concrete = report["grounds"]["concrete"]
    assert concrete["runs"] == 1 and concrete["within"] + len(concrete["misses"]) == 1
    assert list(tmp_path.glob("dev_wronggaps_concrete_100_1.pkl"))  # the frame was cached


def test_gap_scan_bench_refuses_an_empty_seed_range() -> None:
    script = Path(__file__).resolve().parents[2] / "bench" / "rack_gap_scan.py"
    out = subprocess.run([sys.executable, str(script), "--seeds", "5:5", "--cache", ""], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode != 0 and "--seeds" in out.stderr
