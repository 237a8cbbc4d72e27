"""Where the blocks of a sweep or a distributed run are computed: this process, or a Dask cluster
(``dask[distributed]``: a LocalCluster of worker processes, or a running scheduler).

Both executors take a list of tasks (a function of :mod:`.montecarlo` and its arguments) and
yield their results **in task order**, whatever order they finish in: the callers fold the
results as they come, so the merged metric sums are added in one fixed order and every number
of a sweep or a run is the same for any number of workers and any scheduler.

The Dask executor keeps at most a window of tasks submitted and not yet yielded (results that
finished early wait in that window), so the client holds a bounded number of results however
many blocks there are (10^7 runs are 200 blocks of the paper's example); on any exit that is
not the end (an error, Ctrl-C, SIGTERM raised as an exception by the CLI) it cancels the tasks
still on the cluster, and it closes the LocalCluster it started (never a cluster it connected
to). Dask is imported only here, and only when a cluster is used: ``import fusionlog.cli``
and runs in this process never load it.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from fusionlog.driver import JobPlans
from fusionlog.errors import FusionlogError

from .cluster import WorkerWatch, check_address, probe_scheduler
from .common import progress
from .worker_signals import FORK, forking

__all__ = ["DaskExecutor", "Executor", "LocalExecutor", "Task", "default_workers", "executor"]

#: A task: a module-level function (pickled by reference) and its arguments; the executor adds
#: the plan caches of the process that runs it (`plans=`, a `driver.JobPlans`: one for this
#: process, one on each Dask worker), so a job's blocks after the first do not recompile.
Task = tuple[Callable[..., Any], tuple[Any, ...]]
#: The name of the Dask worker plugin that keeps a worker's plan caches (`_WorkerPlans`).
PLANS_PLUGIN = "fusionlog-plans"

#: Tasks in flight per worker: one running, the next ones queued on it, so that a worker never
#: waits for the client between two tasks.
WINDOW_PER_WORKER = 3
#: Dask settings of the LocalCluster we start (its scheduler and nannies live in this
#: process): health checks of the event loops every second instead of every 20 ms, the
#: workers' memory every second instead of every 100 ms. On two cores with two workers, this
#: process's share of a core went from ~16 % to ~13 % (measured with psutil).
#:
#: And no MALLOC_TRIM_THRESHOLD_ in the workers' environment (Dask's nanny sets 64 KiB): with it,
#: glibc hands every freed block above 64 KiB back to the system and stops raising its mmap
#: threshold, so each block's multi-megabyte temporaries are fresh pages again, and in this
#: kind of VM a page fault costs more than the arithmetic done in the page. A sweep in this
#: process with that variable set spent 3-4x the system time (0.3 -> 1.1 s of 4 s of CPU).
_LOCAL_CONFIG = {
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.multiprocessing-method": "fork" if FORK else "spawn",
    "distributed.worker.profile.enabled": False,
}
#: Seconds to wait for a scheduler to answer, and for a cluster to have a worker.
CONNECT_TIMEOUT = 10
WORKER_TIMEOUT = 30


def default_workers() -> int:
    """The CPUs this process may use (the default of --workers)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class Executor:
    """Runs tasks and yields their results in task order; a context manager."""

    #: how many tasks run at once, and what runs them (printed by the commands)
    workers: int = 1
    description: str = "in this process"
    #: the plan caches of this process: its tasks' (`LocalExecutor`), and what the caller
    #: computes here itself (a distributed run's sample runs)
    plans: JobPlans

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def map(self, tasks: Sequence[Task], desc: str) -> Iterator[Any]:
        raise NotImplementedError

    def release(self) -> None:
        """No more tasks: start letting the workers go while the caller writes its outputs
        (``__exit__`` waits for it)."""


class LocalExecutor(Executor):
    """Every task in this process, one after the other (--workers 0; --exact-only by default)."""

    def __init__(self) -> None:
        self.plans = JobPlans()

    def map(self, tasks: Sequence[Task], desc: str) -> Iterator[Any]:
        for fn, args in progress(tasks, len(tasks), desc):
            yield fn(*args, plans=self.plans)


