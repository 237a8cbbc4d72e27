"""How this process's C allocator treats freed memory: kept for reuse instead of handed back.

The per-run kernels and the metric sums allocate and free arrays of 0.1-30 MB at every step.
glibc serves those from fresh mmap()s (above its mmap threshold, 128 KiB at first) and returns
freed heap to the system (above its trim threshold), so the next array of the same size is
fresh pages again, each one a page fault on first touch: in the VMs these benchmarks ran on a
fault costs ~0.25-3 us, and the 20 % dropout example took as much system time (page faults)
as arithmetic (MSC: 16 000 faults, 0.11 s of system time against 0.13 s of user time per
estimate; 0 faults with the settings below). The peak memory does not grow: what is kept is
what the process already had.

Only processes fusionlog owns call this: the CLI (`fusionlog.cli`) and the Dask tasks
(`stages.montecarlo`), which run in worker processes of their own. The library itself never
changes a setting of the process that imports it. Elsewhere than glibc this does nothing.
"""

from __future__ import annotations

import ctypes
import sys

#: Allocations up to this size come from the heap, not a fresh mmap (glibc's upper limit).
MMAP_THRESHOLD = 32 << 20
#: Freed memory kept for reuse before any is handed back to the system.
TRIM_THRESHOLD = 256 << 20
#: One malloc arena for every thread. A Dask worker runs its tasks in a thread of its own, and
#: glibc gives each thread an arena of its own whose heaps shrink (pages handed back) as memory
#: is freed, whatever the trim threshold: a block of the paper's sweep took 34 000 page faults
#: in a thread against 17 500 in the main thread, and 5 % more time; with one arena, the same
#: as the main thread (benchmarks/README.md, issue 23). fusionlog's threads seldom allocate at
#: the same time, so the arena's lock costs nothing here.
ARENA_MAX = 1

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
_done = False


def keep_freed_memory() -> bool:
    """Set the thresholds above once per process; whether they are set (glibc only)."""
    global _done
    if _done or not sys.platform.startswith("linux"):
        return _done
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library the interpreter runs on
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    _done = all(
        mallopt(option, value)
        for option, value in (
            (_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
            (_M_TRIM_THRESHOLD, TRIM_THRESHOLD),
            (_M_ARENA_MAX, ARENA_MAX),
        )
    )
    return _done


def release_freed_memory() -> None:
    """Hand the heap's free memory back to the system now (glibc's ``malloc_trim``; nothing
    elsewhere), between the stages of a run. A long log's import and estimate free a few
    hundred MB of small objects (per-message Python objects, the MCAP writer's buffers) that
    the thresholds above keep for reuse, and the next stage's peak (the recording) would come
    on top of them: at 10^6 instants the stages' leftovers were ~300 MB of a 1.07 GiB peak."""
    if not sys.platform.startswith("linux"):
        return
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
        return
    trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
    trim(0)
