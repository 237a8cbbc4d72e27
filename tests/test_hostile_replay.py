"""Issue 19, replay sources: what a `source` may be (a regular file of bounded size, never a
FIFO, a device or a socket), times a 64-bit nanosecond clock cannot hold, a covariance read
without covariance_index, a ROS 2 schema that does not parse; each one line through
`fusionlog import`, bounded in time, no output and no temporary file left."""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error
from mcap.writer import Writer

from fusionlog.io.mcap import McapFile

T0 = 1_700_000_000_000_000_000  # ns


def replay(tmp_path: Path, source: str, values: str, extra: str = "", topic: str | None = "/j"):
    """A replay file with one sensor reading `values` (a TOML list) from `source`."""
    text = f"""\
[scenario]
name = "hostile"

[model]
kind = "constant-velocity"
n0 = 1.0

[[sensors]]
name = "s"
source = "{source}"
values = {values}
H = [1.0, 0.0]
{f'topic = "{topic}"' if topic else ""}
{extra}
"""
    p = tmp_path / "replay.toml"
    p.write_text(text)
    return p


def json_mcap(path: Path, messages: list[tuple[int, dict]], topic: str = "/j") -> Path:
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        sid = w.register_schema("test.Thing", "jsonschema", b'{"type": "object"}')
        cid = w.register_channel(topic, "json", sid)
        for t, obj in messages:
            w.add_message(cid, log_time=t, publish_time=t, data=json.dumps(obj).encode())
        w.finish()
    return path


def listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


def refused(tmp_path: Path, sc: Path, *fragments: str) -> str:
    """`fusionlog import` exits 2 with one line, and writes nothing."""
    before = listing(tmp_path)
    line = one_line_error(cli("import", sc, "-o", tmp_path / "out.mcap"), *fragments)
    assert listing(tmp_path) == before
    return line


# ------------------------------------------------------------------ covariance_index


def pose(cov: list[float], y: float) -> dict:
    return {"pose": {"pose": {"position": {"x": 0.0, "y": y}}, "covariance": cov}}


def covariances() -> list[list[float]]:
    # two messages, every entry distinct: cov[0] (x variance) != cov[7] (y variance)
    rng = np.random.default_rng(5)
    out = []
    for _ in range(2):
        A = rng.normal(size=(6, 6))
        out.append((A @ A.T + 6 * np.eye(6)).ravel().tolist())
    return out


def test_covariance_without_index_is_refused_not_defaulted(tmp_path: Path) -> None:
    covs = covariances()
    json_mcap(tmp_path / "p.mcap", [(T0 + i, pose(c, 1.0 + i)) for i, c in enumerate(covs)])
    sc = replay(tmp_path, "p.mcap", '["pose.pose.position.y"]', 'covariance = "pose.covariance"')
    refused(tmp_path, sc, "p.mcap", "sensors[0]", "6x6", "covariance_index")


def test_covariance_index_reads_the_right_element(tmp_path: Path) -> None:
    covs = covariances()
    json_mcap(tmp_path / "p.mcap", [(T0 + i, pose(c, 1.0 + i)) for i, c in enumerate(covs)])
    sc = replay(tmp_path, "p.mcap", '["pose.pose.position.y"]',
                'covariance = "pose.covariance"\ncovariance_index = [1]')  # fmt: skip
    ok("import", sc, "-o", tmp_path / "out.mcap")
    got = McapFile(tmp_path / "out.mcap").message_covariances("/sensors/s")
    # row/column 1 of the row-major 6 x 6: the flat entry 7 of each message
    assert got[:, 0, 0].tolist() == [covs[0][7], covs[1][7]]
    assert covs[0][7] != covs[0][0]


