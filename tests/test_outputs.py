"""Issue 12, "Faults lose data", through the real command line, for every command that writes
(simulate, estimate, evaluate with and without --summary, run): docs/reference/outputs.md,
"Outputs never lose data".

1. special targets (a character device and a FIFO made under tmp_path, a directory, a symlink
   to a device) are refused even with --force: exit 2, one line, the special file untouched;
2. an output that is one of the command's inputs (the same path, a hard link, a symlink) is
   refused even with --force, and so is one file given as two outputs;
3. two concurrent writers of one target without --force: exactly one wins, the file is complete
   and is the winner's, the loser exits 2 with one line;
4. SIGTERM and SIGHUP during a long simulate/run: exit 128 + N, no temporary file, the previous
   output byte-identical;
5. a temporary file left by a dead process is reported by `run` and `inspect` with a command
   that removes it, and nothing is deleted (neither it nor anyone else's files);
6. injected write failures (ENOSPC after N bytes of any output, EROFS, EIO at fsync or at the
   commit) and a real read-only tmpfs: exit 2, one line naming the path and the OS error, no
   traceback, previous outputs byte-identical (all or none for the commands with several
   outputs), no temporary file;
7. a full tmpfs (300k, 600k): evaluate and run stop within a bounded time with one line.

In-process (click's CliRunner) wherever a fault can be injected or nothing needs a process of
its own; real processes for signals, races and the full disk. Mounting a tmpfs needs root or
CAP_SYS_ADMIN: those cases are skipped elsewhere.
"""

from __future__ import annotations

import errno
import os
import re
import shlex
import shutil
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import cli, listing, ok, one_line_error
from test_cli import (
    AJGL,
    ENV,
    FUSIONLOG,
    OUTPUTS,
    ROOT,
    all_arrays,
    assert_same_arrays,
    needs_fusionlog,
    run_proc,
    snapshot,
)

import fusionlog.io.atomic as atomic

TINY = ["--runs", "20", "--steps", "5"]
TIMEOUT = 120  # s, for every process we wait on: far above the seconds each one needs
COMMANDS = ["simulate", "estimate", "evaluate", "evaluate --summary", "run"]
#: the base run's file whose content stands for a target's previous output
PREVIOUS = {"s.mcap": "sensors.mcap", "e.mcap": "estimates.mcap", "ev.rrd": "evaluation.rrd"}
PREVIOUS |= {"sum.json": "summary.json"} | {n: n for n in OUTPUTS}
TEMP = re.compile(r"^\.(?P<name>.+)\.fusionlog-(?P<pid>\d+)-[0-9a-f]+\.tmp$")


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """One good `run` (20 runs, K = 5): the inputs of estimate/evaluate and, copied, the
    previous outputs of every command."""
    d = tmp_path_factory.mktemp("base") / "run"
    ok("run", AJGL, "--out-dir", d, *TINY)
    return d


def command(name: str, out: Path, base: Path) -> tuple[list, list[Path]]:
    """The arguments of command `name` writing into `out`, and its targets in writing order."""
    s, e = base / "sensors.mcap", base / "estimates.mcap"
    if name == "simulate":
        return ["simulate", AJGL, "-o", out / "s.mcap", *TINY], [out / "s.mcap"]
    if name == "estimate":
        return ["estimate", s, "-o", out / "e.mcap"], [out / "e.mcap"]
    if name == "evaluate":
        return ["evaluate", s, e, "-o", out / "ev.rrd"], [out / "ev.rrd"]
    if name == "evaluate --summary":
        targets = [out / "ev.rrd", out / "sum.json"]
        return ["evaluate", s, e, "-o", targets[0], "--summary", targets[1]], targets
    assert name == "run"
    return ["run", AJGL, "--out-dir", out, *TINY], [out / n for n in OUTPUTS]


