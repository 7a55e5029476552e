"""Keep the per-frame image buffers' memory in the process (glibc's heap trimming, tuned for a vision loop).

Each frame the rack tracker's OpenCV calls allocate and free a few megabytes of temporaries (the
structure tensor of the corner detector, 4 MB at 720x480; Lucas-Kanade's image pyramids). With
glibc's default, adaptive thresholds the top of the heap is handed back to the kernel as soon as
more than about twice the largest recent block is free, and mapped in again the next frame: about
330 minor page faults per frame on the 5-pipe throughput scene, some 4-8 % of the tracker's time
(`bench/rack_stress.py --throughput`, with and without `--plain-allocator`). Fixed thresholds
keep up to `trim_mib` of freed memory for reuse (37 faults per frame) at the cost of that much
resident memory at most; blocks under `mmap_mib` come from the heap.

Process-wide, so only the process's owner calls it (the daemon's command line, the benchmarks), never
a library module. A no-op returning False where the C library is not glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

_log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1  # mallopt parameters (glibc's malloc.h)
_M_MMAP_THRESHOLD = -3

TRIM_MIB = 32
MMAP_MIB = 16


def keep_freed_memory(trim_mib: int = TRIM_MIB, mmap_mib: int = MMAP_MIB) -> bool:
    """Set glibc's heap trim threshold to `trim_mib` and its mmap threshold to `mmap_mib` (MiB); True if both set.

    Both must be positive and `mmap_mib` at most 32 (glibc's ceiling for the mmap threshold on 64-bit). False
    when glibc refuses a value (a 32-bit build caps the mmap threshold at 512 KiB: the trim threshold is then
    set alone, which still halves the page faults) or the C library is not glibc.
    """
    if trim_mib <= 0 or not 0 < mmap_mib <= 32:
        raise ValueError(f"keep_freed_memory: need trim_mib > 0 and 0 < mmap_mib <= 32, got {trim_mib}, {mmap_mib}")
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        gnu_get_libc_version = libc.gnu_get_libc_version  # glibc only: musl has no such call
    except (OSError, AttributeError, TypeError):
        _log.debug("allocator: not glibc (%s), thresholds left as they are", name)
        return False
    gnu_get_libc_version.restype = ctypes.c_char_p
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    ok = bool(mallopt(_M_TRIM_THRESHOLD, trim_mib << 20)) and bool(mallopt(_M_MMAP_THRESHOLD, mmap_mib << 20))
    _log.log(logging.DEBUG if ok else logging.INFO, "allocator: glibc %s, trim %d MiB, mmap %d MiB: %s",
             gnu_get_libc_version().decode(), trim_mib, mmap_mib, "set" if ok else "refused")
    return ok
