"""MCAP layer, faults: damaged inputs (truncated, flipped bytes anywhere: chunk, metadata,
index, summary), wrong inputs, writer misuse, and failing outputs (an injected ENOSPC, a
full tmpfs, an exception or a signal while writing) through fusionlog.io.atomic.Outputs."""

from __future__ import annotations

import errno
import io
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap_helpers import make_data, mcap_writer, sample_file, write_file

import fusionlog
from fusionlog.errors import DamagedFile, FusionlogError, OutputError, OutputExists
from fusionlog.io.mcap import McapFile, McapWriter, recover


@pytest.fixture()
def sample(tmp_path):
    return sample_file(tmp_path / "s.mcap")


# ------------------------------------------------------------------------------------------
# damaged and wrong inputs
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cut", ["half", "footer"])
def test_truncated_file_error_and_recover(tmp_path, sample, cut):
    raw = sample.read_bytes()
    bad = tmp_path / f"cut_{cut}.mcap"
    bad.write_bytes(raw[: len(raw) // 2] if cut == "half" else raw[:-20])
    with pytest.raises(DamagedFile) as e:
        McapFile(bad)
    msg = str(e.value)
    assert "truncated" in msg and str(bad) in msg and "\n" not in msg
    assert e.value.path == bad and "--recover" not in msg  # the CLI adds how to look further
    rec = recover(bad)
    full = McapFile(sample).topics
    assert rec["error"] is not None
    assert set(rec["topics"]) == set(full)
    assert rec["metadata"]["fusionlog.provenance"] == {"seed": "1"}
    assert rec["steps"] == 10
    if cut == "half":
        assert all(0 < rec["topics"][t] < full[t] for t in full)
        assert 0 < rec["complete_runs"] < 40 and rec["complete_runs"] % 5 == 0
    else:
        assert rec["topics"] == full and rec["complete_runs"] == 40
        assert rec["last_complete_step"] == 9
    assert 0 <= rec["last_complete_step"] <= 9


def test_recover_on_intact_file(sample):
    rec = recover(sample)
    assert rec["error"] is None and rec["topics"] == McapFile(sample).topics
    assert rec["complete_runs"] == 40 and rec["last_complete_step"] == 9
    assert rec["library"].startswith("foxglove-sdk")  # McapWriter writes through the SDK


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_corrupt_chunk_is_reported(tmp_path, compression):
    truth, sens, mean = make_data(5, 40, 10)
    path = tmp_path / "s.mcap"
    covs = [np.eye(2)[None].repeat(10, 0)] * 8
    write_file(path, truth, sens, mean, covs, 5, compression=compression, chunk_size=4096)
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        first = make_reader(f).get_summary().chunk_indexes[0]
    raw = bytearray(path.read_bytes())
    i = first.chunk_start_offset + first.chunk_length // 2  # inside the chunk's record data
    raw[i : i + 40] = bytes(b ^ 0x5A for b in raw[i : i + 40])
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(raw))
    with pytest.raises(DamagedFile, match="corrupt") as e:
        McapFile(bad).read_all(["/truth"])
    assert str(bad) in str(e.value) and "\n" not in str(e.value) and e.value.path == bad


def test_not_mcap_missing_and_empty(tmp_path):
    txt = tmp_path / "notes.mcap"
    txt.write_text("hello, this is not an MCAP file at all\n")
    with pytest.raises(FusionlogError, match="not an MCAP file") as e:
        McapFile(txt)
    assert str(txt) in str(e.value)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(FusionlogError, match="not an MCAP file"):
        McapFile(empty)
    with pytest.raises(FusionlogError, match="no such file") as e:
        McapFile(tmp_path / "missing.mcap")
    assert "missing.mcap" in str(e.value)
    with pytest.raises(FusionlogError, match="directory"):
        McapFile(tmp_path)
    with pytest.raises(FusionlogError, match="no such file"):
        recover(tmp_path / "missing.mcap")


def test_writer_rejects_misuse(tmp_path):
    with pytest.raises(TypeError, match="file object"):
        McapWriter(tmp_path / "w.mcap")  # a path: the owner of the output opens it
    with mcap_writer(tmp_path / "w.mcap") as w:
        w.write_values("/truth", 0, 0.0, 0, np.zeros((2, 1)))
        with pytest.raises(ValueError, match="twice"):
            w.write_values("/truth", 0, 0.0, 0, np.zeros((2, 1)))
        with pytest.raises(ValueError, match="runs"):
            w.write_values("/truth", 1, 0.1, 0, np.zeros((3, 1)))
        with pytest.raises(ValueError, match="expected 2"):
            w.write_values("/truth", 0, 0.0, 5, np.zeros((2, 1)))
        with pytest.raises(ValueError, match="dim"):
            w.write_values("/truth", 1, 0.1, 0, np.zeros((2, 3)))
        with pytest.raises(ValueError, match="written as values"):
            w.write_estimate("/truth", 1, 0.1, 0, np.zeros((2, 1)), np.eye(1))
        with pytest.raises(ValueError, match="time"):
            w.write_values("/truth", 1, -1.0, 0, np.zeros((2, 1)))
        with pytest.raises(ValueError, match="cov"):
            w.write_estimate("/e", 0, 0.0, 0, np.zeros((2, 2)), np.eye(3))
        with pytest.raises(TypeError):
            w.add_metadata("m", {"a": 1})  # type: ignore[dict-item]
    assert McapFile(tmp_path / "w.mcap").topics == {"/truth": 1}


# ------------------------------------------------------------------------------------------
# atomic output
# ------------------------------------------------------------------------------------------


def test_existing_output_is_refused_before_anything_happens(tmp_path, sample):
    before = sample.read_bytes()
    mtime = sample.stat().st_mtime_ns
    listing = sorted(os.listdir(sample.parent))
    with pytest.raises(OutputExists) as e:
        with mcap_writer(sample):
            pass
    assert str(e.value) == f"{sample}: exists"  # the CLI adds "; use --force to overwrite"
    assert sample.read_bytes() == before and sample.stat().st_mtime_ns == mtime
    assert sorted(os.listdir(sample.parent)) == listing
    with mcap_writer(sample, force=True) as w:
        w.write_values("/truth", 0, 0.0, 0, np.ones((1, 1)))
    assert McapFile(sample).topics == {"/truth": 1}
    assert sorted(os.listdir(sample.parent)) == listing


@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt])
def test_exception_inside_with_leaves_nothing(tmp_path, exc):
    out = tmp_path / "new" / "deeper" / "out.mcap"
    with pytest.raises(exc):
        with mcap_writer(out) as w:
            w.write_values("/truth", 0, 0.0, 0, np.ones((1, 1)))
            assert len(list(out.parent.iterdir())) == 1  # the temp file, next to the target
            raise exc()
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # nor the folders made for it