def test_one_asymmetric_covariance_falls_back_to_r_alone(tmp_path: Path) -> None:
    """R applies to the message whose block is not a covariance (here not symmetric), not to
    every message of the stream."""
    blocks = [[[4.0, 0.0], [0.0, 4.0]], [[4.0, 1.0], [0.0, 4.0]], [[9.0, 0.5], [0.5, 9.0]]]
    msgs = []
    for i, b in enumerate(blocks):
        c = np.eye(6)
        c[:2, :2] = b
        msgs.append((T0 + i * 10**9, pose(c.ravel().tolist(), 1.0 + i)))
    json_mcap(tmp_path / "p.mcap", msgs)
    sc = replay(tmp_path, "p.mcap", '["pose.pose.position.x", "pose.pose.position.y"]',
                'covariance = "pose.covariance"\ncovariance_index = [0, 1]\n'
                "R = [[1.0, 0.0], [0.0, 1.0]]")  # fmt: skip
    sc.write_text(sc.read_text().replace("H = [1.0, 0.0]", "H = [[1.0, 0.0], [0.0, 1.0]]"))
    res = ok("import", sc, "-o", tmp_path / "out.mcap")
    assert "1 of 3 messages with an all-zero or not positive definite covariance" in res.stdout
    got = McapFile(tmp_path / "out.mcap").message_covariances("/sensors/s")
    np.testing.assert_array_equal(got, [blocks[0], np.eye(2), blocks[2]])


# ------------------------------------------------------------------ what a source may be


def run_import(tmp_path: Path, sc: Path) -> subprocess.CompletedProcess:
    """A real process with a deadline: a source that blocks must not hang the test."""
    cmd = [sys.executable, "-m", "fusionlog.cli", "import", str(sc), "-o", str(tmp_path / "o.mcap")]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)


@pytest.mark.parametrize("suffix", [".csv", ".mcap"])
def test_fifo_source_is_refused_without_blocking(tmp_path: Path, suffix: str) -> None:
    fifo = tmp_path / f"pipe{suffix}"
    os.mkfifo(fifo)
    sc = replay(tmp_path, fifo.name, '["v"]', "R = 1.0", topic="/j" if suffix == ".mcap" else None)
    t = time.monotonic()
    p = run_import(tmp_path, sc)
    assert time.monotonic() - t < 60
    assert p.returncode == 2, p.stderr
    lines = p.stderr.splitlines()
    assert len(lines) == 1 and "FIFO" in lines[0] and str(fifo.name) in lines[0], p.stderr
    assert listing(tmp_path) == sorted([fifo.name, "replay.toml"])


def test_endless_fifo_with_a_writer_is_refused(tmp_path: Path) -> None:
    """An endless input (a FIFO a writer keeps feeding, like /dev/zero): refused, not read."""
    fifo = tmp_path / "endless.csv"
    os.mkfifo(fifo)
    stop = threading.Event()

    def feed() -> None:
        try:
            fd = os.open(fifo, os.O_WRONLY)  # waits for a reader, if one ever comes
        except OSError:
            return
        try:
            while not stop.is_set():
                os.write(fd, b"time,v\n" + b"1,2\n" * 1000)
        except OSError:  # the reader went away
            pass
        finally:
            os.close(fd)

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    try:
        sc = replay(tmp_path, fifo.name, '["v"]', "R = 1.0", topic=None)
        refused(tmp_path, sc, "endless.csv", "FIFO")
    finally:
        stop.set()
        try:  # release the writer if it still waits for a reader
            os.close(os.open(fifo, os.O_RDONLY | os.O_NONBLOCK))
        except OSError:
            pass
        writer.join(5)


def test_device_node_and_socket_sources_are_refused(tmp_path: Path) -> None:
    dev = tmp_path / "dev.csv"
    try:
        os.mknod(dev, stat.S_IFCHR | 0o600, os.makedev(1, 5))
    except PermissionError:
        pytest.skip("making a device node needs CAP_MKNOD")
    sc = replay(tmp_path, dev.name, '["v"]', "R = 1.0", topic=None)
    refused(tmp_path, sc, "dev.csv", "character device")
    dev.unlink()
    sock = socket.socket(socket.AF_UNIX)
    try:
        sock.bind(str(tmp_path / "sock.mcap"))
        sc = replay(tmp_path, "sock.mcap", '["v"]', "R = 1.0")
        refused(tmp_path, sc, "sock.mcap", "socket")
    finally:
        sock.close()


