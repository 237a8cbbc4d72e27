"""Issue 19, sweeps on Dask: a --scheduler address that is not a Dask scheduler (no scheme,
another scheme, a closed port, a socket that accepts and stays silent, an HTTP server), a
cluster that loses its workers or its scheduler mid-sweep (a real `dask scheduler` and two
`dask worker` processes on 127.0.0.1, killed by pid), --workers beyond the CPUs, and click's
usage errors: each one line on stderr, exit 2, bounded in time, no output left."""

from __future__ import annotations

import http.server
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from cli_helpers import cli, ok, one_line_error, one_line_exit
from dask_cluster import ENV, free_port, loopback_cluster

ROOT = Path(__file__).resolve().parents[1]
AJGL = ROOT / "pipeline" / "ajgl2009.toml"
SWEEP = ["sweep", str(AJGL), "--vary", "scenario.dt=0.5,1", "--arch", "CKF", "--arch", "MSC"]


def fusionlog(*args: str | Path) -> subprocess.Popen:
    """The CLI in a process of its own (its stderr as a user sees it, to the end)."""
    cmd = [sys.executable, "-m", "fusionlog.cli", *map(str, args)]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENV)  # fmt: skip


def finish(p: subprocess.Popen, timeout: float = 90) -> tuple[int, str, str]:
    try:
        out, err = p.communicate(timeout=timeout)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)
    return p.returncode, out, err


# ------------------------------------------------------------------- addresses and services


@pytest.mark.parametrize(("address", "says"), [
    ("127.0.0.1:8786", "give the scheme, e.g. tcp://127.0.0.1:8786"),
    ("ucx://127.0.0.1:8786", "scheme ucx:// is not supported"),
    ("inproc://x", "scheme inproc:// is not supported"),
    ("ws://127.0.0.1:8786", "scheme ws:// is not supported"),
    ("tcp://", "expected tcp://HOST:PORT"),
])  # fmt: skip
def test_scheduler_address_scheme(tmp_path: Path, address: str, says: str) -> None:
    res = cli(*SWEEP, "--scheduler", address, "--out-dir", tmp_path / "o")
    one_line_error(res, f"--scheduler {address}", says)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("timeout", ["0", "-1", "inf", "nan"])
def test_scheduler_timeout_must_be_positive(tmp_path: Path, timeout: str) -> None:
    """(inf used to reach Dask's connect, whose "Invalid time unit: inf" was the message.)"""
    res = cli(*SWEEP, "--scheduler", "tcp://127.0.0.1:1", "--scheduler-timeout", timeout,
              "--out-dir", tmp_path / "o")  # fmt: skip
    one_line_error(res, "--scheduler-timeout", "finite number > 0", f"got {timeout}")
    assert not (tmp_path / "o").exists()


def test_closed_port_is_one_line_at_once(tmp_path: Path) -> None:
    """Nothing listens there: the refused connection is the answer, not --scheduler-timeout
    seconds of Dask's retries (10 s by default)."""
    address = f"tcp://127.0.0.1:{free_port()}"
    t = time.monotonic()
    res = cli(*SWEEP, "--scheduler", address, "--scheduler-timeout", "60", "--out-dir", tmp_path)
    assert time.monotonic() - t < 10
    one_line_error(res, f"--scheduler {address}", "cannot connect", "connection refused")


