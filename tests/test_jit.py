"""Optional compiled kernels (`companion/jit.py`, `companion/camera_jit.py`): the pinhole projection against
the numpy code, the switch, the fallback when compilation fails, and the background compilation that never
makes a caller wait."""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np
import pytest

from companion import camera_jit, jit
from companion.camera import PinholeCamera

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=625.0, cx=361.5, cy=239.25, skew=0.3)
needs_numba = pytest.mark.skipif(camera_jit.kernels() is None, reason="numba not available here")


@needs_numba
def test_pinhole_kernel_matches_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(0)
    p = rng.normal(0.0, 1.0, (500, 3))
    p[:, 2] += 1.5  # most in front, some behind the camera (NaN rows)
    uv, J = CAM.project_with_jacobian(p)
    uv1 = CAM.project(p[7])
    monkeypatch.setattr(jit, "_compiled", {"camera.pinhole": None})
    uv_np, J_np = CAM.project_with_jacobian(p)
    np.testing.assert_array_equal(uv, uv_np)
    np.testing.assert_array_equal(J, J_np)
    np.testing.assert_array_equal(uv1, CAM.project(p[7]))
    assert np.isnan(uv[p[:, 2] <= 0]).all() and np.isfinite(uv[p[:, 2] > 0]).all()


def test_a_failing_compilation_leaves_numpy_in_charge(monkeypatch: pytest.MonkeyPatch,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setattr(jit, "_compiled", {})

    def build(njit: object) -> object:
        raise RuntimeError("no locator available for the cache")

    with caplog.at_level(logging.WARNING, logger="companion.jit"):
        assert jit.compile_kernels("test.failing", build, lambda k: None) is None
    assert "no locator available" in caplog.text
    calls = []
    assert jit.compile_kernels("test.failing", lambda njit: calls.append(1), lambda k: None) is None
    assert calls == []  # tried once per process


def test_switched_off_by_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(jit, "_compiled", {})
    monkeypatch.setenv("COMPANION_JIT", "0")
    built = []
    assert jit.compile_kernels("test.off", lambda njit: built.append(1), lambda k: None) is None
    assert built == [] and jit.compile_in_background() is None


def test_background_compilation_never_makes_a_caller_wait(monkeypatch: pytest.MonkeyPatch) -> None:
    """While the background thread compiles, other threads get None at once (and run numpy); afterwards the
    kernels. The slow `build` here stands for numba's compilation."""
    monkeypatch.setattr(jit, "_compiled", {})
    monkeypatch.setattr(jit, "_background", None)
    monkeypatch.setattr(jit, "_ready", set())
    release = threading.Event()
    started = threading.Event()

    def build(njit: object) -> str:
        started.set()
        assert release.wait(10.0)
        return "kernels"

    def getter() -> object:
        return jit.compile_kernels("test.slow", build, lambda k: None)

    monkeypatch.setattr(jit, "_getters", [getter])
    children: list[list[str]] = []
    monkeypatch.setattr(jit, "_compile_in_child", lambda modules: children.append(modules) or True)
    thread = jit.compile_in_background()
    assert thread is not None and started.wait(10.0)
    assert getter() is None  # not blocked on the lock: numpy meanwhile
    release.set()
    thread.join(10.0)
    assert not thread.is_alive()
    assert children == [[__name__]]  # the child process was asked for the getter's module first
    assert jit.compile_in_background() is None and len(children) == 1  # started again: nothing left to do
    assert getter() == "kernels"


@needs_numba
def test_no_writable_cache_still_compiles(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """numba refuses `cache=True` when no cache directory is writable (a read-only install without
    NUMBA_CACHE_DIR): the kernels are then compiled without a cache, not dropped."""
    import numba.core.caching

    monkeypatch.setattr(numba.core.caching.CacheImpl, "_locator_classes", [])
    monkeypatch.setattr(jit, "_compiled", {})

    def twice(x: float) -> float:
        return 2.0 * x

    with caplog.at_level(logging.WARNING, logger="companion.jit"):
        ks = jit.compile_kernels("test.uncached", lambda njit: njit(twice), lambda k: None)
    assert ks is not None and ks(1.5) == 3.0
    assert "not cached" in caplog.text


@needs_numba
def test_the_child_process_compiles_into_the_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`compile_in_background` has a child process compile (numba's compiler holds the GIL, which would starve
    the daemon's event loop); the child writes the cache this process then loads from."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert jit._compile_in_child(["companion.camera_jit"])
    cached = [p.name for p in tmp_path.rglob("*.nbi")]
    assert any(name.startswith("camera_jit.") for name in cached), cached


def test_a_failing_child_is_reported(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="companion.jit"):
        assert not jit._compile_in_child(["companion.no_such_module"])
    assert "exited 1" in caplog.text and "No module named" in caplog.text