@pytest.mark.parametrize(("name", "size", "says"), [
    ("big.csv", (1 << 30) + 1, "1 GiB"),
    ("big.mcap", (256 << 30) + 1, "256 GiB"),
])  # fmt: skip
def test_sources_larger_than_the_bound_are_refused_unread(
    tmp_path: Path, name: str, size: int, says: str
) -> None:
    big = tmp_path / name
    with open(big, "wb") as f:
        f.truncate(size)  # sparse: no disk, no memory
    topic = "/j" if name.endswith(".mcap") else None
    sc = replay(tmp_path, name, '["v"]', "R = 1.0", topic=topic)
    refused(tmp_path, sc, name, f"more than the {says}")


# ------------------------------------------------------------------ times


@pytest.mark.parametrize(("cell", "says"), [
    ("-1.5", "negative"),
    ("1e999999999", "64-bit nanoseconds"),
    ("9223372037", "64-bit nanoseconds"),
])  # fmt: skip
def test_csv_times_outside_the_clock(tmp_path: Path, cell: str, says: str) -> None:
    (tmp_path / "d.csv").write_text(f"time,v\n1.0,2.0\n{cell},3.0\n")
    sc = replay(tmp_path, "d.csv", '["v"]', "R = 1.0", topic=None)
    refused(tmp_path, sc, "d.csv", "sensors[0]", "line 3", says)


def test_json_mcap_negative_time_field(tmp_path: Path) -> None:
    json_mcap(tmp_path / "j.mcap", [(T0, {"t": 1.0, "v": 1.0}), (T0 + 1, {"t": -2.0, "v": 2.0})])
    sc = replay(tmp_path, "j.mcap", '["v"]', 'R = 1.0\ntime = "t"')
    refused(tmp_path, sc, "j.mcap", "message 2", "-2000000000 ns", "negative")


@pytest.mark.parametrize("log_time", [2**63, 2**64 - 1])
def test_json_mcap_log_time_past_int64(tmp_path: Path, log_time: int) -> None:
    json_mcap(tmp_path / "j.mcap", [(T0, {"v": 1.0}), (log_time, {"v": 2.0})])
    sc = replay(tmp_path, "j.mcap", '["v"]', "R = 1.0")
    refused(tmp_path, sc, "j.mcap", "message 2", str(log_time), "past 2^63 - 1 ns")


def test_json_mcap_log_time_at_the_int64_limit_is_accepted(tmp_path: Path) -> None:
    json_mcap(tmp_path / "j.mcap", [(2**63 - 2, {"v": 1.0}), (2**63 - 1, {"v": 2.0})])
    sc = replay(tmp_path, "j.mcap", '["v"]', "R = 1.0")
    res = ok("import", sc, "-o", tmp_path / "out.mcap")
    assert "1 run x 2 instants" in res.stdout


# ------------------------------------------------------------------ schemas


def test_cdr_schema_that_does_not_parse_is_one_line(tmp_path: Path) -> None:
    with open(tmp_path / "bad.mcap", "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("pkg/msg/Bad", "ros2msg", b"float64 x\nnot a field ! !\n")
        cid = w.register_channel("/x", "cdr", sid)
        w.add_message(cid, log_time=T0, publish_time=T0, data=b"\x00\x01\x00\x00" + bytes(8))
        w.finish()
    sc = replay(tmp_path, "bad.mcap", '["x"]', "R = 1.0", topic="/x")
    refused(tmp_path, sc, "bad.mcap", "cannot decode its schema")


# ------------------------------------------------------------------ every command's inputs


@pytest.mark.parametrize(
    ("args", "fifo"),
    [
        (["simulate", "{f}", "-o", "s.mcap"], "f.toml"),
        (["run", "{f}", "--out-dir", "o"], "f.toml"),
        (["estimate", "{f}", "-o", "e.mcap"], "f.mcap"),
        (["evaluate", "{f}", "{f}", "-o", "x.rrd"], "f.mcap"),
        (["inspect", "{f}"], "f.mcap"),
        (["inspect", "--recover", "{f}"], "f.mcap"),
        (["compare", "{f}", "{f}"], "f.json"),
    ],
)
def test_every_command_refuses_a_fifo_input_without_blocking(
    tmp_path: Path, args: list[str], fifo: str
) -> None:
    os.mkfifo(tmp_path / fifo)
    argv = [a.replace("{f}", fifo) for a in args]
    cmd = [sys.executable, "-m", "fusionlog.cli", *argv]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False, cwd=tmp_path)
    assert p.returncode == 2, p.stderr
    assert p.stderr.splitlines() == [
        f"fusionlog: error: {fifo}: is a FIFO (named pipe), not a regular file"
    ]
    assert listing(tmp_path) == [fifo]


