"""Golden-file regression tests: a small seed-pinned scenario through the whole CLI pipeline.

`tests/golden/small.toml` (the paper's model, 3 sensors, M = 500, K = 10, seed 7, all seven
architectures) is run with `fusionlog run` into a temporary folder and checked against:

* `small_summary.json` -- the summary.json, compared with `fusionlog.compare.compare_summaries`
  at rtol = 1e-9. Why not exact: the simulation itself is bit-reproducible (a seeded PCG64
  stream per run), but every filter, the exact covariance analysis and the Monte Carlo sums go
  through numpy/BLAS/LAPACK, which choose kernels, SIMD widths, FMA use and summation order by
  CPU, library build and array shape (see test_cli: even the block size moves estimates by an
  ulp). On one platform results repeat bitwise; across machines they differ in the last few
  digits (~1e-15 relative per operation, ~1e-13 after K steps and M-run sums). 1e-9 leaves
  four orders of magnitude for that and is still far below any real change: Monte Carlo
  noise at M = 500 is ~5 %, and a modelling or algorithm change moves these numbers by far
  more than 1e-9.
* `small_mcap_structure.json` -- for both MCAP files: library, topics, their schema names,
  encodings and fields, message counts, metadata record names and the keys inside them (not
  the values: they hold the command line, paths and the fusionlog version).
* `small_rrd_structure.json` -- the recording's application and recording id, and per entity
  path its components, timeline names and numbers of rows (temporal and static).

Updating: after an intended change of results run `make golden`, i.e.
`FUSIONLOG_UPDATE_GOLDEN=1 pytest tests/test_golden.py`, which rewrites the golden files from
this run; review the diff (`git diff tests/golden`) before committing it. Every file in
tests/golden/ must be listed in GOLDEN_FILES and used by a test (checked below), so stale
golden files cannot pile up.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from fusionlog.cli import main
from fusionlog.compare import compare_summaries

GOLDEN = Path(__file__).resolve().parent / "golden"
SCENARIO = GOLDEN / "small.toml"
UPDATE = os.environ.get("FUSIONLOG_UPDATE_GOLDEN") == "1"
SUMMARY_RTOL = 1e-9  # see the module docstring
SUMMARY_ATOL = 1e-12

#: Every file in tests/golden/ and what uses it; test_no_unused_golden_files keeps this honest.
GOLDEN_FILES = {
    "small.toml": "the scenario every test here runs",
    "small_summary.json": "test_summary_matches_golden, test_compare_cli_against_golden",
    "small_mcap_structure.json": "test_mcap_structure_matches_golden",
    "small_rrd_structure.json": "test_rrd_structure_matches_golden",
    "heterogeneous_summary.json": "test_heterogeneous_summary_matches_golden",
}
HETEROGENEOUS = GOLDEN.parents[1] / "pipeline" / "heterogeneous.toml"

OUTPUTS = ("sensors.mcap", "estimates.mcap", "evaluation.rrd", "summary.json")
_bin = Path(sys.executable).parent / "rerun"
RERUN = str(_bin) if _bin.exists() else shutil.which("rerun")
ENV = {**os.environ, "RERUN_ANALYTICS": "0"}


def run_small(out: Path, *extra: str) -> Path:
    res = CliRunner().invoke(main, ["run", str(SCENARIO), "--out-dir", str(out), *extra])
    assert res.exit_code == 0, (res.output, res.exception)
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUTS)
    return out


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    return run_small(tmp_path_factory.mktemp("golden") / "a")


@pytest.fixture(scope="module")
def small_again(tmp_path_factory) -> Path:
    """The same command a second time, in another folder."""
    return run_small(tmp_path_factory.mktemp("golden") / "b")


def dumps(obj: Any, inline_at: int, level: int = 0) -> str:
    """JSON with sorted keys; dicts nested `inline_at` deep or more go on one line each, so a
    golden file has one line per topic or entity and its diffs read well."""
    if not isinstance(obj, dict) or level >= inline_at:
        return json.dumps(obj, sort_keys=True)
    if not obj:
        return "{}"
    pad = "  " * (level + 1)
    items = [
        f"{pad}{json.dumps(k)}: {dumps(v, inline_at, level + 1)}" for k, v in sorted(obj.items())
    ]
    return "{\n" + ",\n".join(items) + "\n" + "  " * level + "}"


def golden(name: str, actual: Any, render) -> Any:
    """The golden content of `name`; with FUSIONLOG_UPDATE_GOLDEN=1 first rewritten from
    `actual` (written as `render(actual)`)."""
    assert name in GOLDEN_FILES, f"register {name} in GOLDEN_FILES"
    path = GOLDEN / name
    if UPDATE:
        if os.environ.get("CI", "").lower() in ("true", "1"):
            pytest.fail("FUSIONLOG_UPDATE_GOLDEN is refused under CI: it would pass by rewriting")
        path.write_text(render(actual) + "\n")
        # A rewritten file compared with itself proves nothing: report it, do not pass it.
        pytest.skip(f"{path.name} rewritten; review `git diff tests/golden`")
    if not path.exists():
        pytest.fail(f"{path} is missing; create it with `make golden` and review it")
    return json.loads(path.read_text())


# ------------------------------------------------------------------------------------------
# structure extractors (values that hold paths, command lines or versions are left out)
# ------------------------------------------------------------------------------------------


def mcap_structure(path: Path) -> dict[str, Any]:
    """Topics, schemas (with their fields), message counts and metadata keys, read with the
    plain `mcap` reader."""
    from google.protobuf import descriptor_pb2
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        metadata = {m.name: sorted(m.metadata) for m in reader.iter_metadata()}
    assert summary is not None and summary.statistics is not None
    counts = summary.statistics.channel_message_counts
    type_names = {
        v.number: k.removeprefix("TYPE_").lower()
        for k, v in descriptor_pb2.FieldDescriptorProto.Type.DESCRIPTOR.values_by_name.items()
    }
    schemas = {}
    for schema in summary.schemas.values():
        fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
        fields = []
        for fdp in fds.file:
            for m in fdp.message_type:
                if f"{fdp.package}.{m.name}" == schema.name:
                    fields = [
                        f"{fl.name} = {fl.number}: "
                        f"{'repeated ' if fl.label == fl.LABEL_REPEATED else ''}"
                        f"{type_names[fl.type]}"
                        for fl in m.field
                    ]
        schemas[schema.name] = {"encoding": schema.encoding, "fields": fields}
    topics = {}
    for cid, ch in summary.channels.items():
        topics[ch.topic] = {
            "message_encoding": ch.message_encoding,
            "schema": summary.schemas[ch.schema_id].name,
            "messages": counts.get(cid, 0),
        }
    return {
        # the writing library's name without versions, which move within the pinned range
        "library": header.library.split("/")[0],
        "profile": header.profile,
        "messages": summary.statistics.message_count,
        "schemas": schemas,
        "topics": topics,
        "metadata": metadata,
    }


def rrd_structure(path: Path) -> dict[str, Any]:
    """Stores, and per entity path its components, timelines and row counts."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    entities: dict[str, dict[str, Any]] = {}
    for ch in reader.store().stream().to_chunks():
        e = entities.setdefault(
            str(ch.entity_path),
            {"components": set(), "timelines": set(), "rows": 0, "static_rows": 0},
        )
        timelines = set(ch.timeline_names)
        names = ch.to_record_batch().schema.names
        e["timelines"] |= timelines
        e["components"] |= {n for n in names if n != "rerun.controls.RowId" and n not in timelines}
        e["static_rows" if ch.is_static else "rows"] += ch.num_rows
    for e in entities.values():
        e["components"] = sorted(e["components"])
        e["timelines"] = sorted(e["timelines"])
    return {
        "recordings": [
            {"application_id": s.application_id, "recording_id": s.recording_id}
            for s in reader.recordings()
        ],
        "blueprints": len(reader.blueprints()),
        "entities": entities,
    }


# ------------------------------------------------------------------------------------------
# golden comparisons
# ------------------------------------------------------------------------------------------


def test_summary_matches_golden(small: Path) -> None:
    actual = json.loads((small / "summary.json").read_text())
    expected = golden("small_summary.json", actual, lambda d: json.dumps(d, indent=2))
    diffs = compare_summaries(actual, expected, rtol=SUMMARY_RTOL, atol=SUMMARY_ATOL)
    assert not diffs, "summary differs from tests/golden/small_summary.json:\n" + "\n".join(diffs)
    assert actual["scenario"] == "small" and actual["seed"] == 7
    assert actual["runs"] == 500 and actual["steps"] == 10
    assert list(actual["architectures"]) == ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "FBS"]


def test_heterogeneous_summary_matches_golden(tmp_path: Path) -> None:
    """Different sensors with correlated noise (pipeline/heterogeneous.toml), every architecture
    including CI, AVG and HKF, pinned number by number (not only "finite")."""
    out = tmp_path / "h"
    args = ["run", str(HETEROGENEOUS), "--out-dir", str(out), "--runs", "300", "--steps", "60"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, (res.output, res.exception)
    actual = json.loads((out / "summary.json").read_text())
    expected = golden("heterogeneous_summary.json", actual, lambda d: json.dumps(d, indent=2))
    diffs = compare_summaries(actual, expected, rtol=SUMMARY_RTOL, atol=SUMMARY_ATOL)
    assert not diffs, "differs from tests/golden/heterogeneous_summary.json:\n" + "\n".join(diffs)
    archs = actual["architectures"]
    assert list(archs) == ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "FBS", "AVG"]
    # HKF's equivalent measurements assume independent sensors: it loses consistency, exactly
    # (the exact ANEES, not only the Monte Carlo one); MSC-GMF with the cross terms does not.
    assert archs["HKF"]["expected"]["anees"] > 2.2
    assert archs["MSC-GMF"]["expected"]["anees"] == pytest.approx(2.0, abs=1e-9)


