"""What the two kinds of scenario (state and identity) share, tested once for both.

The stage drivers are generic (`fusionlog.stages`): the block loop, provenance, atomic outputs
and progress are the same code whatever the kind, so the same behaviour is asked of both here,
through the CLI in-process: the kind decided once and recorded in the sensors file, bad input
as one line, outputs never replaced without --force (and kept when a forced run fails),
determinism whatever the block size, silence when piped.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error

from fusionlog.io.mcap import McapFile

ROOT = Path(__file__).resolve().parents[1]
KINDS = {
    "state": ROOT / "pipeline" / "ajgl2009.toml",
    "identity": ROOT / "pipeline" / "aircraft_identity.toml",
}
SMALL = ["--runs", "120", "--steps", "6"]
OUTPUTS = ("sensors.mcap", "estimates.mcap", "evaluation.rrd", "summary.json")


def arrays(path: Path) -> dict[str, np.ndarray]:
    f = McapFile(path)
    out: dict[str, np.ndarray] = {}
    for topic, v in f.read_all(sorted(f.topics)).items():
        for i, a in enumerate(v if isinstance(v, tuple) else (v,)):
            out[f"{topic}:{i}"] = a
    return out


@pytest.fixture(params=sorted(KINDS))
def kind(request) -> str:
    return request.param


def test_the_kind_is_decided_once_and_recorded(kind: str, tmp_path: Path) -> None:
    """`run` works the same for both kinds; the sensors file records the kind, which the later
    stages read back (estimate and evaluate on their own give the same summary)."""
    out = tmp_path / "run"
    ok("run", KINDS[kind], "--out-dir", out, *SMALL)
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUTS)
    meta = McapFile(out / "sensors.mcap").metadata["fusionlog.scenario"]
    assert meta["kind"] == kind
    summary = json.loads((out / "summary.json").read_text())
    assert summary.get("kind", "state") == kind
    ok("estimate", out / "sensors.mcap", "-o", tmp_path / "e.mcap")
    ok("evaluate", out / "sensors.mcap", tmp_path / "e.mcap", "-o", tmp_path / "ev.rrd",
       "--summary", tmp_path / "s.json")  # fmt: skip
    again = json.loads((tmp_path / "s.json").read_text())
    assert again["architectures"] == summary["architectures"]


def test_unknown_key_is_one_line_naming_file_and_key(kind: str, tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(KINDS[kind].read_text().replace("[scenario]", "[scenario]\nstpes = 3", 1))
    line = one_line_error(cli("simulate", bad, "-o", tmp_path / "s.mcap"), "bad.toml", "stpes")
    assert not (tmp_path / "s.mcap").exists(), line


def test_outputs_are_never_replaced_without_force(kind: str, tmp_path: Path) -> None:
    s = tmp_path / "s.mcap"
    ok("simulate", KINDS[kind], "-o", s, *SMALL, "--seed", "1")
    before = s.read_bytes()
    one_line_error(cli("simulate", KINDS[kind], "-o", s, *SMALL, "--seed", "2"), str(s), "--force")
    assert s.read_bytes() == before
    ok("simulate", KINDS[kind], "-o", s, *SMALL, "--seed", "2", "--force")
    assert s.read_bytes() != before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.mcap"]  # no temporary file


def test_a_forced_run_that_fails_keeps_the_previous_outputs(kind: str, tmp_path: Path) -> None:
    out = tmp_path / "run"
    ok("run", KINDS[kind], "--out-dir", out, *SMALL)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    # evaluate's second output cannot be written: a directory stands where summary.json goes
    # in the --force run below, after sensors and estimates were already computed.
    (out / "summary.json").unlink()
    (out / "summary.json").mkdir()
    one_line_error(cli("run", KINDS[kind], "--out-dir", out, *SMALL, "--seed", "9", "--force"),
                   "summary.json")  # fmt: skip
    for name, data in before.items():
        if name != "summary.json":
            assert (out / name).read_bytes() == data, name
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUTS)


def test_block_size_does_not_change_the_numbers(kind: str, tmp_path: Path) -> None:
    """Every run draws from its own chunk of the seed's stream, whatever the block of runs a
    stage works on: the sensors files hold the same numbers bit for bit. Estimates do not
    depend on the blocks either, up to the rounding of matrix products of other shapes."""
    sensors, estimates = [], []
    for blocks in ("7", "120"):
        d = tmp_path / blocks
        ok("simulate", KINDS[kind], "-o", d / "s.mcap", *SMALL, "--block-runs", blocks)
        ok("estimate", d / "s.mcap", "-o", d / "e.mcap", "--block-runs", blocks)
        sensors.append(arrays(d / "s.mcap"))
        estimates.append(arrays(d / "e.mcap"))
    assert sensors[0].keys() == sensors[1].keys() and estimates[0].keys() == estimates[1].keys()
    for k in sensors[0]:
        np.testing.assert_array_equal(sensors[0][k], sensors[1][k], err_msg=k)
    for k in estimates[0]:
        np.testing.assert_allclose(estimates[0][k], estimates[1][k], rtol=1e-12, atol=1e-12,
                                   err_msg=k)  # fmt: skip


def test_quiet_when_not_on_a_terminal(kind: str, tmp_path: Path) -> None:
    res = ok("simulate", KINDS[kind], "-o", tmp_path / "s.mcap", *SMALL, "--block-runs", "10")
    # No progress bar when stderr is not a terminal; the result is one line on stdout.
    assert res.stderr == ""
    assert res.stdout.splitlines() == [f"{tmp_path / 's.mcap'}: 120 runs x 7 steps, "
                                       + res.stdout.split(", ")[-1].strip()]  # fmt: skip
