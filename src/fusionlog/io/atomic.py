"""One way to write an output (DESIGN.md, "Outputs never lose data").

Every output of every command goes through :class:`Outputs`:

1. **Before anything is written**, each target is checked: it must not be one of the command's
   inputs (same file, by device and inode), nor a device, FIFO, socket or directory (even with
   ``force``), nor exist unless ``force``; two outputs of one command must differ.
2. Each output is written to a temporary file beside its target (same file system, so the
   commit is a link or a rename), through :class:`CheckedFile`, which turns the first failed
   write (disk full, I/O error) into an :class:`OutputError` naming the target and the OS error.
3. ``commit()`` fsyncs every temporary file, then moves all of them into place together:
   without ``force`` by ``os.link`` (which fails if the target appeared meanwhile: no race
   between the check and the commit can clobber another writer's file), with ``force`` by
   ``os.replace`` after keeping a link to the old file. If any commit step fails, the targets
   already committed are put back as they were: several outputs are committed all or none.
4. On any error (or KeyboardInterrupt / SIGTERM, see :func:`stale_temporaries` for what a
   SIGKILL leaves) the temporary files are deleted.

Temporary files are named ``.<target name>.fusionlog-<pid>-<random>.tmp``, so that a file left
behind by a killed process can be recognised (its process is gone) and reported.
"""

from __future__ import annotations

import errno
import os
import secrets
import stat
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import BinaryIO

from fusionlog.errors import OutputError, OutputExists

__all__ = [
    "CheckedFile",
    "Outputs",
    "check_target",
    "same_file",
    "stale_temporaries",
    "write_bytes",
]

_TAG = ".fusionlog-"
#: Bytes written between two hand-overs to the disk (`CheckedFile.write`); Linux only, where
#: POSIX_FADV_DONTNEED starts the writeback of dirty pages and leaves them cached.
WRITEBACK_STEP = 8 << 20
_DONTNEED = getattr(os, "POSIX_FADV_DONTNEED", None) if sys.platform.startswith("linux") else None


def _strerror(e: OSError) -> str:
    return e.strerror or str(e)


def _stat(path: Path) -> os.stat_result | None:
    try:
        return os.stat(path)
    except FileNotFoundError:
        return None
    except OSError as e:
        raise OutputError(f"{path}: cannot check the output: {_strerror(e)}") from None


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def same_file(a: os.stat_result, b: os.stat_result) -> bool:
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def check_target(path: Path, *, force: bool, inputs: Iterable[Path] = ()) -> None:
    """Refuse an output that is an input, a non-regular file, or exists without ``force``."""
    st = _stat(path)
    if st is None:
        return
    for p in inputs:
        ist = _stat(Path(p))
        if ist is not None and same_file(st, ist):
            raise OutputError(f"{path}: is an input of this command, not an output")
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{path}: is {_kind(st.st_mode)}; outputs are regular files")
    if not force:
        raise OutputExists(f"{path}: exists")


