"""The CLI as the tests drive it, in one place: in this process (click's CliRunner) -- run,
expect success, or expect the one-line error of exit 2 (DESIGN.md, "CLI") -- and the same
one-line check of a real process's exit status and stderr."""

from __future__ import annotations

import os
from pathlib import Path

from click.testing import CliRunner, Result

from fusionlog.cli import main


def cli(*args: str | os.PathLike[str]) -> Result:
    """`fusionlog ARGS` in this process; stdout and stderr kept apart."""
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=True)


def ok(*args: str | os.PathLike[str]) -> Result:
    """`fusionlog ARGS` in this process, which must succeed."""
    res = cli(*args)
    assert res.exit_code == 0, (res.output, res.exception)
    return res


def one_line_error(res: Result, *fragments: str, code: int = 2) -> str:
    """Exit `code` (2: a user's mistake) by SystemExit, exactly one `fusionlog: error: ` line
    on stderr holding every fragment, no traceback; returns the line."""
    assert isinstance(res.exception, SystemExit), f"unexpected exception {res.exception!r}"
    assert res.exit_code == code, (res.exit_code, res.output)
    return _one_line(res.stderr, res.output, fragments)


def one_line_exit(rc: int, err: str, *fragments: str) -> str:
    """The same of a finished process: exit status 2 and its stderr `err` one such line."""
    assert rc == 2, (rc, err)
    return _one_line(err, err, fragments)


def _one_line(err: str, output: str, fragments: tuple[str, ...]) -> str:
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {err!r}"
    assert lines[0].startswith("fusionlog: error: "), lines[0]
    assert "Traceback" not in output
    for f in fragments:
        assert f in lines[0], f"{f!r} not in {lines[0]!r}"
    return lines[0]


def listing(folder: Path) -> list[str]:
    """Every entry of a folder, hidden temporary files included (none: the folder is absent)."""
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []
