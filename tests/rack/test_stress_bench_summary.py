"""`bench/rack_stress.py`: its per-cell summary (the errors along the rack's axes add up to the total) and its
tracking on one OpenCV thread."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest


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


def test_tracking_runs_opencv_on_one_thread_and_restores_its_pool() -> None:
    """The frames/s are claimed single-threaded: OpenCV's own pool (which OMP_NUM_THREADS does not reach) is set to
    one thread inside `one_thread()` and given back afterwards, also when the block raises."""
    bench = _bench()
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        with bench.one_thread():  # type: ignore[attr-defined]
            assert cv2.getNumThreads() == 1
        assert cv2.getNumThreads() == 2
        with pytest.raises(RuntimeError), bench.one_thread():  # type: ignore[attr-defined]
            raise RuntimeError("a failed run")
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(before)
