"""glibc malloc settings for processes that allocate and free multi-MB blocks over and over (frame tasks,
training steps): blocks up to 1 GiB come from the heap and up to 1 GiB of free heap is kept, so a freed block is
the next one's memory instead of a fresh mapping that page-faults on first touch.

With glibc's defaults every block above the (dynamic, at most 32 MiB) mmap threshold is mapped afresh, and dask's
own MALLOC_TRIM_THRESHOLD_=64 KiB freezes that threshold at 128 KiB in its workers: on the AMD EPYC VM that was ~20% more CPU per raw frame in preprocess and, in a `fast` training step, a 30 ms zeroing
of its 67 MB table gradient (docs/benchmarks.md). Peak memory is unchanged: the freed block is reused.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

MMAP_THRESHOLD = 1 << 30
TRIM_THRESHOLD = 1 << 30
# for processes started with them (dask workers, through `pre-spawn-environ`): one arena too, since tasks run in
# a worker thread whose own arena cannot hold such blocks and maps them afresh
WORKER_MALLOC_ENV = {
    "MALLOC_ARENA_MAX": "1",
    "MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD),
    "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD),
}
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters


@functools.cache
def _libc() -> ctypes.CDLL | None:
    """This process's C library, or None where it cannot be loaded."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c"))
    except (OSError, TypeError):
        return None


@functools.cache
def keep_large_blocks() -> bool:
    """Apply the thresholds to this running process (glibc's `mallopt`); False where there is no glibc."""
    mallopt = getattr(_libc(), "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    mmap_set = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    return bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)) and mmap_set


def release_free_heap() -> bool:
    """Give the heap's free memory back to the system now (glibc's `malloc_trim(0)`); False where there is no
    glibc. For a process under the thresholds above that stops allocating its large blocks: without it, up to
    1 GiB of freed blocks stays resident for the rest of the process (a worker whose decoder probe decoded whole
    frames, then kept the banded decoder: ~270 MB, docs/benchmarks.md)."""
    trim = getattr(_libc(), "malloc_trim", None)
    if trim is None:
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True
