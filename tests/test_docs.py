"""The documentation (issue 28, part 4): the site builds with `mkdocs build --strict`, every code
example of README.md and docs/**/*.md runs (tests/doc_examples.py says how, docs/contributing.md
how to add a page), and the README is a front page that stands alone."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from doc_examples import ROOT, Block, blocks, commands, pages, run_command, run_page, scratch

README = ROOT / "README.md"


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_the_examples_of_a_page_run(page: Path, tmp_path: Path) -> None:
    """The page's python, console, bash and sh blocks, in order, in a scratch folder laid out
    as the repository's root (what is not run is marked, with a reason)."""
    run_page(page, scratch(tmp_path))


def test_the_site_builds_strictly(tmp_path: Path) -> None:
    """`mkdocs build --strict`: every page in the nav, every link and anchor resolved, the API
    reference rendered from the docstrings and the CLI reference from the click commands."""
    site = tmp_path / "site"
    res = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-5000:]
    cli = (site / "reference/cli/index.html").read_text()
    from fusionlog.cli import main

    for name in main.commands:  # mkdocs-click rendered every command, from the code
        assert f"fusionlog {name}" in cli, name
    api = (site / "reference/api/index.html").read_text()
    for name in ("fusionlog.api.simulate", "fusionlog.api.estimate", "fusionlog.api.evaluate"):
        assert name in api, name
    assert (site / "images/ajgl2009_recording.png").is_file()
    for page in site.rglob("*.html"):  # docstrings rendered into the site point nowhere else
        text = page.read_text(encoding="utf-8")
        for outside in ("DESIGN.md", "../shared", "seed 00"):
            assert outside not in text, (page.relative_to(site), outside)


def test_the_arch_help_names_every_registered_architecture() -> None:
    """`--arch`'s help lists every architecture the registry defines (it omitted AVG), on
    every command that takes it."""
    from fusionlog.cli import main
    from fusionlog.core.names import STATE_ARCHITECTURES

    taking = [c for c in main.commands.values() if any(p.name == "archs" for p in c.params)]
    assert {c.name for c in taking} >= {"estimate", "run", "sweep"}
    for command in taking:
        (arch,) = [p for p in command.params if p.name == "archs"]
        for name in (*STATE_ARCHITECTURES, "BAYES", "DS"):
            assert re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", arch.help), name


def test_the_readme_is_a_front_page_that_stands_alone() -> None:
    """At most 250 lines; no path outside the repository; every relative link and image is a
    file of the repository; a bare `fusionlog` only once the text has said to activate the venv;
    the honesty statement about Table I with both numbers and the reason."""
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    for outside in ("../", "/work/", "shared/", "seeds/", "DESIGN.md"):
        assert outside not in text, outside
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if "://" in target:
            continue
        path = ROOT / target.split("#", 1)[0]
        assert path.resolve().is_relative_to(ROOT) and path.exists(), target
    activate = text.index("source .venv/bin/activate")
    for block in blocks(README):
        for command in commands(block) if block.language in {"console", "bash", "sh"} else []:
            if command.split()[0] == "fusionlog":
                assert text.index(block.text) > activate, command
    assert "Table I cannot be reproduced exactly (Ts unstated)" in text
    for number in ("0.1010", "0.2470", "0.17596", "Ts = 0.304"):
        assert number in text, number
    assert "does not state the sampling" in text


def test_the_docs_point_nowhere_outside_the_repository() -> None:
    for page in pages():
        text = page.read_text(encoding="utf-8")
        for outside in ("../shared", "/work/", "seeds/", "DESIGN.md"):
            assert outside not in text, (page, outside)


# The mechanism itself, on pages written here.


def _page(tmp_path: Path, text: str) -> Path:
    page = tmp_path / "page.md"
    page.write_text(text, encoding="utf-8")
    return page


def test_markers_and_fences_are_read_as_documented(tmp_path: Path) -> None:
    page = _page(
        tmp_path,
        "# t\n\n<!-- docs-test: skip opens a window -->\n\n```sh\nrerun x.rrd\n```\n\n"
        "<!-- docs-test: exit 2 -->\n```console\n$ fusionlog inspect nothing \\\n"
        "    --help-not\nfusionlog: error: ...\n$ fusionlog inspect b\n```\n"
        "```toml\n[a]\n```\n````python\nx = 1\n````\n",
    )
    got = blocks(page)
    assert [(b.language, b.skip, b.exit_code) for b in got] == [
        ("sh", "opens a window", 0),
        ("console", None, 2),
        ("toml", None, 0),
        ("python", None, 0),
    ]
    assert commands(got[1]) == ["fusionlog inspect nothing  --help-not", "fusionlog inspect b"]
    assert [b.runs for b in got] == [False, True, False, True]


@pytest.mark.parametrize(
    "text, problem",
    [
        ("<!-- docs-test: skip -->\n```sh\nx\n```\n", "skip needs a reason"),
        ("<!-- docs-test: sometimes -->\n```sh\nx\n```\n", "unknown marker"),
        ("```sh\nx\n", "not closed"),
        ("text\n<!-- docs-test: exit 1 -->\n", "a marker without a block"),
        ("<!-- docs-test: exit 1 -->\nsome words\n```sh\nx\n```\n", "a marker without a block"),
    ],
)
def test_a_malformed_page_is_refused(tmp_path: Path, text: str, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        blocks(_page(tmp_path, text))


def test_commands_run_through_the_real_cli_and_their_exit_codes_count(tmp_path: Path) -> None:
    """A failing command fails the page; another program is refused; the exit marker is the
    expected code; `.venv/bin/fusionlog` resolves in the scratch folder."""
    cwd = scratch(tmp_path)
    ok = Block(tmp_path / "p.md", 1, "console", "")
    res = run_command(ok, ".venv/bin/fusionlog --version", cwd)
    assert res.stdout.startswith("fusionlog, version")
    with pytest.raises(AssertionError, match="exited 2, the page expects 0"):
        run_command(ok, "fusionlog inspect no-such.mcap", cwd)
    two = Block(tmp_path / "p.md", 1, "console", "", exit_code=2)
    assert "no such file" in run_command(two, "fusionlog inspect no-such.mcap", cwd).stderr
    with pytest.raises(AssertionError, match="not a command the examples run"):
        run_command(ok, "make run", cwd)


def test_a_failing_python_block_fails_its_page(tmp_path: Path) -> None:
    page = _page(tmp_path, "```python\nx = 2\n```\n\n```python\nassert x == 3, 'x'\n```\n")
    (tmp_path / "run").mkdir()
    with pytest.raises(AssertionError, match="x"):
        run_page(page, tmp_path / "run")