def put_previous(targets: list[Path], base: Path) -> dict[str, tuple[int, bytes]]:
    """Give every target the content of a good run's output; returns their snapshot."""
    for t in targets:
        t.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(base / PREVIOUS[t.name], t)
    return snapshot(targets)


def temporaries(folder: Path) -> list[str]:
    return [n for n in listing(folder) if TEMP.match(n)]


def dead_pid() -> int:
    """A process id that no process has."""
    for pid in range(999_999, 1, -1):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return pid
        except PermissionError:
            continue
    raise AssertionError("no free pid")  # pragma: no cover


def mount_tmpfs(mnt: Path, size: str) -> None:
    """Mount a tmpfs of `size` at `mnt` (made under tmp_path), or skip the test."""
    mnt.mkdir(parents=True, exist_ok=True)
    try:
        r = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        pytest.skip(f"cannot run mount: {e}")
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")


def umount(mnt: Path) -> None:
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30, check=False)


@pytest.fixture
def tmpfs(tmp_path: Path) -> Iterator:
    """mount(size) -> a fresh tmpfs under tmp_path; all unmounted at the end of the test."""
    mounted: list[Path] = []

    def mount(size: str) -> Path:
        mnt = tmp_path / f"tmpfs{len(mounted)}"
        mount_tmpfs(mnt, size)
        mounted.append(mnt)
        return mnt

    try:
        yield mount
    finally:
        for mnt in mounted:
            umount(mnt)


