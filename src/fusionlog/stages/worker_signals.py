"""How a LocalCluster's worker processes start, as far as signals go: forked from this process
on Linux (`FORK`), spawned elsewhere, and in both cases without taking the user's Ctrl-C or
this process's SIGTERM/SIGHUP handlers with them (`forking`, `sigint_ignored`)."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import warnings
from collections.abc import Iterator
from typing import Any

#: How the LocalCluster's worker processes start. On Linux, forked from this process, which
#: has already imported numpy, Dask and fusionlog and often compiled the first plans: a worker
#: is up in ~0.05 s and ~0.03 s of CPU, against ~1 s and 0.4-0.6 s of CPU for a fresh
#: interpreter importing all of it (spawn, Dask's default, and elsewhere than Linux, where
#: fork is unsafe). The fork is made while the thread that starts the cluster waits in
#: Dask's LocalCluster and no other thread of ours works (`_forking`); the commands (`sweep`,
#: `run --workers`) are the callers, in a process of fusionlog's own: a program calling the
#: stages from threads of its own would have them copied mid-work too.
FORK = sys.platform.startswith("linux")


@contextlib.contextmanager
def sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the LocalCluster starts its worker processes, which inherit the
    ignored disposition (exec keeps SIG_IGN, and a Python that starts with SIGINT ignored
    raises no KeyboardInterrupt).

    Ctrl-C at a terminal sends SIGINT to every process of the foreground group, the workers
    too: each would die printing a KeyboardInterrupt traceback. Ignoring it in them leaves it
    to this process (the CLI's one line), which stops the workers by closing the cluster. The
    price: a Ctrl-C during the cluster's start-up (a second or two) is dropped. Blocking the
    signal instead would hold it, but the processes are started by threads of Dask's, and
    threads do not take the mask over from this one."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def forking() -> Iterator[None]:
    """While Dask forks our worker processes, and this thread waits for them.

    A signal for this process (Ctrl-C, SIGTERM, SIGHUP) is held until the workers are up and
    then delivered: closing a cluster whose nannies are half-way through starting makes Dask
    fail with errors of its own, where the user should see our one line. Each child starts
    with SIGINT ignored (a Ctrl-C at a terminal goes to the whole process group: the worker
    leaves it to this process, which closes the cluster) and SIGTERM/SIGHUP as a fresh
    interpreter has them (the CLI's handlers unwind this process's outputs, not a worker's).
    Python 3.12's warning about forking a process with threads is not shown: Dask's event loop
    is one, and the fork is made while the threads of ours wait
    (`distributed.DaskExecutor.__enter__`)."""
    if not FORK:
        with sigint_ignored():
            yield
        return
    global _HOOKED
    if not _HOOKED:
        os.register_at_fork(after_in_child=_child_signals)
        _HOOKED = True
    held: list[int] = []
    old: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in _HELD:
            old[sig] = signal.signal(sig, lambda signum, _frame: held.append(signum))
    _FORKING.set()
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*fork\(\)", category=DeprecationWarning)
            yield
    finally:
        _FORKING.clear()
        for sig, handler in old.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
    if held:
        signal.raise_signal(held[0])


#: The signals held while workers are forked (`forking`).
_HELD = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP) if FORK else ()
_FORKING = threading.Event()
_HOOKED = False


def _child_signals() -> None:
    """After a fork, in the child: a worker of ours gets its dispositions (`forking`); any
    other fork of this process is left alone."""
    if _FORKING.is_set():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        for sig in (signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_DFL)
