"""Keep freed large arrays in the process for reuse instead of handing them back to the OS.

A step's volumes are megabytes each (a (3, 128, 128, 48) float32 flow is 9.4 MB). glibc's malloc maps
each such block fresh and unmaps it on free, so every array of every step is page-faulted in again, 4 kB
at a time: measured, that was 27% of `dsr-bench evaluate`'s time per sequence (0.208 s -> 0.150 s,
`python bench/bench_evaluate.py`). Raising the mmap and trim thresholds makes freed blocks stay in the
heap, so the next step's arrays of the same sizes reuse pages already mapped. The cost is memory the
process keeps until it exits (at most its peak). Called where it was measured to pay and the process is
dsr-bench's own: `dsr-bench evaluate`, and the worker processes of evaluate, validate and generate
(`dsr_bench.parallel`, `dsr_bench.engines`); not in a library call, whose process is the user's. Without
glibc (macOS, musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import functools

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
#: blocks up to this size come from the heap (glibc's upper limit for the mmap threshold on 64-bit)
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
#: free memory at the heap's top kept before any is given back
TRIM_THRESHOLD_BYTES = 512 * 1024 * 1024


@functools.cache
def keep_freed_memory() -> bool:
    """Set glibc's malloc to keep freed blocks up to 32 MB for reuse; True if it took (glibc), else False.
    Idempotent; the setting is process-wide."""
    try:
        libc = ctypes.CDLL(None)  # the process itself: libc's symbols where it is glibc
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    kept = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    return bool(kept) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
