"""Writing a recording when the disk fails: the first failed write is an OutputError naming the
output and the OS error (Rerun's file sink only logged it, left a truncated file, or hung in
disconnect()), every case is bounded in time, and through Outputs no temporary file is left and
the previous output is unchanged.

Faults are injected three ways: a file object that fails with ENOSPC after a given number of
bytes (always works), a file-size limit (RLIMIT_FSIZE, EFBIG) in a child process (always works
on Linux), and a real full tmpfs mounted under a temporary folder (skipped where mounting is
not allowed)."""

from __future__ import annotations

import errno
import json
import subprocess
import sys
import textwrap
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
from test_rrd import identity_data, synthetic

from fusionlog.errors import OutputError
from fusionlog.io.atomic import CheckedFile, Outputs
from fusionlog.io.rrd import write_identity_recording, write_recording

TIMEOUT = 60  # s: far above a normal write (well under a second); a hang fails the test


def bounded(fn: Callable[[], object]) -> BaseException | None:
    """Run `fn` in a thread; fail if it does not finish in TIMEOUT; return what it raised."""
    out: dict[str, BaseException] = {}

    def run() -> None:
        try:
            fn()
        except BaseException as e:  # noqa: BLE001 - handed to the test
            out["error"] = e

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(TIMEOUT)
    assert not t.is_alive(), f"writer still running after {TIMEOUT} s (hang)"
    return out.get("error")


class FullDisk:
    """A binary file that takes `room` bytes, then fails every write with ENOSPC."""

    def __init__(self, room: int) -> None:
        self.room, self.data, self.closed, self.calls = room, bytearray(), False, 0

    def write(self, b) -> int:
        self.calls += 1
        b = bytes(b)
        if len(self.data) + len(b) > self.room:
            self.data += b[: self.room - len(self.data)]
            raise OSError(errno.ENOSPC, "No space left on device")
        self.data += b
        return len(b)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def fileno(self) -> int:  # pragma: no cover - only used by CheckedFile.close
        raise OSError(errno.EBADF, "no file")


WRITERS = {
    "state": (write_recording, synthetic),
    "identity": (write_identity_recording, identity_data),
}


@pytest.mark.parametrize("kind", sorted(WRITERS))
@pytest.mark.parametrize("room", [0, 1000, 100_000])
def test_checked_file_on_a_full_disk_raises_output_error(tmp_path: Path, kind, room) -> None:
    writer, data = WRITERS[kind]
    target = tmp_path / "ev.rrd"
    disk = FullDisk(room)
    cf = CheckedFile(target, tmp_path / ".ev.rrd.tmp", disk)
    err = bounded(lambda: writer(cf, **data()))
    assert isinstance(err, OutputError), repr(err)
    msg = str(err)
    assert "\n" not in msg and str(target) in msg and "No space left on device" in msg
    assert len(disk.data) == room  # it did write up to the failure: part-way, not up front
    calls = disk.calls
    with pytest.raises(OutputError):  # and the file stays failed
        cf.write(b"x")
    assert disk.calls == calls


def test_plain_file_object_failure_is_an_output_error() -> None:
    disk = FullDisk(5000)
    disk.name = "somewhere/ev.rrd"
    err = bounded(lambda: write_recording(disk, **synthetic()))
    assert isinstance(err, OutputError), repr(err)
    assert str(err) == "somewhere/ev.rrd: cannot write: No space left on device"


# A child process with a file-size limit: the kernel refuses writes past it with EFBIG.
CHILD = textwrap.dedent(
    """
    import json, resource, signal, sys
    sys.path[:0] = [sys.argv[3], sys.argv[4]]
    from pathlib import Path
    from test_rrd import synthetic
    from fusionlog.errors import FusionlogError
    from fusionlog.io.atomic import Outputs
    from fusionlog.io.rrd import write_recording
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of being killed
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[2]), resource.RLIM_INFINITY))
    target = Path(sys.argv[1])
    try:
        with Outputs([target], force=True) as outs:
            write_recording(outs.open(target), **synthetic())
            outs.commit()
        print(json.dumps({"ok": True}))
    except FusionlogError as e:
        print(json.dumps({"ok": False, "type": type(e).__name__, "msg": str(e)}))
    """
)


@pytest.mark.parametrize("limit", [50_000, 300_000])
def test_outputs_with_a_file_size_limit(tmp_path: Path, limit: int) -> None:
    target = tmp_path / "ev.rrd"
    target.write_bytes(b"previous recording")
    src = str(Path(__file__).parents[1] / "src")
    res = subprocess.run(
        [sys.executable, "-c", CHILD, str(target), str(limit), src, str(Path(__file__).parent)],
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out == {
        "ok": False,
        "type": "OutputError",
        "msg": f"{target}: cannot write: File too large",
    }
    assert target.read_bytes() == b"previous recording"
    assert [p.name for p in tmp_path.iterdir()] == ["ev.rrd"]  # no temporary file


@pytest.fixture
def tiny_tmpfs(tmp_path: Path):
    """A 64 KiB tmpfs under tmp_path (needs the right to mount: skipped elsewhere)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    res = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {res.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True, timeout=30, check=False)


@pytest.mark.parametrize("force", [False, True])
def test_outputs_on_a_full_tmpfs(tiny_tmpfs: Path, force: bool) -> None:
    target = tiny_tmpfs / "ev.rrd"
    summary = tiny_tmpfs / "summary.json"
    if force:
        target.write_bytes(b"previous recording")
        summary.write_text("{}\n")

    def evaluate_outputs() -> None:
        with Outputs([target, summary], force=force) as outs:
            write_recording(outs.open(target), **synthetic())  # about 0.5 MB: does not fit
            outs.open(summary).write(b"{}\n")
            outs.commit()

    err = bounded(evaluate_outputs)
    assert isinstance(err, OutputError), repr(err)
    assert str(err) == f"{target}: cannot write: No space left on device"
    names = sorted(p.name for p in tiny_tmpfs.iterdir())
    if force:
        assert names == ["ev.rrd", "summary.json"]  # no temporary file, old outputs kept
        assert target.read_bytes() == b"previous recording"
        assert summary.read_text() == "{}\n"
    else:
        assert names == []


def test_the_pipe_folder_is_removed_after_a_write_and_after_a_failure(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Rerun's file sink writes into a named pipe in a private temporary folder (io/rrd/stream.py)
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    target = tmp_path / "out" / "ev.rrd"
    target.parent.mkdir()
    with Outputs([target], force=True) as outs:
        write_recording(outs.open(target), **synthetic())
        outs.commit()
    assert target.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    err = bounded(lambda: write_recording(FullDisk(5000), **synthetic()))
    assert isinstance(err, OutputError), repr(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
