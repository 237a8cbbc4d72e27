"""How this process's C allocator treats freed memory: kept for reuse instead of handed back;
OpenBLAS's threads, which this process does not start (`one_blas_thread`); and its objects at
exit, which the collector does not visit again (`leave_objects_at_exit`).

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

import atexit
import ctypes
import gc
import os
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
_leave_at_exit = False


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


def one_blas_thread() -> bool:
    """No threads of OpenBLAS's own (numpy's BLAS) unless the user asked for some
    (OPENBLAS_NUM_THREADS): fusionlog's arithmetic is elementwise over the runs and products of
    small matrices, which OpenBLAS computes on the calling thread anyway (the numbers are the
    same), while each thread it starts with numpy's import spins ~0.1 s of a CPU waiting for
    work: on a shared 2-CPU machine, time taken from the command itself (`fusionlog estimate`
    of 10^4 radar runs: 0.40 s of CPU instead of 0.49). Child processes (Dask workers) inherit
    it. Effective only before numpy is imported; whether it was."""
    if "numpy" in sys.modules:
        return False
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    return True


def leave_objects_at_exit() -> None:
    """When the process exits, its objects are left to the system rather than collected: the
    interpreter's last collections pass over every object the imports made (numpy, click,
    mcap, fusionlog's modules: ~20 ms of a 0.4 s `fusionlog estimate`), and Python does not
    promise finalisers for objects alive at exit anyway. gc.freeze() runs as an atexit
    handler, after those registered later (Dask's, multiprocessing's); the outputs are
    committed and closed by then. Registered once per process."""
    global _leave_at_exit
    if not _leave_at_exit:
        atexit.register(gc.freeze)
        _leave_at_exit = True


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
