"""Optional compiled kernels (numba), loaded once per process, with each caller's numpy code as fallback.

The per-frame tracking code is vectorised numpy, and on its small arrays (a few hundred samples) most of
its time is numpy's per-call overhead rather than arithmetic. A few hot loops are therefore also written
as plain per-element Python loops and compiled with numba (`companion/vision/rack/rack_jit.py`,
`companion/vision/rack/limbs_jit.py`, `companion/vision/rack/ground_height_jit.py`,
`companion/vision/rack/corners_jit.py`, `companion/camera_jit.py`). Each does the same arithmetic in the same
floating-point types and order as the numpy code it replaces, so that both give the same results (their
tests compare them; `bench/rack_stress.py --throughput` measures the speed).

numba is optional at run time: where it is not installed (no wheel for the platform), cannot compile, or
`COMPANION_JIT=0` is set in the environment, `compile_kernels` returns None and the callers keep their
numpy code. Compiled code is cached beside the module that defines it, or in numba's per-user cache (or
`NUMBA_CACHE_DIR`) when that directory is read-only, so only the first process after an install pays the
compilation (about ten seconds on this project's 2-core x86 VM, longer on a Raspberry Pi).

A flight process must not stall its vision loop on that compilation: `compile_in_background()` (called by
the daemon at start) gets every registered kernel set in a thread, and until it is done the callers get
None and run numpy (the same results, slower). numba's compiler is Python code holding the GIL, so a
compilation in that thread would still starve the event loop (heartbeats, the link: a cold cache cost the
daemon its autopilot link for 3 s and most of its frames); the thread therefore first has a child process
(`python -m companion.jit MODULE...`) compile and cache the kernels, waiting on it without the GIL, and
then only loads them from the cache (under a second).
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import os
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any, TypeVar

_log = logging.getLogger(__name__)

K = TypeVar("K")

_compiled: dict[str, Any] = {}  # name -> kernels, or None when unavailable (final either way)
_lock = threading.Lock()
_getters: list[Callable[[], Any]] = []
_ready: set[Callable[[], Any]] = set()  # getters `compile_in_background` has seen through (no second child)
_background: threading.Thread | None = None


def jit_enabled() -> bool:
    """False when the environment variable `COMPANION_JIT` is "0" (run the numpy code everywhere)."""
    return os.environ.get("COMPANION_JIT", "1") != "0"


def register(getter: Callable[[], Any]) -> None:
    """Register a module's kernel getter (its `kernels()`) for `compile_in_background`."""
    if getter not in _getters:
        _getters.append(getter)


def compile_kernels(name: str, build: Callable[[Callable[[Any], Any]], K], warm_up: Callable[[K], None]) -> K | None:
    """The kernels `name`, built on the first call by `build(njit)` (njit compiles one Python function) and
    compiled or loaded from the cache by `warm_up(kernels)`; None (logged once) when numba is missing or fails,
    when the JIT is disabled, or, in other threads, while `compile_in_background` is still at work."""
    if name in _compiled:
        return _compiled[name]  # type: ignore[no-any-return]
    bg = _background
    if bg is not None and bg.is_alive() and threading.current_thread() is not bg:
        return None  # being compiled in the background: numpy meanwhile, never a stall
    with _lock:
        if name in _compiled:
            return _compiled[name]  # type: ignore[no-any-return]
        kernels: K | None = None
        if jit_enabled():
            try:
                import numba

                warned: list[bool] = []

                def njit(f: Any) -> Any:
                    try:
                        return numba.njit(cache=True, nogil=True)(f)
                    except RuntimeError as exc:  # numba found no writable cache directory
                        if not warned:
                            warned.append(True)
                            _log.warning("kernels %r not cached (%s): compiled in every process; set "
                                         "NUMBA_CACHE_DIR to a writable directory", name, exc)
                        return numba.njit(nogil=True)(f)

                built = build(njit)
                warm_up(built)
                kernels = built
            except Exception as exc:  # any failure to import or compile leaves the numpy code in charge
                _log.warning("compiled kernels %r unavailable (%s: %s); using numpy", name, type(exc).__name__, exc)
        _compiled[name] = kernels
        return kernels


def compile_in_background() -> threading.Thread | None:
    """Compile (or load) every registered kernel set in a daemon thread; None when there is nothing to do (the JIT
    off, or every kernel set already got by an earlier call in this process: a daemon started again, a test)."""
    global _background
    getters = [g for g in _getters if g not in _ready]
    if not jit_enabled() or not getters or (_background is not None and _background.is_alive()):
        return None

    def run() -> None:
        if importlib.util.find_spec("numba") is not None:  # without numba there is nothing for a child to compile
            _compile_in_child(sorted({g.__module__ for g in getters}))
        for getter in getters:
            getter()  # loaded from the cache the child wrote (or compiled here when it could not)
            _ready.add(getter)
        _log.info("compiled kernels ready: %s", ", ".join(compiled_names()) or "none")

    _background = threading.Thread(target=run, name="jit-compile", daemon=True)
    _background.start()
    return _background


def _compile_in_child(modules: list[str], timeout_s: float = 600.0) -> bool:
    """Compile and cache the kernels of `modules` in a child process; True when it succeeded. A failure
    (no numba, no writable cache, a crash) is only logged: the caller then compiles in its own process."""
    try:
        done = subprocess.run([sys.executable, "-m", "companion.jit", *modules], capture_output=True, text=True,
                              timeout=timeout_s, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        _log.warning("kernel compilation in a child process failed (%s); compiling in this one", exc)
        return False
    if done.returncode != 0:
        _log.warning("kernel compilation in a child process exited %d (%s); compiling in this one",
                     done.returncode, done.stderr.strip().splitlines()[-1:] or "no message")
        return False
    return True


def compile_modules(modules: list[str]) -> list[str]:
    """Import `modules` and get every kernel set they register (compiled and cached); the names compiled."""
    for name in modules:
        importlib.import_module(name)
    for getter in list(_getters):
        getter()
    return compiled_names()


def compiled_names() -> list[str]:
    """The kernel sets compiled (or loaded) in this process so far, sorted (benchmarks report them)."""
    return sorted(n for n, k in _compiled.items() if k is not None)


def forget_compiled() -> None:
    """Forget every kernel set, so that the next `compile_kernels` re-reads `COMPANION_JIT` (tests)."""
    with _lock:
        _compiled.clear()
        _ready.clear()


if __name__ == "__main__":  # the child of `compile_in_background`
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from companion import jit as _registry  # the modules register with the imported module, not __main__

    names = _registry.compile_modules(sys.argv[1:])
    print("compiled:", ", ".join(names) or "none")