def test_a_stamp_far_from_its_log_time_is_noted(tmp_path: Path) -> None:
    """A header stamp left at 0 among stamps that follow the log time (by a constant offset
    here, as another clock would): noted with the message, not read in silence as 1970."""
    msgs = []
    for i in range(20):
        t = T0 + i * 10**8
        st = T0 - 5 * 10**9 + i * 10**8 if i != 7 else 0
        stamp = {"sec": st // 10**9, "nanosec": st % 10**9}
        msgs.append((t, {"header": {"stamp": stamp}, "v": float(i)}))
    json_mcap(tmp_path / "p.mcap", msgs)
    sc = replay(tmp_path, "p.mcap", '["v"]', 'time = "header.stamp"\nR = [[1.0]]')
    out = ok("import", sc, "-o", tmp_path / "out.mcap").stdout
    assert (
        "note: s: 1 message whose time is more than 60 s off the others' (time - log time -5 s "
        f"for most), e.g. message 8: time 0 ns at log time {T0 + 7 * 10**8} ns"
    ) in out, out
    # the offset alone (every stamp 5 s behind) is no note, nor the log time itself
    json_mcap(tmp_path / "p.mcap", [(t, m) for t, m in msgs if t != T0 + 7 * 10**8])
    assert "more than 60 s" not in ok("import", sc, "-o", tmp_path / "o2.mcap").stdout
    sc.write_text(sc.read_text().replace('time = "header.stamp"', ""))
    assert "more than 60 s" not in ok("import", sc, "-o", tmp_path / "o3.mcap").stdout


def test_stamps_all_zero_say_unset(tmp_path: Path) -> None:
    msgs = [(T0 + i, {"header": {"stamp": {"sec": 0, "nanosec": 0}}, "v": 1.0}) for i in range(3)]
    json_mcap(tmp_path / "p.mcap", msgs)
    sc = replay(tmp_path, "p.mcap", '["v"]', 'time = "header.stamp"\nR = [[1.0]]')
    refused(tmp_path, sc, "p.mcap", "duplicate instant 0 ns", "an unset stamp? (without `time`")


def test_a_subnormal_variance_is_not_a_usable_covariance(tmp_path: Path) -> None:
    """An uninitialised covariance (a VectorNav driver's 1.6e-315) is positive definite to a
    Cholesky factorisation, but its inverse overflows: R applies there, as for zeros."""
    msgs = []
    for i, var in enumerate([2.0, 1.59173414e-315, 3.0]):
        c = np.eye(6)
        c[1, 1] = var
        msgs.append((T0 + i * 10**9, pose(c.ravel().tolist(), 1.0 + i)))
    json_mcap(tmp_path / "p.mcap", msgs)
    sc = replay(tmp_path, "p.mcap", '["pose.pose.position.y"]',
                'covariance = "pose.covariance"\ncovariance_index = [1]\nR = [[0.5]]')  # fmt: skip
    res = ok("import", sc, "-o", tmp_path / "out.mcap")
    assert "1 of 3 messages with an all-zero or not positive definite covariance" in res.stdout
    got = McapFile(tmp_path / "out.mcap").message_covariances("/sensors/s")
    assert got[:, 0, 0].tolist() == [2.0, 0.5, 3.0]