class CheckedFile:
    """A binary file whose first failed write raises OutputError (path and OS error).

    Writers that cannot propagate an exception themselves (a Rust writer calling ``write``)
    leave it in ``error``; their owner checks it and raises it after each call.
    """

    def __init__(self, target: Path, tmp: Path, f: BinaryIO) -> None:
        self.target, self.tmp, self._f = target, tmp, f
        self.error: OutputError | None = None
        self.written = 0
        self._handed = self._pending = 0  # file bytes handed to the disk; written since

    def _fail(self, e: OSError, what: str) -> OutputError:
        if self.error is None:
            self.error = OutputError(f"{self.target}: cannot {what}: {_strerror(e)}")
        return self.error

    def write(self, data: bytes | bytearray | memoryview) -> int:
        if self.error is not None:
            raise self.error
        try:
            n = self._f.write(data)
        except OSError as e:
            raise self._fail(e, "write") from None
        self.written += n
        self._pending += n
        if self._pending >= WRITEBACK_STEP and _DONTNEED is not None:
            self._hand_over()
        return n

    def _hand_over(self) -> None:
        """Start writing to the disk what was written since the last call, instead of all of
        it at the commit's fsync, which then waits for the last few MB only (50 MB of
        estimates: 25 -> 3 ms): POSIX_FADV_DONTNEED on the new range starts the writeback
        of its dirty pages, which Linux keeps cached (a later reader finds them in memory).
        Advice only, its errors ignored: the fsync at the commit is what makes the file
        durable, whatever was rewritten meanwhile (a chunk header patched in place)."""
        self._pending = 0
        try:
            self._f.flush()
        except OSError as e:
            raise self._fail(e, "write") from None
        try:
            fd = self._f.fileno()
            end = os.fstat(fd).st_size
            if end > self._handed:
                os.posix_fadvise(fd, self._handed, end - self._handed, _DONTNEED)
                self._handed = end
        except (OSError, ValueError, AttributeError):
            pass

    def flush(self) -> None:
        if self.error is not None:
            raise self.error
        try:
            self._f.flush()
        except OSError as e:
            raise self._fail(e, "write") from None

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def raise_error(self) -> None:
        """Raise the first write error, if any (for writers that swallow exceptions)."""
        if self.error is not None:
            raise self.error

    def close(self) -> None:
        """Flush, fsync and close; raises the first error of any of them."""
        if self._f.closed:
            self.raise_error()
            return
        try:
            self.flush()
            try:
                os.fsync(self._f.fileno())
            except OSError as e:
                raise self._fail(e, "write") from None
        finally:
            try:
                self._f.close()
            except OSError as e:
                self._fail(e, "write")
        self.raise_error()

    def discard(self) -> None:
        try:
            self._f.close()
        except OSError:
            pass


def _temp_name(target: Path) -> Path:
    return target.parent / f".{target.name}{_TAG}{os.getpid()}-{secrets.token_hex(4)}.tmp"


class Outputs:
    """The outputs of one command, written to temporary files and committed together.

    Use as a context manager; call :meth:`open` (or :meth:`temp_path`) per target, write, and
    :meth:`commit` at the end. Leaving the block without a commit (an error, Ctrl-C) deletes
    every temporary file, and the folders made for them, and leaves the targets as they were.
    """

    def __init__(
        self, targets: Sequence[Path], *, force: bool = False, inputs: Iterable[Path] = ()
    ) -> None:
        self.force = force
        self.targets = [Path(t) for t in targets]
        self.inputs = [Path(p) for p in inputs]
        seen: dict[tuple[int, int] | str, Path] = {}
        for t in self.targets:
            key: tuple[int, int] | str = os.path.abspath(t)
            st = _stat(t)
            if st is not None:
                key = (st.st_dev, st.st_ino)
            if key in seen:
                raise OutputError(f"{t}: given twice as an output (also {seen[key]})")
            seen[key] = t
            check_target(t, force=force, inputs=self.inputs)
        self._tmp: dict[Path, Path] = {}
        self._files: dict[Path, CheckedFile] = {}
        self._made: list[Path] = []  # folders temp_path created, deepest first

    def __enter__(self) -> Outputs:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.abort()

    def temp_path(self, target: Path) -> Path:
        """Claim (O_EXCL, mode 0666 less the umask) a temporary file beside ``target``."""
        target = Path(target)
        if target not in self.targets:
            raise ValueError(f"{target} is not one of the outputs {self.targets}")
        if target in self._tmp:
            return self._tmp[target]
        missing = [d for d in (target.parent, *target.parent.parents) if not d.exists()]
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            self._made += [d for d in missing if d not in self._made]
        except OSError as e:
            raise OutputError(
                f"{target}: cannot create folder {target.parent}: {_strerror(e)}"
            ) from None
        for _ in range(100):
            tmp = _temp_name(target)
            try:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            except FileExistsError:
                continue
            except OSError as e:
                raise OutputError(
                    f"{target}: cannot write in {target.parent}: {_strerror(e)}"
                ) from None
            self._tmp[target] = tmp
            return tmp
        raise OutputError(f"{target}: cannot create a temporary file")  # pragma: no cover

    def open(self, target: Path) -> CheckedFile:
        """A :class:`CheckedFile` writing the temporary file of ``target``."""
        tmp = self.temp_path(target)
        try:
            f = open(tmp, "wb")  # noqa: SIM115 - closed by commit/abort
        except OSError as e:
            raise OutputError(f"{target}: cannot write: {_strerror(e)}") from None
        cf = CheckedFile(Path(target), tmp, f)
        self._files[Path(target)] = cf
        return cf

    def commit(self) -> None:
        """Fsync and move every output into place, all or none."""
        for t in self.targets:
            if t not in self._tmp:
                raise ValueError(f"output {t} was never written")
        for cf in self._files.values():
            cf.close()
        for t, tmp in self._tmp.items():
            if t not in self._files:
                _fsync_path(tmp, t)
        done: list[tuple[Path, bool, Path | None]] = []  # (target, replaced, backup)
        try:
            for t in self.targets:
                done.append((t, *self._commit_one(t, self._tmp[t])))
        except BaseException:
            _roll_back(done)
            raise
        for _t, _replaced, backup in done:
            if backup is not None:
                backup.unlink(missing_ok=True)
        for d in {t.parent for t in self.targets}:
            _fsync_dir(d)
        self._tmp.clear()
        self._files.clear()
        self._made.clear()  # committed: the folders hold the outputs

    def _commit_one(self, target: Path, tmp: Path) -> tuple[bool, Path | None]:
        """Move one output into place: (whether a file was replaced, a link to the old one)."""
        # Checked again: the target may have changed while we were computing.
        check_target(target, force=self.force, inputs=self.inputs)
        try:
            os.link(tmp, target)  # fails if the target exists: never clobbers
            tmp.unlink()
            return False, None
        except FileExistsError:
            if not self.force:
                raise OutputExists(f"{target}: exists") from None
        except OSError as e:
            if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV):
                raise OutputError(f"{target}: cannot commit: {_strerror(e)}") from None
            # No hard links on this file system: rename after the check above.
            if not self.force and os.path.lexists(target):
                raise OutputExists(f"{target}: exists") from None
            os.rename(tmp, target)
            return False, None
        # force and the target exists: keep a link to the old file for the roll-back.
        backup = _temp_name(target)
        try:
            os.link(target, backup)
        except OSError:
            backup = None
        try:
            os.replace(tmp, target)
        except OSError as e:
            if backup is not None:
                backup.unlink(missing_ok=True)
            raise OutputError(f"{target}: cannot commit: {_strerror(e)}") from None
        return True, backup

    def abort(self) -> None:
        """Delete every temporary file (never raises)."""
        for cf in self._files.values():
            cf.discard()
        for tmp in self._tmp.values():
            try:
                tmp.unlink()
            except OSError:
                pass
        self._files.clear()
        self._tmp.clear()
        # an empty folder made only for outputs that were never committed goes too
        for d in sorted(self._made, key=lambda p: len(p.parts), reverse=True):
            try:
                d.rmdir()  # only if empty: never what another process put there
            except OSError:
                pass
        self._made.clear()


def _roll_back(done: list[tuple[Path, bool, Path | None]]) -> None:
    """Put committed targets back as they were: new ones removed, replaced ones restored."""
    for target, replaced, backup in reversed(done):
        try:
            if not replaced:
                target.unlink()
            elif backup is not None:
                os.replace(backup, target)
        except OSError:
            pass


def _fsync_path(tmp: Path, target: Path) -> None:
    try:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as e:
        raise OutputError(f"{target}: cannot write: {_strerror(e)}") from None


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems do not fsync directories; the data itself is synced
    finally:
        os.close(fd)


def write_bytes(
    target: Path, data: bytes, *, force: bool = False, inputs: Iterable[Path] = ()
) -> None:
    """One output from bytes in memory, through :class:`Outputs`."""
    with Outputs([target], force=force, inputs=inputs) as out:
        out.open(target).write(data)
        out.commit()


def stale_temporaries(target: Path) -> list[Path]:
    """Temporary files of ours beside ``target`` whose writing process is gone (SIGKILL, a
    crash): they are never cleaned up by themselves, so commands report them."""
    target = Path(target)
    prefix = f".{target.name}{_TAG}"
    out = []
    try:
        entries = list(os.scandir(target.parent if str(target.parent) else "."))
    except OSError:
        return []
    for e in entries:
        if not (e.name.startswith(prefix) and e.name.endswith(".tmp")):
            continue
        pid_text = e.name[len(prefix) :].split("-", 1)[0]
        if pid_text.isdigit() and not _alive(int(pid_text)):
            out.append(Path(e.path))
    return sorted(out)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, owned by someone else
    return True
