"""A LocalCluster started in the background while this process works on the first tasks.

Starting a LocalCluster takes half a second to two (importing Dask, ~0.45 s of CPU; its
scheduler; worker processes, each importing numpy, Dask and fusionlog where they are spawned),
during which its workers compute nothing. `WarmStartExecutor` starts the cluster in a thread
and meanwhile runs tasks from the front of the list in this process, one after the other;
from the moment the cluster is ready, the tasks not yet taken go to it.

Where the workers are forked (Linux, `distributed.FORK`), the thread starts only Dask's
scheduler; the worker processes are forked afterwards by this thread, between two tasks, while
it waits (`DaskExecutor.start_workers`): a fork copies the process as it is, and a task half
done (a lock held, a module half imported) must not be part of the copy.

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
        self._done_here = False
        self.description = "in this process while a LocalCluster starts"

    def __enter__(self) -> WarmStartExecutor:
        # Spawned worker processes must not see Ctrl-C (`distributed._sigint_ignored`, which
        # only the main thread can arrange): SIGINT is ignored until the cluster is up, as
        # when the cluster is started in the foreground. (Forked ones are started from here.)
        main = threading.current_thread() is threading.main_thread()
        if main and not self._cluster.defers_workers:
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

    @property
    def may_fork(self) -> bool:
        return self._cluster.may_fork and not self._done_here

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
        self._done_here = i == len(tasks)  # no worker needed: none will be forked
        if i < len(tasks):
            self._cluster.start_workers()  # between two tasks, here (see the module's note)
            self.workers = self._cluster.workers
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
