"""Opening a recorded file for replay: a regular file of bounded size, never anything that
could block or never end (a FIFO, a device, a socket).

The file is opened without blocking (opening a FIFO for reading would otherwise wait for a
writer forever) and checked with ``fstat`` on the open descriptor, so what is checked is what is
read. The size bounds say what each reader holds:

* a text table (CSV) is held as arrays of its rows' times and values: at most
  ``MAX_TEXT_BYTES`` (1 GiB, tens of millions of rows), and a file that grows while it is read
  stops there too;
* an MCAP is read through its index, only the chosen topic decoded: at most
  ``MAX_MCAP_BYTES`` (256 GiB).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

from fusionlog.errors import FusionlogError
from fusionlog.inputs import special_kind

__all__ = ["MAX_MCAP_BYTES", "MAX_TEXT_BYTES", "bounded_lines", "open_source"]

MAX_TEXT_BYTES = 1 << 30
MAX_MCAP_BYTES = 256 << 30


def _size(n: int) -> str:
    return f"{n / 2**30:.3g} GiB" if n >= 2**30 else f"{n} bytes"


def _not_regular(path: Path, prefix: str, mode: int) -> FusionlogError:
    kind = "a directory" if stat.S_ISDIR(mode) else special_kind(mode) or "not a regular file"
    return FusionlogError(f"{path}: {prefix}is {kind}, not a regular file (a recorded log)")


def open_source(path: Path, what: str | None, limit: int, kind: str) -> BinaryIO:
    """`path` opened for reading in binary mode, if it is a regular file of at most `limit`
    bytes (`kind` names the reader in the error: "an MCAP", "a text table"); else a one-line
    FusionlogError ``<path>: [<what>: ]...``."""
    prefix = f"{what}: " if what else ""
    try:
        st = os.stat(path)  # a socket cannot even be opened: name it first
        if not stat.S_ISREG(st.st_mode):
            raise _not_regular(path, prefix, st.st_mode)
        flags = os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise FusionlogError(f"{path}: {prefix}no such file") from None
    except OSError as e:
        raise FusionlogError(f"{path}: {prefix}cannot read: {e.strerror or e}") from None
    try:
        st = os.fstat(fd)  # what was opened (the path may have been replaced meanwhile)
        if not stat.S_ISREG(st.st_mode):
            raise _not_regular(path, prefix, st.st_mode)
        if st.st_size > limit:
            raise FusionlogError(
                f"{path}: {prefix}{_size(st.st_size)}, more than the {_size(limit)} {kind} "
                'source may be (docs/reference/replay.md, "Limits")'
            )
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def bounded_lines(lines: Iterable[str], limit: int, path: Path, what: str) -> Iterator[str]:
    """The lines of a text source, stopping with a one-line error once they pass `limit`
    characters (a file that grows while it is read)."""
    total = 0
    for line in lines:
        total += len(line)
        if total > limit:
            raise FusionlogError(
                f"{path}: {what}: grew past {_size(limit)} while being read (a text table "
                "source may be at most that)"
            )
        yield line
