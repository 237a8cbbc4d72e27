"""A LocalCluster started in the background while this process works on the first tasks
(where its workers are spawned: elsewhere than Linux, `worker_signals.FORK`; forked workers are
up a few tenths of a second after Dask's import, which would not overlap with work here, both
holding the GIL).

Starting a LocalCluster takes a second or two (worker processes spawned, each importing numpy,
Dask and fusionlog), during which its workers compute nothing. `WarmStartExecutor` starts the
cluster in a thread and meanwhile runs tasks from the front of the list in this process, one
after the other; from the moment the cluster has a worker, the tasks not yet taken go to it.
The start-up is then no longer time in which nothing is computed (with a core free, a sweep
on one worker should cost about what it costs in this process; the busy machine of
benchmarks/README.md could not confirm it).

The results still come in task order and are the same numbers: a task is the same function
of its arguments here and in a worker (BLAS on one thread in both, `stages.montecarlo`).
Tasks taken here are run to the end; those handed to the cluster never run here.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator, Sequence
from typing import Any

from .distributed import DaskExecutor, Executor, Task


class WarmStartExecutor(Executor):
    """`cluster` (a LocalCluster's DaskExecutor, not yet entered) started in a thread; this
    process runs tasks until it is ready."""

    def __init__(self, cluster: DaskExecutor) -> None:
        self._cluster = cluster
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._entered = False
        self._thread: threading.Thread | None = None
        self._old_sigint: Any = None
        self.description = "in this process while a LocalCluster starts"

    def __enter__(self) -> WarmStartExecutor:
        # The worker processes must not see Ctrl-C (`worker_signals.sigint_ignored`, which only
        # the main thread can arrange): SIGINT is ignored until the cluster is up, as when
        # the cluster is started in the foreground.
        if threading.current_thread() is threading.main_thread():
            self._old_sigint = signal.signal(signal.SIGINT, signal.SIG_IGN)
        self._thread = threading.Thread(target=self._start, name="fusionlog: LocalCluster")
        self._thread.start()
        return self

    def _start(self) -> None:
        try:
            self._cluster.__enter__()
            self._entered = True
        except BaseException as e:  # reported by map or __exit__, in the main thread
            self._error = e
        finally:
            with self._lock:
                self._ready.set()

    def _wait(self) -> None:
        """Wait for the start; restore SIGINT; raise what the start raised."""
        self._ready.wait()
        if self._old_sigint is not None:
            signal.signal(signal.SIGINT, self._old_sigint)
            self._old_sigint = None
        if self._error is not None:
            error, self._error = self._error, None
            raise error
        self.workers = self._cluster.workers
        self.description = self._cluster.description

    def map(self, tasks: Sequence[Task], desc: str) -> Iterator[Any]:
        i = 0
        while i < len(tasks):
            with self._lock:  # a task is taken here only while the cluster is not ready
                if self._ready.is_set():
                    break
            fn, args = tasks[i]
            yield fn(*args)
            i += 1
        self._wait()
        if i:
            self.description += f" (the first {i} of {len(tasks)} tasks here while it started)"
        if i < len(tasks):
            yield from self._cluster.map(tasks[i:], desc)

    def release(self) -> None:
        if self._entered:
            self._cluster.release()

    def __exit__(self, *exc: object) -> None:
        if self._thread is not None:
            self._thread.join()  # a cluster being started is closed, not left behind
            self._thread = None
        if self._old_sigint is not None:
            signal.signal(signal.SIGINT, self._old_sigint)
            self._old_sigint = None
        if self._entered:
            self._cluster.__exit__(*exc)
