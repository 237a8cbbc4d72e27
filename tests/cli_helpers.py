"""The CLI in-process (click's CliRunner), as the newer test modules drive it: run, expect
success, or expect the one-line error of exit 2 (DESIGN.md, "CLI")."""

from __future__ import annotations

import os

from click.testing import CliRunner, Result

from fusionlog.cli import main


def cli(*args: str | os.PathLike[str]) -> Result:
    """`fusionlog ARGS` in this process; stdout and stderr kept apart."""
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=True)


def ok(*args: str | os.PathLike[str]) -> Result:
    res = cli(*args)
    assert res.exit_code == 0, (res.output, res.exception)
    return res


def one_line_error(res: Result, *fragments: str) -> str:
    """Exit 2, exactly one `fusionlog: error: ` line on stderr holding every fragment, no
    traceback; returns the line."""
    assert res.exit_code == 2, (res.exit_code, res.output, res.exception)
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("fusionlog: error: "), res.stderr
    assert "Traceback" not in res.output
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]