def popen(*args) -> subprocess.Popen:
    return subprocess.Popen(
        [FUSIONLOG, *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )


def finish(proc: subprocess.Popen) -> tuple[str, str]:
    """Wait for `proc` (bounded); killed if it does not end in time."""
    try:
        return proc.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise AssertionError(f"{proc.args} still running after {TIMEOUT} s") from None


# ------------------------------------------------------------------------------------------
# 1. special files are never outputs, even with --force
# ------------------------------------------------------------------------------------------


def mknod(path: Path) -> None:
    """A character device (1, 3), a null device of our own: never a system path."""
    try:
        os.mknod(path, stat.S_IFCHR | 0o600, os.makedev(1, 3))
    except PermissionError as e:
        pytest.skip(f"cannot make a device node here: {e}")


def make_special(path: Path, kind: str, scratch: Path) -> str:
    """Make `path` a special file of `kind`; returns how the error names it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if kind == "device":
        mknod(path)
        return "a device"
    if kind == "fifo":
        os.mkfifo(path)
        return "a FIFO"
    if kind == "directory":
        path.mkdir()
        (path / "keep").write_text("inside")
        return "a directory"
    assert kind == "symlink to a device"
    dev = scratch / f"dev-{path.name}"
    mknod(dev)
    os.symlink(dev, path)
    return "a device"


def identity(path: Path) -> tuple:
    st = os.lstat(path)
    return st.st_mode, st.st_ino, st.st_rdev, st.st_size, st.st_mtime_ns


SPECIAL_TARGETS = [
    ("simulate", 0),
    ("estimate", 0),
    ("evaluate", 0),
    ("evaluate --summary", 0),
    ("evaluate --summary", 1),
    ("run", 0),
    ("run", 3),
]


@pytest.mark.parametrize("kind", ["device", "fifo", "directory", "symlink to a device"])
@pytest.mark.parametrize(("name", "which"), SPECIAL_TARGETS)
def test_special_target_is_refused_even_with_force(
    base: Path, tmp_path: Path, name: str, which: int, kind: str
) -> None:
    out, scratch = tmp_path / "out", tmp_path / "scratch"
    scratch.mkdir()
    args, targets = command(name, out, base)
    special = targets[which]
    regular = [t for t in targets if t != special]
    before = put_previous(regular, base)
    what = make_special(special, kind, scratch)
    was = identity(special)
    names = listing(out)
    # a reader on the FIFO: had anything opened it for writing, that would not block, and
    # the bytes would show up here
    reader = os.open(special, os.O_RDONLY | os.O_NONBLOCK) if kind == "fifo" else None
    try:
        res = cli(*args, "--force")
        line = one_line_error(res)
        assert line == f"fusionlog: error: {special}: is {what}; outputs are regular files"
        if reader is not None:
            assert os.read(reader, 1) == b""  # no writer ever, no data
    finally:
        if reader is not None:
            os.close(reader)
    assert res.stdout == ""
    assert identity(special) == was
    if kind == "directory":
        assert listing(special) == ["keep"]
    assert snapshot(regular) == before
    assert listing(out) == names  # no temporary file, nothing else written


@pytest.mark.parametrize("kind", ["device", "fifo"])
def test_special_out_dir_of_run(tmp_path: Path, kind: str) -> None:
    out = tmp_path / "out"
    make_special(out, kind, tmp_path)
    was = identity(out)
    res = cli("run", AJGL, "--out-dir", out, *TINY, "--force")
    line = one_line_error(res, str(out))
    assert "Not a directory" in line
    assert identity(out) == was
    assert listing(tmp_path) == ["out"]


# ------------------------------------------------------------------------------------------
# 2. an input is never an output, even with --force
# ------------------------------------------------------------------------------------------


def alias(path: Path, via: str, folder: Path) -> Path:
    """`path` itself, or a new hard link or symlink to it in `folder`."""
    if via == "same path":
        return path
    link = folder / f"{via.replace(' ', '-')}-to-{path.name}"
    if via == "hard link":
        os.link(path, link)
    else:
        os.symlink(path, link)
    return link


INPUT_CASES = {
    # case -> (its arguments from the inputs {name: path} and the output, the input the
    # output is: itself, a hard link to it or a symlink to it)
    "simulate -o SCENARIO": (lambda i, a: ["simulate", i["scn"], "-o", a, *TINY], "scn"),
    "estimate S -o S": (lambda i, a: ["estimate", i["s"], "-o", a], "s"),
    "estimate S --model M -o M": (
        lambda i, a: ["estimate", i["s"], "--model", i["model"], "-o", a],
        "model",
    ),
    "evaluate S E -o S": (lambda i, a: ["evaluate", i["s"], i["e"], "-o", a], "s"),
    "evaluate S E -o E": (lambda i, a: ["evaluate", i["s"], i["e"], "-o", a], "e"),
    "evaluate --summary E": (
        lambda i, a: ["evaluate", i["s"], i["e"], "-o", i["dir"] / "new.rrd", "--summary", a],
        "e",
    ),
    "evaluate --summary S": (
        lambda i, a: ["evaluate", i["s"], i["e"], "-o", i["dir"] / "new.rrd", "--summary", a],
        "s",
    ),
}


@pytest.mark.parametrize("via", ["same path", "hard link", "symlink"])
@pytest.mark.parametrize("case", sorted(INPUT_CASES))
def test_input_as_output_is_refused_even_with_force(
    base: Path, tmp_path: Path, case: str, via: str
) -> None:
    inputs = {
        "scn": tmp_path / "scn.toml",
        "model": tmp_path / "model.toml",
        "s": tmp_path / "s.mcap",
        "e": tmp_path / "e.mcap",
        "dir": tmp_path,
    }
    shutil.copyfile(AJGL, inputs["scn"])
    shutil.copyfile(AJGL, inputs["model"])
    shutil.copyfile(base / "sensors.mcap", inputs["s"])
    shutil.copyfile(base / "estimates.mcap", inputs["e"])
    make_args, which = INPUT_CASES[case]
    target = alias(inputs[which], via, tmp_path)
    files = [p for k, p in inputs.items() if k != "dir"]
    before, names = snapshot(files), listing(tmp_path)
    res = cli(*make_args(inputs, target), "--force")
    line = one_line_error(res)
    assert line == f"fusionlog: error: {target}: is an input of this command, not an output"
    assert snapshot(files) == before  # byte-identical, not even touched
    assert listing(tmp_path) == names  # no temporary file, not even new.rrd


@pytest.mark.parametrize("via", ["hard link", "symlink"])
@pytest.mark.parametrize("which", ["sensors.mcap", "summary.json"])
def test_run_output_that_is_its_scenario_is_refused(tmp_path: Path, which: str, via: str) -> None:
    scn = tmp_path / "scn.toml"
    shutil.copyfile(AJGL, scn)
    out = tmp_path / "out"
    out.mkdir()
    target = out / which
    if via == "hard link":
        os.link(scn, target)
    else:
        os.symlink(scn, target)
    before, names = snapshot([scn]), listing(out)
    res = cli("run", scn, "--out-dir", out, *TINY, "--force")
    line = one_line_error(res)
    assert line == f"fusionlog: error: {target}: is an input of this command, not an output"
    assert snapshot([scn]) == before
    assert listing(out) == names


@pytest.mark.parametrize("exists", [False, True])
@pytest.mark.parametrize("via", ["same path", "hard link"])
def test_one_file_as_both_outputs_of_evaluate(
    base: Path, tmp_path: Path, via: str, exists: bool
) -> None:
    x = tmp_path / "x"
    if exists or via == "hard link":
        x.write_bytes(b"previous")
    y = alias(x, via, tmp_path)
    before, names = snapshot([x]) if x.exists() else {}, listing(tmp_path)
    s, e = base / "sensors.mcap", base / "estimates.mcap"
    res = cli("evaluate", s, e, "-o", x, "--summary", y, "--force")
    line = one_line_error(res)
    assert line == f"fusionlog: error: {y}: given twice as an output (also {x})"
    assert (snapshot([x]) if x.exists() else {}) == before
    assert listing(tmp_path) == names


# ------------------------------------------------------------------------------------------
# 3. two writers of one target at the same time, without --force
# ------------------------------------------------------------------------------------------


@needs_fusionlog
def test_concurrent_writers_one_wins_the_other_is_refused(tmp_path: Path) -> None:
    """Two `simulate` of one target started together: never both exit 0. Trials go on (3 to
    6) until one has had both writing at once (both temporary files seen), so that the race
    was decided by the commit's no-clobber link, not by the check before writing."""
    args = ["--runs", "10000", "--steps", "20"]
    both_writing = 0
    for trial in range(6):
        if trial >= 3 and both_writing:
            break
        out = tmp_path / f"trial{trial}"
        out.mkdir()
        target = out / "s.mcap"
        seeds = (100 + 2 * trial, 101 + 2 * trial)
        procs = [popen("simulate", AJGL, "-o", target, *args, "--seed", s) for s in seeds]
        try:
            deadline, most = time.monotonic() + TIMEOUT, 0
            while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
                most = max(most, len(temporaries(out)))
                time.sleep(0.002)
            results = [(p, *finish(p)) for p in procs]
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait(timeout=TIMEOUT)
        both_writing += most == 2
        codes = sorted(p.returncode for p, _, _ in results)
        assert codes == [0, 2], [(p.returncode, err) for p, _, err in results]
        (winner,) = [i for i, (p, _, _) in enumerate(results) if p.returncode == 0]
        _, loser_out, loser_err = results[1 - winner]
        assert loser_err.splitlines() == [
            f"fusionlog: error: {target}: exists; use --force to overwrite"
        ]
        assert loser_out == ""
        assert listing(out) == ["s.mcap"]  # the loser's temporary file is gone
        # complete, readable, and entirely the winner's
        res = ok("inspect", target)
        assert f"scenario: ajgl2009 (seed {seeds[winner]})" in res.stdout
        assert "runs: 10000, instants: 21" in res.stdout
        ref = tmp_path / f"ref{trial}.mcap"
        ok("simulate", AJGL, "-o", ref, *args, "--seed", seeds[winner])
        assert_same_arrays(all_arrays(target), all_arrays(ref))
    assert both_writing, "the two writers never overlapped in 6 trials"


# ------------------------------------------------------------------------------------------
# 4. SIGTERM and SIGHUP
# ------------------------------------------------------------------------------------------


@needs_fusionlog
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
@pytest.mark.parametrize("name", ["simulate", "run"])
def test_signal_during_a_long_write_keeps_the_previous_output(
    base: Path, tmp_path: Path, name: str, sig: signal.Signals
) -> None:
    out = tmp_path / "out"
    args, targets = command(name, out, base)
    before = put_previous(targets, base)
    long_args = [a for a in args if a not in TINY] + ["--runs", "600000", "--force"]
    proc = popen(*long_args)
    try:
        deadline = time.monotonic() + 60
        while True:  # until it is writing: its temporary file exists
            tmp = [TEMP.match(n) for n in temporaries(out)]
            if any(m and int(m["pid"]) == proc.pid for m in tmp):
                break
            assert proc.poll() is None, f"ended before the signal: {proc.communicate()}"
            assert time.monotonic() < deadline, "no temporary file after 60 s"
            time.sleep(0.01)
        time.sleep(0.1)
        proc.send_signal(sig)
        stdout, stderr = finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=TIMEOUT)
    assert proc.returncode == 128 + sig, (proc.returncode, stderr)
    assert stderr.splitlines() == ["fusionlog: interrupted; no partial output was left behind"]
    assert stdout == ""
    assert temporaries(out) == []
    assert listing(out) == sorted(t.name for t in targets)
    assert snapshot(targets) == before