def test_clean_write_creates_parent_and_leaves_no_temp(tmp_path):
    out = tmp_path / "a" / "b" / "x.mcap"
    with mcap_writer(out) as w:
        w.write_values("/truth", 0, 0.0, 0, np.ones((1, 1)))
    assert [p.name for p in out.parent.iterdir()] == ["x.mcap"]
    mode = out.stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask


def test_any_file_object_with_write_seek_flush(tmp_path):
    """Not only CheckedFile: an in-memory buffer, or a plain file opened by the caller."""
    buf = io.BytesIO()
    with McapWriter(buf) as w:
        w.write_values("/truth", 0, 0.0, 0, np.ones((2, 1)))
    path = tmp_path / "mem.mcap"
    path.write_bytes(buf.getvalue())
    assert McapFile(path).read_all(["/truth"])["/truth"].shape == (2, 1, 1)
    plain = tmp_path / "plain.mcap"
    with open(plain, "wb") as fh, McapWriter(fh) as w:
        w.write_values("/truth", 0, 0.0, 0, np.ones((2, 1)))
    assert McapFile(plain).topics == {"/truth": 1}


# ------------------------------------------------------------------------------------------
# CRCs: one changed byte anywhere is an error
# ------------------------------------------------------------------------------------------

SCENARIO_TOML = "[scenario]\nname = 't'\n[model]\nkind = 'constant-velocity'\nn0 = 0.16\n"


def _with_scenario(path, **kw):
    truth, sens, mean = make_data(5, 6, 4)
    with mcap_writer(path, **kw) as w:
        w.add_metadata("fusionlog.scenario", {"toml": SCENARIO_TOML, "steps": "3"})
        for o in (0, 3):
            for k in range(4):
                w.write_values("/truth", k, k * 0.5, o, truth[o : o + 3, k])
                w.write_values("/sensors/a", k, k * 0.5, o, sens[o : o + 3, k])
    return path


