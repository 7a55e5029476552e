"""`drivers.allocator.keep_freed_memory`: freed image buffers stay mapped for the next frame (glibc)."""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path

import pytest

from drivers.allocator import keep_freed_memory

# A vision loop's pattern: each "frame" allocates a few megabytes, touches them and frees them. Prints the
# minor page faults per frame after a warm-up (a fresh interpreter: the allocator's state is per process).
_LOOP = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from drivers.allocator import keep_freed_memory
    assert keep_freed_memory()
def frame():
    # the structure tensor of a 720x480 image (4 MB), two float32 images (1.4 MB each) and a pyramid's two
    # gradient planes: more than twice the largest block is free at once when they go
    a = np.ones((480, 720, 3), np.float32)
    b = np.ones((480, 720), np.float32)
    c = np.ones((480, 720), np.float32)
    d = np.ones((2, 502, 742), np.int16)
    return float(a[::97, ::89].sum() + b[::97, ::89].sum() + c[::97, ::89].sum() + d[:, ::97, ::89].sum())
for _ in range(5):
    frame()
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(40):
    frame()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0) / 40)
"""


def _faults_per_frame(mode: str) -> float:
    root = Path(__file__).resolve().parents[2]  # the repository: `drivers` importable from the fresh interpreter
    out = subprocess.run([sys.executable, "-c", _LOOP, mode], capture_output=True, text=True, check=True, cwd=root)
    return float(out.stdout.strip())


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_freed_buffers_are_reused_instead_of_mapped_again() -> None:
    plain = _faults_per_frame("plain")
    kept = _faults_per_frame("keep")
    # 8.3 MB per frame is ~2000 pages: mapped anew each frame by default, reused once kept.
    assert plain > 500
    assert kept < 0.1 * plain


def test_rejects_thresholds_out_of_range() -> None:
    for trim, mmap in ((0, 16), (32, 0), (32, 64)):
        with pytest.raises(ValueError):
            keep_freed_memory(trim, mmap)