# ------------------------------------------------------------------------------------------
# 5. temporary files left by a killed process
# ------------------------------------------------------------------------------------------


def stale_warning(p: Path) -> str:
    return (
        f"fusionlog: warning: {p} is a temporary file left by a killed fusionlog run "
        f"(its process is gone); remove it with: rm -- {shlex.quote(str(p))}"
    )


def test_stale_temporaries_are_reported_and_never_deleted(base: Path, tmp_path: Path) -> None:
    out = tmp_path / "out 'dir'"  # a space and quotes: the suggested command must still work
    targets = command("run", out, base)[1]
    put_previous(targets, base)
    dead = dead_pid()
    stale = [
        out / f".sensors.mcap.fusionlog-{dead}-abcdef.tmp",
        out / f".summary.json.fusionlog-{dead}-0a1b2c.tmp",
    ]
    others = [
        out / ".estimates.mcap.fusionlog-1-abcdef.tmp",  # pid 1 is alive: maybe being written
        out / ".evaluation.rrd.fusionlog-x-abcdef.tmp",  # not our pattern
        out / f".unrelated.fusionlog-{dead}-abcdef.tmp",  # beside no output of this command
        out / f"sensors.mcap.fusionlog-{dead}-abcdef.tmp",  # not hidden: not ours
    ]
    for i, p in enumerate(stale + others):
        p.write_bytes(f"somebody's file {i}".encode())
    planted = snapshot(stale + others)

    res = ok("run", AJGL, "--out-dir", out, *TINY, "--force")
    assert res.stderr.splitlines() == [stale_warning(p) for p in stale]
    assert snapshot(stale + others) == planted  # reported, not deleted

    res = ok("inspect", out / "sensors.mcap")
    assert res.stderr.splitlines() == [stale_warning(stale[0])]
    assert "scenario: ajgl2009" in res.stdout
    assert snapshot(stale + others) == planted

    # the suggested command removes exactly that file
    cmd = stale_warning(stale[0]).split("remove it with: ", 1)[1]
    subprocess.run(["sh", "-c", cmd], check=True, timeout=TIMEOUT)
    assert not stale[0].exists()
    assert snapshot(stale[1:] + others) == {k: v for k, v in planted.items() if k != str(stale[0])}
    assert snapshot(targets)  # the outputs are still there