class DaskExecutor(Executor):
    """Tasks on a Dask cluster: a LocalCluster of `workers` processes (one thread each) on
    127.0.0.1, or the running scheduler at `scheduler` (its workers as they are)."""

    def __init__(
        self,
        workers: int | None = None,
        scheduler: str | None = None,
        timeout: float = CONNECT_TIMEOUT,
    ) -> None:
        self._n = workers
        self._address = scheduler
        self._timeout = timeout
        self._cluster: Any = None
        self._client: Any = None
        self._closing: threading.Thread | None = None
        self.plans = JobPlans()

    def __enter__(self) -> DaskExecutor:
        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError as e:  # pragma: no cover - a dependency, but say so plainly
            raise FusionlogError(
                f"Dask is not installed ({e}): pip install 'dask[distributed]'"
            ) from None
        try:
            if self._address is None:
                cpus = default_workers()
                n = min(self._n or cpus, cpus)
                # One thread per process: the blocks are numpy work that holds the GIL often,
                # and Dask's nanny already limits each worker's BLAS to one thread. The
                # constructor returns once the workers are up: forked ones, while this thread
                # waits in it (`worker_signals.forking`).
                with dask.config.set(_LOCAL_CONFIG), forking():
                    self._cluster = LocalCluster(
                        n_workers=n,
                        threads_per_worker=1,
                        processes=True,
                        host="127.0.0.1",
                        # the scheduler's HTTP server (its dashboard, which needs bokeh, and
                        # its metrics) on a free loopback port: without an address it takes
                        # 8787, and warns when another cluster has it
                        dashboard_address="127.0.0.1:0",
                        silence_logs=logging.CRITICAL,  # a failing task: our one line only
                    )
                self._client = Client(self._cluster, set_as_default=False)
                self.description = f"on a LocalCluster of {n} worker process{'es' * (n != 1)}"
                if self._n is not None and self._n > n:
                    # more processes than CPUs only compete for them (and each one's
                    # heartbeats time out): capped, and said where the executor is printed
                    self.description += f" (--workers {self._n} capped at the {n} CPUs)"
            else:
                self._client = self._connect(Client, self._address, self._timeout)
            self._client.register_plugin(_worker_plans(), name=PLANS_PLUGIN)
            self.workers = self._wait_for_workers()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    @staticmethod
    def _connect(client_cls: Any, address: str, timeout: float) -> Any:
        # a quiet client: a scheduler going away (at the end, or killed) must not print
        # warnings and tracebacks of its own around our line
        _quiet_dask()
        # what answers there is a scheduler, asked before a Client exists: a Client that
        # fails to connect prints Dask's Client.__del__ traceback when it is collected
        probe_scheduler(address, timeout)
        try:
            return client_cls(address, timeout=timeout, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as e:
            raise FusionlogError(
                f"--scheduler {address}: cannot connect to a Dask scheduler ({_reason(e)})"
            ) from None

    def _wait_for_workers(self) -> int:
        wait = WORKER_TIMEOUT if self._address is None else self._timeout
        try:
            self._client.wait_for_workers(1, timeout=wait)
        except (TimeoutError, OSError) as e:
            raise FusionlogError(
                f"{self._address or 'LocalCluster'}: no Dask worker joined within "
                f"{wait:g} s ({_reason(e)})"
            ) from None
        info = self._client.scheduler_info(n_workers=-1)["workers"]
        threads = sum(int(w.get("nthreads", 1)) for w in info.values()) or 1
        if self._address is not None:
            self.description = (
                f"on the Dask scheduler at {self._address} ({len(info)} workers, {threads} threads)"
            )
        return threads

    def release(self) -> None:
        # Closing a LocalCluster waits a second or so for its processes to exit: that wait
        # runs beside the caller's writing of its outputs instead of after it.
        if self._closing is None and (self._client is not None or self._cluster is not None):
            self._closing = threading.Thread(target=self._close, name="fusionlog: close Dask")
            self._closing.start()

    def __exit__(self, *exc: object) -> None:
        if self._closing is None:
            self._close()
        else:
            self._closing.join()
            self._closing = None

    def _close(self) -> None:
        client, cluster = self._client, self._cluster
        self._client = self._cluster = None
        try:
            if client is not None:
                with contextlib.suppress(Exception):  # a scheduler already gone: nothing to close
                    client.close(timeout=self._timeout)
        finally:
            if cluster is not None:
                cluster.close(timeout=CONNECT_TIMEOUT)

    def map(self, tasks: Sequence[Task], desc: str) -> Iterator[Any]:
        # The first window is submitted now, not at the first next(): the caller may compute
        # something of its own meanwhile (distributed run: the sample runs).
        where = f"--scheduler {self._address}" if self._address else "LocalCluster"
        watch = WorkerWatch(self._client, where, self._timeout if self._address else WORKER_TIMEOUT)
        window = max(2, WINDOW_PER_WORKER * self.workers)
        return _OrderedResults(self._client, tasks, desc, window, watch)


class _OrderedResults:
    """Results of tasks on a Dask client in task order, at most `window` tasks submitted and
    not yet yielded; close() (or an error while waiting) cancels what is still running."""

    def __init__(
        self, client: Any, tasks: Sequence[Task], desc: str, window: int, watch: WorkerWatch
    ) -> None:
        from distributed import as_completed

        self._client, self._tasks, self._window, self._watch = client, tasks, window, watch
        self._futures: dict[int, Any] = {}
        self._index: dict[str, int] = {}
        self._done: dict[int, Any] = {}
        self._submitted = self._yielded = 0
        self._pending = as_completed(loop=client.loop)
        self._submit_more()
        self._completed = iter(progress(self._pending, len(tasks), desc))

    def _submit_more(self) -> None:
        while self._submitted < len(self._tasks) and self._submitted - self._yielded < self._window:
            fn, args = self._tasks[self._submitted]
            fut = self._client.submit(on_worker, fn, *args, pure=False)
            self._futures[self._submitted] = fut
            self._index[fut.key] = self._submitted
            self._pending.add(fut)
            self._submitted += 1

    def __iter__(self) -> _OrderedResults:
        return self

    def __next__(self) -> Any:
        if self._yielded >= len(self._tasks):
            raise StopIteration
        try:
            while self._yielded not in self._done:
                # as_completed has no timeout: wait here, where the cluster can be watched
                while not self._pending.has_ready():
                    self._watch.check()
                    time.sleep(0.005)  # a result is seldom late by more than this
                fut = next(self._completed)
                i = self._index.pop(fut.key)
                self._done[i] = _result(fut, self._tasks[i], self._watch.where)
                del self._futures[i]
                fut.release()
        except BaseException:  # a failed task, Ctrl-C, SIGTERM: stop the others too
            self.close()
            raise
        result = self._done.pop(self._yielded)
        self._yielded += 1
        self._submit_more()
        return result

    def close(self) -> None:
        """Cancel every task still submitted (nothing of ours keeps running on the cluster)."""
        if self._futures:
            futures = list(self._futures.values())
            self._futures.clear()
            self._client.cancel(futures)


def on_worker(fn: Callable[..., Any], *args: Any) -> Any:
    """A task on a Dask worker, given that worker's plan caches (`Task`)."""
    from distributed import get_worker

    return fn(*args, plans=get_worker().plugins[PLANS_PLUGIN].plans)


def _worker_plans() -> Any:
    """The worker plugin that gives each Dask worker a `JobPlans` of its own (a class made
    here: Dask is imported only when a cluster is used)."""
    from distributed import WorkerPlugin

    class _WorkerPlans(WorkerPlugin):
        def setup(self, worker: Any) -> None:
            self.plans = JobPlans()

    return _WorkerPlans()


def _reason(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _quiet_dask() -> None:
    """Dask's loggers (its config gives several their own level) silent below CRITICAL."""
    for name in ["distributed", *logging.root.manager.loggerDict]:
        if name == "distributed" or name.startswith("distributed."):
            logging.getLogger(name).setLevel(logging.CRITICAL)


def _result(fut: Any, task: Task, where: str) -> Any:
    """A finished task's result; a worker's failure as one line (a FusionlogError from the
    task stays what it is: a numerical error names the architecture and the step)."""
    from distributed.comm import CommClosedError

    try:
        return fut.result()
    except FusionlogError:
        raise
    except (CommClosedError, concurrent.futures.CancelledError) as e:  # the scheduler went away
        why = "scheduler-connection-lost" if "scheduler-connection-lost" in str(e) else _reason(e)
        raise FusionlogError(
            f"{where}: lost the connection to the Dask scheduler ({why}); nothing was written"
        ) from None
    except ImportError as e:
        raise FusionlogError(
            f"a Dask worker cannot run fusionlog ({_reason(e)}): install fusionlog, the same "
            "version, where the workers run"
        ) from None
    except Exception as e:
        from distributed import KilledWorker

        if isinstance(e, KilledWorker):
            raise FusionlogError(
                f"Dask workers died running {task[0].__name__} (out of memory?): {_reason(e)}"
            ) from None
        raise


def executor(
    workers: int | None,
    scheduler: str | None,
    *,
    local_default: bool = False,
    timeout: float = CONNECT_TIMEOUT,
) -> Executor:
    """The executor the options ask for: ``scheduler`` a running cluster; ``workers`` 0 this
    process, N a LocalCluster of N processes; neither: a LocalCluster of one process per CPU,
    or this process when `local_default` (work too small to be worth starting a cluster). A
    LocalCluster starts in the foreground: forked workers (Linux) are up a few tenths of a second
    after Dask's import; spawned workers (elsewhere) take a second or two, during which nothing
    is computed (a warm start that computed here meanwhile was deleted: benchmarks/README.md
    "Fast paths", no gain measured)."""
    if workers is not None and scheduler is not None:
        raise FusionlogError("--workers and --scheduler: give one of them, not both")
    if workers is not None and workers < 0:
        raise FusionlogError(f"--workers: must be >= 0, got {workers}")
    if not 0 < timeout < math.inf:  # Dask's connect takes no infinite timeout (nor NaN)
        raise FusionlogError(
            f"--scheduler-timeout: must be a finite number > 0 of seconds, got {timeout:g}"
        )
    if scheduler is not None:
        return DaskExecutor(scheduler=check_address(scheduler), timeout=timeout)
    if workers == 0 or (workers is None and local_default):
        return LocalExecutor()
    return DaskExecutor(workers=workers)