def test_changed_byte_in_metadata_is_caught(tmp_path):
    """Issue 12 (8): n0 = 0.16 -> 0.96 in the scenario metadata used to give another model."""
    good = _with_scenario(tmp_path / "s.mcap")
    raw = good.read_bytes()
    assert raw.count(b"n0 = 0.16") == 1
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(raw.replace(b"n0 = 0.16", b"n0 = 0.96"))
    with pytest.raises(DamagedFile) as e:
        McapFile(bad)
    msg = str(e.value)
    assert msg.startswith(f"{bad}: ") and "data section CRC" in msg and "\n" not in msg
    assert e.value.path == bad
    rec = recover(bad)  # every record still reads; the damage is named
    assert rec["error"] is not None and "crc" in rec["error"].lower()
    assert rec["topics"] == McapFile(good).topics


def test_cli_names_the_damaged_file_and_how_to_look_further(tmp_path):
    from click.testing import CliRunner

    from fusionlog.cli import main

    raw = _with_scenario(tmp_path / "s.mcap").read_bytes()
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(raw.replace(b"n0 = 0.16", b"n0 = 0.96"))
    res = CliRunner().invoke(main, ["inspect", str(bad)])
    assert res.exit_code == 2
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"fusionlog: error: {bad}: corrupt MCAP")
    assert lines[0].endswith(f"; `fusionlog inspect --recover {bad}` shows what is still readable")


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_every_single_changed_byte_is_an_error(tmp_path, compression):
    """Flip each byte of a small file (several chunks, metadata, indexes, summary) in turn:
    opening and reading every topic raises, DamagedFile but for the leading magic bytes."""
    good = _with_scenario(tmp_path / "s.mcap", compression=compression, chunk_size=400)
    raw = good.read_bytes()
    topics = ["/truth", "/sensors/a"]
    clean = McapFile(good).read_all(topics)
    bad = tmp_path / "bad.mcap"
    silent = []
    for i in range(len(raw)):
        b = bytearray(raw)
        b[i] ^= 0x10
        bad.write_bytes(bytes(b))
        try:
            got = McapFile(bad).read_all(topics)
        except DamagedFile:
            continue
        except FusionlogError:
            assert i < 8, i  # "not an MCAP file"
            continue
        same = all(np.array_equal(got[t], clean[t], equal_nan=True) for t in topics)
        silent.append((i, same))
    assert silent == [], f"{len(raw)} bytes, read without error after a flip at {silent[:10]}"


# ------------------------------------------------------------------------------------------
# failing outputs: the first failed write stops the writer with one error, nothing left
# ------------------------------------------------------------------------------------------


class _FailsAfter:
    """A binary file that raises ENOSPC once ``limit`` bytes are written (write layer
    injection: what a full disk does to write(2))."""

    def __init__(self, f, limit: int) -> None:
        self._f, self.limit, self.written, self.calls = f, limit, 0, 0

    def write(self, data) -> int:
        self.calls += 1
        if self.written + len(data) > self.limit:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.written += len(data)
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)


@pytest.mark.parametrize("limit", [0, 100, 50_000, 400_000])
def test_injected_enospc_gives_one_error_and_leaves_nothing(tmp_path, monkeypatch, capfd, limit):
    import fusionlog.io.atomic as atomic

    injected: list[_FailsAfter] = []

    def failing_open(path, mode="r", *a, **kw):
        f = _FailsAfter(open(path, mode, *a, **kw), limit)  # noqa: SIM115
        injected.append(f)
        return f

    monkeypatch.setattr(atomic, "open", failing_open, raising=False)
    out = tmp_path / "out" / "s.mcap"
    v = np.random.default_rng(0).normal(size=(100, 4))
    written = 0
    with pytest.raises(OutputError) as e:
        with mcap_writer(out, chunk_size=64 * 1024) as w:
            for k in range(2000):  # 6.4 MB in all
                w.write_values("/truth", k, k * 0.1, 0, v)
                written += 1
    assert str(e.value) == f"{out}: cannot write: No space left on device"
    assert not out.parent.exists()  # no temporary file, no target, nor the folder made for them
    # stopped at the first failure: within about a chunk of messages, one failing write
    assert written * v.nbytes <= limit + 2 * 64 * 1024
    assert injected[0].written <= limit
    err = capfd.readouterr().err
    assert err == "", err  # the Rust writer printed nothing


def test_error_after_the_last_message_is_caught_at_close(tmp_path, monkeypatch):
    """The summary and footer are written at close: a failure there is the same one error."""
    import fusionlog.io.atomic as atomic

    monkeypatch.setattr(
        atomic,
        "open",
        lambda p, m="r": _FailsAfter(open(p, m), 3000),
        raising=False,  # noqa: SIM115
    )
    out = tmp_path / "s.mcap"
    with pytest.raises(OutputError, match="No space left on device"):
        with mcap_writer(out) as w:  # 1 MB chunks: everything is written at close
            for k in range(10):
                w.write_values("/truth", k, k * 0.1, 0, np.ones((10, 2)))
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("exc", [KeyboardInterrupt, MemoryError])
def test_exception_inside_the_file_object_reaches_the_caller(tmp_path, monkeypatch, exc):
    """An exception raised in write() while Rust calls it is not swallowed by the Rust side."""
    import fusionlog.io.atomic as atomic

    class Raises(_FailsAfter):
        def write(self, data):
            if self.written + len(data) > self.limit:
                raise exc()
            return super().write(data)

    monkeypatch.setattr(atomic, "open", lambda p, m="r": Raises(open(p, m), 5000), raising=False)  # noqa: SIM115
    out = tmp_path / "s.mcap"
    with pytest.raises(exc):
        with mcap_writer(out, chunk_size=1024) as w:
            for k in range(1000):
                w.write_values("/truth", k, k * 0.1, 0, np.ones((10, 2)))
    assert os.listdir(tmp_path) == []


def test_signal_during_a_write_is_delivered_after_it(tmp_path, monkeypatch):
    """SIGINT handled inside a write the Rust writer called: deferred, not lost, and raised
    from the writer's call once Rust has returned; the write itself completes."""
    import fusionlog.io.atomic as atomic

    class Interrupts(_FailsAfter):
        def write(self, data):
            n = self._f.write(data)  # completes
            self.written += n
            if self.written > self.limit and not getattr(self, "sent", False):
                self.sent = True
                os.kill(os.getpid(), signal.SIGINT)  # its handler runs in this frame
            return n

    monkeypatch.setattr(
        atomic,
        "open",
        lambda p, m="r": Interrupts(open(p, m), 20_000),
        raising=False,  # noqa: SIM115
    )
    out = tmp_path / "s.mcap"
    written = 0
    with pytest.raises(KeyboardInterrupt):
        with mcap_writer(out, chunk_size=1024) as w:
            for k in range(1000):
                w.write_values("/truth", k, k * 0.1, 0, np.ones((10, 2)))
                written += 1
    assert 0 < written < 1000
    assert os.listdir(tmp_path) == []
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # guard removed


@pytest.fixture()
def full_tmpfs(tmp_path):
    """A 300 kB tmpfs of our own under tmp_path (skipped where mounting is not allowed)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    try:
        r = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(mnt)],
            capture_output=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        pytest.skip("cannot run mount")
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {r.stderr.decode(errors='replace').strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=10, check=False)


def test_full_disk(full_tmpfs):
    out = full_tmpfs / "s.mcap"
    with pytest.raises(OutputError) as e:
        with mcap_writer(out, chunk_size=64 * 1024) as w:
            for k in range(100):  # 3.2 MB into 300 kB
                w.write_values("/truth", k, k * 0.1, 0, np.ones((4000, 1)))
    assert str(e.value) == f"{out}: cannot write: No space left on device"
    assert os.listdir(full_tmpfs) == []


def test_full_disk_cli_simulate_one_line(full_tmpfs):
    """The whole command: exit 2, one line naming the file and the OS error, nothing left,
    within seconds (no hang)."""
    out = full_tmpfs / "s.mcap"
    scenario = Path(__file__).resolve().parents[1] / "pipeline" / "ajgl2009.toml"
    env = {**os.environ, "PYTHONPATH": str(Path(fusionlog.__file__).resolve().parents[1])}
    p = subprocess.run(
        [sys.executable, "-m", "fusionlog.cli", "simulate", str(scenario), "-o", str(out)]
        + ["--runs", "20000"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        check=False,
    )
    assert p.returncode == 2, p.stderr
    assert p.stderr.splitlines() == [
        f"fusionlog: error: {out}: cannot write: No space left on device"
    ]
    assert os.listdir(full_tmpfs) == []
