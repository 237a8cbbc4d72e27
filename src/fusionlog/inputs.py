"""What an input may be: a regular file (or a folder where one is expected), never something
whose reading can block or never end.

Opening a FIFO for reading waits for a writer (forever, if none comes), and a device such as
``/dev/zero`` never ends; a socket cannot even be opened. Every command's inputs (scenario and
model files, MCAP logs, summaries) are checked here first, by ``stat``, which never blocks;
replay sources are also opened without blocking and checked again on the descriptor
(:mod:`fusionlog.io.replay.source`).
"""

from __future__ import annotations

import os
import stat

from fusionlog.errors import FusionlogError

__all__ = ["check_input", "special_kind"]

_KINDS = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def special_kind(mode: int) -> str | None:
    """What a file of this st_mode is when reading it could block or never end, else None."""
    return next((name for test, name in _KINDS if test(mode)), None)


def check_input(path: str | os.PathLike[str], prefix: str = "") -> None:
    """A one-line FusionlogError ``<path>: [<prefix>]is a FIFO ...`` when `path` is a FIFO, a
    device or a socket; nothing otherwise (a missing or unreadable file is left to the
    caller's own open, which says why)."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return
    kind = special_kind(mode)
    if kind is not None:
        raise FusionlogError(f"{os.fspath(path)}: {prefix}is {kind}, not a regular file")
