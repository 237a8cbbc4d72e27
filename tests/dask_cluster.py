"""A real Dask cluster on loopback for the tests: `dask scheduler` and two `dask worker`
processes (one thread, no nanny, so a killed worker stays dead), started as the docs say and
stopped by their process ids within bounded time."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

DASK = Path(sys.executable).parent / "dask"
ENV = {**os.environ, "RERUN_ANALYTICS": "0"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop(procs: list[subprocess.Popen], sig_kill: bool = False) -> None:
    """SIGTERM (or SIGKILL) every process still running, then wait for all within ~10 s."""
    for p in procs:
        if p.poll() is None:
            p.kill() if sig_kill else p.terminate()
    deadline = time.monotonic() + 10
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=5)


@contextlib.contextmanager
def loopback_cluster(
    log_dir: Path, *, sig_kill: bool = False
) -> Iterator[tuple[str, subprocess.Popen, list[subprocess.Popen]]]:
    """(address, scheduler process, worker processes) of a cluster whose two workers have
    joined; each process logs to its own file in `log_dir`. Skips the test without the
    `dask` console script; fails it (with the logs' tails) if the cluster does not start."""
    if not DASK.exists():
        pytest.skip("the dask console script is missing")
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs: list[subprocess.Popen] = []
    logs: list = []

    def start(name: str, *args: str) -> subprocess.Popen:
        out = open(log_dir / f"{name}.log", "wb")  # noqa: SIM115 - closed after the processes
        logs.append(out)
        procs.append(subprocess.Popen([str(DASK), *args], stdout=out, stderr=out, env=ENV))
        return procs[-1]

    try:
        sched = start(
            "scheduler", "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"
        )
        workers = [
            start(
                f"worker{i}",
                "worker",
                address,
                "--nthreads",
                "1",
                "--no-nanny",
                "--host",
                "127.0.0.1",
                "--no-dashboard",
                "--name",
                f"w{i}",
                "--death-timeout",
                "60",
            )  # fmt: skip
            for i in range(2)
        ]
        from distributed import Client

        deadline = time.monotonic() + 60
        while True:
            try:
                with Client(address, timeout=2, set_as_default=False) as c:
                    c.wait_for_workers(2, timeout=max(1, deadline - time.monotonic()))
                break
            except (OSError, TimeoutError):
                if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                    tails = {f.name: f.read_text()[-400:] for f in log_dir.glob("*.log")}
                    pytest.fail(f"the Dask cluster did not start: {tails}")
                time.sleep(0.5)
        yield address, sched, workers
    finally:
        stop(procs, sig_kill)
        for f in logs:  # an unclosed file is a ResourceWarning, an error in this suite
            f.close()
        assert all(p.poll() is not None for p in procs)
