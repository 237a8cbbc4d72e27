"""The code examples of the documentation (README.md and docs/**/*.md), as test_docs runs them.

A page's fenced blocks run in page order, in one scratch folder per page (a notebook: a later
block may read what an earlier one wrote, python blocks share one namespace):

- ```python blocks are executed;
- ```console blocks run each line that starts with `$ ` (a trailing backslash continues it),
  the other lines being the output shown, which is not compared;
- ```bash / ```sh blocks run every line that is not blank or a comment;
- every other block (toml, text, an output without a language) is not run.

A command runs through bash in the scratch folder, where `pipeline`, `tests` and `docs` are
links to the repository's folders and `.venv` to the environment running the tests, with its
`bin` first on PATH: `fusionlog ...` and `.venv/bin/fusionlog ...` are the real console script.
The first word of each command must be one of COMMANDS, so a new kind of command is a decision
(`make`, `git`, a viewer are never run here: mark their blocks).

An HTML comment on the line before a block (blank lines between are allowed) marks it:
`<!-- docs-test: skip REASON -->` does not run it (the reason is required), and
`<!-- docs-test: exit N -->` expects every command of the block to exit with N instead of 0.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def pages() -> list[Path]:
    """The pages whose examples run: the front page and every page of the site."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _name(page: Path) -> str:
    return str(page.relative_to(ROOT)) if page.is_relative_to(ROOT) else str(page)


#: blocks run, by the fence's language
RUN_LANGUAGES = {"python", "console", "bash", "sh"}
#: what a shell example may start with (`source .venv/bin/activate` is accepted and skipped:
#: the tests already run in that environment)
COMMANDS = {"fusionlog", ".venv/bin/fusionlog", "source"}
#: the repository's folders an example may read, linked into its scratch folder
LINKED = ("pipeline", "tests", "docs")

_FENCE = re.compile(r"^(?P<indent> {0,3})(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`\n]*)$")
_MARKER = re.compile(r"^\s*<!--\s*docs-test:\s*(?P<what>\w+)\s*(?P<arg>.*?)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    """One fenced block of a page: its language, text, first line (1-based) and marker."""

    page: Path
    line: int
    language: str
    text: str
    skip: str | None = None  # the reason, when marked skip
    exit_code: int = 0

    @property
    def where(self) -> str:
        return f"{_name(self.page)}:{self.line}"

    @property
    def runs(self) -> bool:
        return self.language in RUN_LANGUAGES and self.skip is None


def blocks(page: Path) -> list[Block]:
    """The fenced blocks of a page with their markers; ValueError for a malformed marker or
    an unclosed fence."""
    lines = page.read_text(encoding="utf-8").splitlines()
    out: list[Block] = []
    marker: tuple[str, str, int] | None = None
    i = 0
    while i < len(lines):
        m = _MARKER.match(lines[i])
        if m:
            marker = (m["what"], m["arg"], i + 1)
            i += 1
            continue
        f = _FENCE.match(lines[i])
        if not f:
            if lines[i].strip() and marker is not None:  # a marker belongs to the next block
                raise ValueError(f"{_name(page)}:{marker[2]}: a marker without a block")
            i += 1
            continue
        fence, lang = f["fence"], (f["info"].split() or [""])[0].lower()
        start, body = i + 1, []
        i += 1
        while i < len(lines) and not lines[i].strip().startswith(fence):
            body.append(lines[i][len(f["indent"]) :] if f["indent"] else lines[i])
            i += 1
        if i == len(lines):
            raise ValueError(f"{_name(page)}:{start}: a fence that is not closed")
        i += 1
        skip, exit_code = None, 0
        if marker is not None:
            what, arg, at = marker
            if what == "skip":
                if not arg:
                    raise ValueError(f"{_name(page)}:{at}: skip needs a reason")
                skip = arg
            elif what == "exit" and arg.isdigit() and lang != "python":
                exit_code = int(arg)
            else:
                raise ValueError(f"{_name(page)}:{at}: unknown marker {what} {arg}")
        out.append(Block(page, start, lang, "\n".join(body) + "\n", skip, exit_code))
        marker = None
    if marker is not None:
        raise ValueError(f"{_name(page)}:{marker[2]}: a marker without a block")
    return out


def commands(block: Block) -> list[str]:
    """The shell commands of a console/bash/sh block, continuation lines joined."""
    out: list[str] = []
    pending = ""
    for raw in block.text.splitlines():
        line = raw.rstrip()
        if block.language == "console":
            if pending:
                line = line.strip()
            elif line.startswith("$ "):
                line = line[2:]
            else:
                continue  # output shown under the command
        elif not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        out.append(pending + line)
        pending = ""
    if pending:
        raise ValueError(f"{block.where}: a command continued past the block's end")
    return out


def scratch(folder: Path) -> Path:
    """A scratch folder laid out as the repository's root for the examples."""
    for name in LINKED:
        os.symlink(ROOT / name, folder / name)
    os.symlink(sys.prefix, folder / ".venv")
    return folder


def run_command(block: Block, command: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """One command of a block, through bash in `cwd`; AssertionError for a command that is
    not one of COMMANDS or exits otherwise than the block says."""
    words = shlex.split(command, comments=True)
    assert words, f"{block.where}: an empty command"
    assert words[0] in COMMANDS, (
        f"{block.where}: `{words[0]}` is not a command the examples run ({sorted(COMMANDS)}); "
        "mark the block <!-- docs-test: skip REASON --> if it must not run"
    )
    if words[0] == "source":
        assert words[1:] == [".venv/bin/activate"], f"{block.where}: source {words[1:]}"
        return subprocess.CompletedProcess(words, 0, "", "")
    env = dict(os.environ, PATH=f"{Path(sys.prefix) / 'bin'}{os.pathsep}{os.environ['PATH']}")
    env.pop("FUSIONLOG_UPDATE_GOLDEN", None)
    res = subprocess.run(
        ["bash", "-c", command], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )
    assert res.returncode == block.exit_code, (
        f"{block.where}: `{command}` exited {res.returncode}, the page expects "
        f"{block.exit_code}\nstdout: {res.stdout[-2000:]}\nstderr: {res.stderr[-2000:]}"
    )
    return res


def run_page(page: Path, cwd: Path) -> int:
    """Every runnable block of a page in order, in `cwd` (a scratch folder); the number run."""
    namespace: dict[str, object] = {"__name__": "__docs__"}
    done = 0
    here = os.getcwd()
    os.chdir(cwd)
    try:
        for block in blocks(page):
            if not block.runs:
                continue
            if block.language == "python":
                # the block's first line keeps its line number in a traceback
                code = "\n" * (block.line - 1) + block.text
                exec(compile(code, str(page), "exec"), namespace)
            else:
                for command in commands(block):
                    run_command(block, command, cwd)
            done += 1
    finally:
        os.chdir(here)
    return done