class _Silent:
    """A TCP server that accepts connections and never says anything."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen()
        self.port = self.sock.getsockname()[1]
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        try:
            while True:
                self.conns.append(self.sock.accept()[0])
        except OSError:
            pass

    def close(self) -> None:
        for c in self.conns:
            c.close()
        self.sock.close()


class _Quiet(http.server.BaseHTTPRequestHandler):
    def log_message(self, *args) -> None:  # no access log on the test's stderr
        pass


@pytest.fixture
def http_port() -> Iterator[int]:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Quiet)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()


@pytest.mark.parametrize("service", ["silent", "http", "closed"])
def test_scheduler_address_where_no_scheduler_answers(
    tmp_path: Path, service: str, http_port: int
) -> None:
    silent = _Silent() if service == "silent" else None
    try:
        port = {"silent": silent.port if silent else 0, "http": http_port,
                "closed": free_port()}[service]  # fmt: skip
        address = f"tcp://127.0.0.1:{port}"
        t = time.monotonic()
        p = fusionlog(*SWEEP, "--scheduler", address, "--scheduler-timeout", "2",
                      "--out-dir", tmp_path / "o")  # fmt: skip
        rc, _, err = finish(p, timeout=60)
        # the timeout bounds it (plus the interpreter's start); no Client.__del__ traceback
        # follows our line: the process has ended and its stderr is that one line
        assert time.monotonic() - t < 30
        one_line_exit(rc, err, f"--scheduler {address}", "Dask scheduler")
    finally:
        if silent is not None:
            silent.close()
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------- a real cluster, killed


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[tuple[str, subprocess.Popen, list[subprocess.Popen]]]:
    """A real scheduler and two workers on 127.0.0.1 (`dask_cluster.loopback_cluster`), every
    process stopped by its pid (SIGKILL) at the end."""
    with loopback_cluster(tmp_path, sig_kill=True) as c:
        yield c


def wait_until_processing(address: str, proc: subprocess.Popen) -> None:
    """Until a task of the sweep runs on a worker (then it is mid-sweep)."""
    from distributed import Client

    deadline = time.monotonic() + 60
    with Client(address, timeout=5, set_as_default=False) as c:
        while not any(c.processing().values()):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the sweep never started a task"
            time.sleep(0.02)


def test_every_worker_killed_mid_sweep_is_one_line(tmp_path: Path, cluster) -> None:
    address, _, workers = cluster
    d = tmp_path / "o"
    p = fusionlog(*SWEEP, "--runs", "400000", "--block-runs", "500", "--scheduler", address,
                  "--scheduler-timeout", "3", "--out-dir", d)  # fmt: skip
    wait_until_processing(address, p)
    t = time.monotonic()
    for w in workers:
        os.kill(w.pid, signal.SIGKILL)
    rc, out, err = finish(p, timeout=60)
    assert time.monotonic() - t < 30  # "no worker for 3 s", not a hang
    one_line_exit(rc, err, f"--scheduler {address}", "no Dask worker for 3 s")
    assert out == "" and not d.exists()


def test_scheduler_killed_mid_sweep_is_one_line(tmp_path: Path, cluster) -> None:
    address, sched, _ = cluster
    d = tmp_path / "o"
    p = fusionlog(*SWEEP, "--runs", "400000", "--block-runs", "500", "--scheduler", address,
                  "--scheduler-timeout", "3", "--out-dir", d)  # fmt: skip
    wait_until_processing(address, p)
    os.kill(sched.pid, signal.SIGKILL)
    rc, out, err = finish(p, timeout=60)
    one_line_exit(rc, err, f"--scheduler {address}", "lost the connection to the Dask scheduler")
    assert out == "" and not d.exists()  # never a partial table


def test_one_worker_killed_mid_sweep_gives_the_same_table(tmp_path: Path, cluster) -> None:
    address, _, workers = cluster
    args = [*SWEEP, "--runs", "60000", "--block-runs", "500"]
    ok(*args, "--workers", "0", "--out-dir", tmp_path / "here")
    p = fusionlog(*args, "--scheduler", address, "--out-dir", tmp_path / "dist")
    wait_until_processing(address, p)
    os.kill(workers[0].pid, signal.SIGKILL)
    rc, out, err = finish(p, timeout=120)
    assert rc == 0, err
    here, dist = (pq.read_table(tmp_path / d / "sweep.parquet") for d in ("here", "dist"))
    assert dist.equals(here)


# ------------------------------------------------------------------- workers and usage


def test_a_task_failing_on_a_local_cluster_is_one_line(tmp_path: Path) -> None:
    """Tasks that fail numerically in a LocalCluster's workers: our one line naming the file,
    not also each worker's "Compute Failed" log with its traceback (same stderr)."""
    sc = tmp_path / "overflow.toml"
    sc.write_text(
        '[scenario]\nname = "overflow"\nsteps = 4\nruns = 20\nseed = 1\ndt = 1.0\n'
        "[model]\nF = [[1e120]]\nQ = [[1.0]]\n[prior]\nmean = [0.0]\ncov = [[1.0]]\n"
        '[[sensors]]\nname = "s"\nH = [[1.0]]\nR = 1.0\n'
    )
    p = fusionlog("sweep", sc, "--vary", "scenario.dt=1,2", "--workers", "2",
                  "--out-dir", tmp_path / "o")  # fmt: skip
    rc, _, err = finish(p)
    # whichever task fails first (a block's simulation, a point's exact analysis) is named
    one_line_exit(rc, err, str(sc))
    assert not (tmp_path / "o").exists()


def test_workers_beyond_the_cpus_are_capped_with_a_note(tmp_path: Path) -> None:
    cpus = len(os.sched_getaffinity(0))
    res = ok(*SWEEP, "--runs", "100", "--workers", str(cpus + 30), "--out-dir", tmp_path / "o")
    note = f"LocalCluster of {cpus} worker process{'es' * (cpus != 1)} (--workers {cpus + 30} "
    assert note + f"capped at the {cpus} CPUs)" in res.stdout
    assert res.stderr == ""


@pytest.mark.parametrize("case", ["negative", "both", "directory", "out-dir-file"])
def test_usage_errors_are_one_line(tmp_path: Path, case: str) -> None:
    (tmp_path / "f").write_text("")
    args = {
        "negative": [*SWEEP, "--workers", "-1"],
        "both": [*SWEEP, "--workers", "1", "--scheduler", "tcp://127.0.0.1:1"],
        "directory": ["sweep", tmp_path, "--vary", "scenario.dt=1"],
        "out-dir-file": [*SWEEP, "--out-dir", tmp_path / "f"],
    }[case]
    says = {"negative": "--workers", "both": "give one of them", "directory": "is a directory",
            "out-dir-file": "is a file"}[case]  # fmt: skip
    one_line_error(cli(*args), says, "fusionlog sweep --help")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["f"]


# ------------------------------------------------------------------- grids


@pytest.mark.parametrize(
    ("vary", "says"),
    [
        (["scenario.dt=0.1:10:100000"], "100000 values is more than 10000"),
        (["scenario.dt=0.1:10:200", "model.n0=0.1:1:60"], "12000 grid points is more than 10000"),
    ],
)
def test_grids_beyond_the_bound_are_refused(tmp_path: Path, vary: list[str], says: str) -> None:
    args = [a for v in vary for a in ("--vary", v)]
    t = time.monotonic()
    res = cli("sweep", AJGL, *args, "--exact-only", "--out-dir", tmp_path / "o")
    one_line_error(res, says)
    assert time.monotonic() - t < 10 and not (tmp_path / "o").exists()


def test_ctrl_c_cancels_a_long_grid(tmp_path: Path) -> None:
    d = tmp_path / "o"
    # 5000 points of exact analysis: minutes of work, interrupted after a second or two
    p = fusionlog("sweep", AJGL, "--vary", "scenario.dt=0.1:10:5000", "--exact-only",
                  "--out-dir", d)  # fmt: skip
    time.sleep(3)
    assert p.poll() is None
    p.send_signal(signal.SIGINT)
    rc, out, err = finish(p, timeout=30)
    assert rc == 130, err
    assert err.splitlines() == ["fusionlog: interrupted; no partial output was left behind"]
    assert not d.exists() or not any(d.iterdir())
