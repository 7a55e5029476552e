"""`bench/rack_stress.py`'s per-cell summary: the errors along the rack's axes add up to the total."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np


def _bench() -> object:
    path = Path(__file__).resolve().parents[2] / "bench" / "rack_stress.py"
    spec = importlib.util.spec_from_file_location("rack_stress_bench", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_axes_rms_compose_the_total_rms() -> None:
    bench = _bench()
    rng = np.random.default_rng(1427)
    results = []
    for _ in range(2):
        axes = [np.concatenate([rng.normal(0, [0.01, 0.02, 0.005]), np.radians(rng.normal(0, [0.3, 0.2, 0.05]))])
                for _ in range(50)]
        results.append({"perr": [float(np.linalg.norm(a[:3])) for a in axes],
                        "aerr": [float(np.degrees(np.linalg.norm(a[3:]))) for a in axes],
                        "axes_err": axes, "lost": 0, "t_ms": [5.0] * 50, "gap_err_100_cm": None})
    out = bench.summarize(results)  # type: ignore[attr-defined]
    xyz = np.array(out["rms_position_rack_xyz_cm"])
    rot = np.array(out["rms_rotation_rack_xyz_deg"])
    assert np.isclose(np.sqrt(np.sum(xyz**2)), out["rms_position_cm"])
    assert np.isclose(np.sqrt(np.sum(rot**2)), out["rms_orientation_deg"])
    assert xyz[1] > xyz[0] > xyz[2]  # the along-pipe axis carries the largest error here, by construction
    assert rot[0] > rot[1] > rot[2]