@pytest.mark.skipif(not hasattr(os, "POSIX_FADV_DONTNEED"), reason="no writeback advice")
def test_outputs_are_handed_to_the_disk_as_they_are_written(tmp_path: Path, monkeypatch) -> None:
    """Every WRITEBACK_STEP bytes, an output's new range is handed to the disk (Linux:
    POSIX_FADV_DONTNEED starts its writeback), each byte once and in order, so the commit's
    fsync has little left; the file is what was written, a range rewritten in place included,
    and stays in memory for a reader that follows."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the advice starts the writeback on Linux only")
    calls: list[tuple[int, int]] = []
    real = os.posix_fadvise

    def spy(fd: int, offset: int, length: int, advice: int) -> None:
        assert advice == os.POSIX_FADV_DONTNEED
        calls.append((offset, length))
        real(fd, offset, length, advice)

    monkeypatch.setattr(atomic.os, "posix_fadvise", spy)
    target = tmp_path / "out.bin"
    data = os.urandom(3 * atomic.WRITEBACK_STEP + 1_000_000)
    with atomic.Outputs([target]) as outs:
        f = outs.open(target)
        for i in range(0, len(data), 300_000):
            f.write(data[i : i + 300_000])
        f.seek(10)  # a header patched in place, as the MCAP writer does with its chunks
        f.write(b"patched!")
        f.seek(0, os.SEEK_END)
        outs.commit()
    assert target.read_bytes() == data[:10] + b"patched!" + data[18:]
    assert len(calls) == 3
    assert [c[0] for c in calls] == [0, sum(calls[0]), sum(calls[1])]  # contiguous, once each
    assert sum(calls[-1]) <= len(data)


# ------------------------------------------------------------------------------------------
# 6. injected write failures, in-process
# ------------------------------------------------------------------------------------------


class FailsAfter:
    """A file whose writes fail with `err` once `limit` bytes are written (what write(2) does
    on a full disk: the bytes that fit are written, then the error)."""

    def __init__(self, f, limit: int | None, err: int) -> None:
        self._f, self.limit, self.err = f, limit, err
        self.written, self.fired = 0, False

    def write(self, data) -> int:
        n = memoryview(data).nbytes
        if self.limit is not None and self.written + n > self.limit:
            room = self.limit - self.written
            if room > 0:
                self._f.write(bytes(memoryview(data).cast("B")[:room]))
                self.written += room
            self.fired = True
            raise OSError(self.err, os.strerror(self.err))
        self.written += n
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)


class Injector:
    """Replaces `open` in fusionlog.io.atomic (the one place every output's file is opened:
    `Outputs.open`): the `which`-th file opened fails after `limit` bytes."""

    def __init__(self, which: int, limit: int, err: int) -> None:
        self.which, self.limit, self.err = which, limit, err
        self.files: list[tuple[Path, FailsAfter]] = []

    def open(self, path, mode="r", *args, **kw):
        f = FailsAfter(
            open(path, mode, *args, **kw),  # noqa: SIM115 - closed by its owner
            self.limit if len(self.files) == self.which else None,
            self.err,
        )
        self.files.append((Path(path), f))
        return f

    def target(self) -> Path:
        """The output whose temporary file failed."""
        path, f = self.files[self.which]
        assert f.fired, f"no failure injected: {f.written} bytes written"
        m = TEMP.match(path.name)
        assert m, path
        return path.parent / m["name"]


FAULT_CASES = [
    (name, which, at)
    for name, n in [
        ("simulate", 1),
        ("estimate", 1),
        ("evaluate", 1),
        ("evaluate --summary", 2),
        ("run", 4),
    ]
    for which in range(n)
    for at in (["0", "100", "half", "end"] if n == 1 or which == n - 1 else ["0", "half"])
]


def limit_of(at: str, size: int) -> int:
    """Bytes written before the failure; "end" is in the last 1 % (recordings vary in size
    by a few hundred bytes from one run to the next: Rerun's chunk ids and timestamps)."""
    return {"0": 0, "100": 100, "half": size // 2, "end": size - max(100, size // 100)}[at]


def assert_failed_cleanly(res, line: str, out: Path, before: dict, targets: list[Path]) -> None:
    got = one_line_error(res)
    assert got == line
    assert res.stdout == ""
    assert snapshot(targets) == before  # every previous output byte-identical: all or none
    assert listing(out) == sorted(t.name for t in targets)  # no temporary file


@pytest.mark.parametrize(("name", "which", "at"), FAULT_CASES)
def test_enospc_after_n_bytes(
    base: Path, tmp_path: Path, monkeypatch, name: str, which: int, at: str
) -> None:
    out = tmp_path / "out"
    args, targets = command(name, out, base)
    before = put_previous(targets, base)
    size = len(before[str(targets[which])][1])
    inj = Injector(which, limit_of(at, size), errno.ENOSPC)
    monkeypatch.setattr(atomic, "open", inj.open, raising=False)
    res = cli(*args, "--force")
    target = inj.target()
    assert target == targets[which]
    line = f"fusionlog: error: {target}: cannot write: No space left on device"
    assert_failed_cleanly(res, line, out, before, targets)


@pytest.mark.parametrize("name", COMMANDS)
@pytest.mark.parametrize("force", [False, True])
def test_erofs_on_the_last_output(
    base: Path, tmp_path: Path, monkeypatch, name: str, force: bool
) -> None:
    """EROFS at the first write of the last output: with --force the previous outputs stay,
    without it (fresh targets) the folder stays empty."""
    out = tmp_path / "out"
    out.mkdir()
    args, targets = command(name, out, base)
    before = put_previous(targets, base) if force else {}
    inj = Injector(len(targets) - 1, 0, errno.EROFS)
    monkeypatch.setattr(atomic, "open", inj.open, raising=False)
    res = cli(*args, *(["--force"] if force else []))
    line = f"fusionlog: error: {targets[-1]}: cannot write: Read-only file system"
    if force:
        assert_failed_cleanly(res, line, out, before, targets)
    else:
        assert one_line_error(res) == line
        assert listing(out) == []


@pytest.mark.parametrize("name", COMMANDS)
def test_a_failed_command_leaves_no_folder_it_made(
    base: Path, tmp_path: Path, monkeypatch, name: str
) -> None:
    """Outputs into folders that did not exist: a failure removes the empty folders made for
    them too (they were left behind, e.g. by `estimate -o new/e.mcap --arch BOGUS`)."""
    out = tmp_path / "new" / "deeper"
    args, targets = command(name, out, base)
    inj = Injector(len(targets) - 1, 0, errno.EROFS)
    monkeypatch.setattr(atomic, "open", inj.open, raising=False)
    res = cli(*args)
    assert one_line_error(res) == (
        f"fusionlog: error: {targets[-1]}: cannot write: Read-only file system"
    )
    assert listing(tmp_path) == []


def test_bad_usage_after_the_outputs_were_claimed_leaves_no_folder(
    base: Path, tmp_path: Path
) -> None:
    new = tmp_path / "new"
    res = cli("estimate", base / "sensors.mcap", "-o", new / "e.mcap", "--arch", "BOGUS")
    one_line_error(res, "BOGUS")
    res = cli("run", ROOT / "pipeline" / "aircraft_identity.toml", "--out-dir", new / "a" / "b",
              "--filter", "UKF")  # fmt: skip
    one_line_error(res, "--filter")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("name", COMMANDS)
def test_eio_at_fsync_of_the_last_output(base: Path, tmp_path: Path, monkeypatch, name) -> None:
    """Every byte written, then fsync fails (a lost write-back): nothing is committed."""
    out = tmp_path / "out"
    args, targets = command(name, out, base)
    before = put_previous(targets, base)
    real = os.fsync
    failed: list[str] = []

    def fsync(fd: int) -> None:
        name = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        m = TEMP.match(name)
        if m and m["name"] == targets[-1].name:
            failed.append(name)
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    res = cli(*args, "--force")
    assert failed
    line = f"fusionlog: error: {targets[-1]}: cannot write: Input/output error"
    assert_failed_cleanly(res, line, out, before, targets)


@pytest.mark.parametrize("name", ["evaluate --summary", "run"])
@pytest.mark.parametrize("force", [False, True])
def test_commit_failure_of_the_last_output_rolls_back_the_others(
    base: Path, tmp_path: Path, monkeypatch, name: str, force: bool
) -> None:
    """Several outputs are committed all or none: the last one's link (fresh target) or
    replace (--force) fails after the others were moved into place; they are put back."""
    out = tmp_path / "out"
    out.mkdir()
    args, targets = command(name, out, base)
    before = put_previous(targets, base) if force else {}
    last = targets[-1]
    real_link, real_replace = os.link, os.replace
    failed: list[str] = []

    def link(src, dst, *a, **kw):
        if Path(dst) == last and not os.path.lexists(dst):
            failed.append("link")
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        return real_link(src, dst, *a, **kw)

    def replace(src, dst, *a, **kw):
        if Path(dst) == last:
            failed.append("replace")
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        return real_replace(src, dst, *a, **kw)

    monkeypatch.setattr(atomic.os, "link", link)
    monkeypatch.setattr(atomic.os, "replace", replace)
    res = cli(*args, *(["--force"] if force else []))
    assert failed == ["replace" if force else "link"]
    line = f"fusionlog: error: {last}: cannot commit: Input/output error"
    if force:
        assert_failed_cleanly(res, line, out, before, targets)
    else:
        assert one_line_error(res) == line
        assert listing(out) == []  # the outputs committed before it were removed again


@pytest.mark.parametrize("name", COMMANDS)
def test_read_only_file_system(base: Path, tmpfs, name: str) -> None:
    """A real read-only mount (chmod does not stop root): refused at the temporary file."""
    mnt = tmpfs("4m")
    args, targets = command(name, mnt, base)
    before = put_previous(targets, base)
    r = subprocess.run(
        ["mount", "-o", "remount,ro", str(mnt)], capture_output=True, timeout=30, check=False
    )
    if r.returncode != 0:
        pytest.skip(f"cannot remount read-only: {r.stderr.decode(errors='replace').strip()}")
    res = cli(*args, "--force")
    line = f"fusionlog: error: {targets[0]}: cannot write in {mnt}: Read-only file system"
    assert_failed_cleanly(res, line, mnt, before, targets)


# ------------------------------------------------------------------------------------------
# 7. a full disk, real processes
# ------------------------------------------------------------------------------------------


@needs_fusionlog
@pytest.mark.parametrize(("size", "previous"), [("300k", True), ("600k", False)])
@pytest.mark.parametrize("name", ["evaluate --summary", "run"])
def test_full_tmpfs(base: Path, tmpfs, name: str, size: str, previous: bool) -> None:
    """The recording (about 1 MB) does not fit: exit 2 within the timeout, one line naming it,
    no temporary file, and the small previous outputs kept (or nothing, if there were none)."""
    mnt = tmpfs(size)
    args, targets = command(name, mnt, base)
    before = {}
    if previous:
        for t in targets:
            t.write_bytes(f"previous {t.name}".encode())
        before = snapshot(targets)
        args = [*args, "--force"]
    t0 = time.monotonic()
    p = run_proc(*args)  # timeout=120: a hang fails the test
    assert time.monotonic() - t0 < TIMEOUT
    assert p.returncode == 2, p.stderr
    rrd = next(t for t in targets if t.suffix == ".rrd")
    assert p.stderr.splitlines() == [
        f"fusionlog: error: {rrd}: cannot write: No space left on device"
    ]
    assert p.stdout == ""
    if previous:
        assert snapshot(targets) == before
        assert listing(mnt) == sorted(t.name for t in targets)
    else:
        assert listing(mnt) == []