def test_compare_cli_against_golden(small: Path) -> None:
    """The CI gate as a user runs it: `fusionlog compare summary.json golden.json`."""
    if UPDATE:
        pytest.skip("golden files are being rewritten")
    args = ["compare", str(small / "summary.json"), str(GOLDEN / "small_summary.json")]
    res = CliRunner().invoke(main, [*args, "--rtol", str(SUMMARY_RTOL)])
    assert res.exit_code == 0, res.output


def test_mcap_structure_matches_golden(small: Path) -> None:
    actual = {name: mcap_structure(small / name) for name in ("sensors.mcap", "estimates.mcap")}
    # Compare through JSON so that tuples/lists and key order do not matter.
    actual = json.loads(json.dumps(actual, sort_keys=True))
    assert actual == golden("small_mcap_structure.json", actual, lambda d: dumps(d, 3))


def test_rrd_structure_matches_golden(small: Path) -> None:
    actual = json.loads(json.dumps(rrd_structure(small / "evaluation.rrd"), sort_keys=True))
    expected = golden("small_rrd_structure.json", actual, lambda d: dumps(d, 2))
    if actual != expected:
        a, e = set(actual["entities"]), set(expected["entities"])
        detail = [f"new entity {p}" for p in sorted(a - e)]
        detail += [f"missing entity {p}" for p in sorted(e - a)]
        detail += [
            f"{p}: {actual['entities'][p]} != golden {expected['entities'][p]}"
            for p in sorted(a & e)
            if actual["entities"][p] != expected["entities"][p]
        ]
        if actual["recordings"] != expected["recordings"]:
            detail.append(f"recordings {actual['recordings']} != {expected['recordings']}")
        if actual["blueprints"] != expected["blueprints"]:
            detail.append(f"blueprints {actual['blueprints']} != {expected['blueprints']}")
        pytest.fail("recording structure differs from golden:\n" + "\n".join(detail[:30]))


def test_no_unused_golden_files() -> None:
    """Every file in tests/golden/ is registered (and so used); every registered file exists."""
    present = {p.name for p in GOLDEN.iterdir()}
    unused = sorted(present - set(GOLDEN_FILES))
    missing = sorted(set(GOLDEN_FILES) - present)
    assert not unused, f"files in tests/golden/ that no test uses: {unused}"
    assert not missing, f"golden files missing (run `make golden`): {missing}"


# ------------------------------------------------------------------------------------------
# Rerun's own tools on the recording
# ------------------------------------------------------------------------------------------


@pytest.mark.skipif(RERUN is None, reason="rerun CLI missing")
def test_rerun_rrd_verify(small: Path) -> None:
    p = subprocess.run(
        [RERUN, "rrd", "verify", str(small / "evaluation.rrd")],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
        check=False,
    )
    assert p.returncode == 0, p.stdout + p.stderr


@pytest.mark.skipif(RERUN is None, reason="rerun CLI missing")
def test_rerun_rrd_compare_same_seed(small: Path, small_again: Path, tmp_path: Path) -> None:
    """Two same-seed recordings hold the same data (the files are not byte-identical: Rerun
    stamps row and chunk ids with the clock). A different run count is told apart."""

    def compare(a: Path, b: Path) -> subprocess.CompletedProcess:
        return subprocess.run(
            [RERUN, "rrd", "compare", "--unordered", str(a), str(b)],
            capture_output=True,
            text=True,
            env=ENV,
            timeout=120,
            check=False,
        )

    rrd = "evaluation.rrd"
    p = compare(small / rrd, small_again / rrd)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    # negative control: the comparison does look at the data
    other = run_small(tmp_path / "c", "--runs", "499")
    assert compare(small / rrd, other / rrd).returncode != 0
    # and the MCAP files of the two same-seed runs hold identical data
    from fusionlog.io.mcap import McapFile

    for name in ("sensors.mcap", "estimates.mcap"):
        fa, fb = McapFile(small / name), McapFile(small_again / name)
        assert fa.topics == fb.topics
        da, db = fa.read_all(sorted(fa.topics)), fb.read_all(sorted(fb.topics))
        for t in da:
            assert repr(da[t]) == repr(db[t]), t
