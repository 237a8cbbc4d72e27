"""`fusionlog compare`'s classes and strict JSON out (issue 12, items 7 and 9).

Every comparison here is between a real summary written by `fusionlog run` and a perturbed or
damaged copy of it (comparing a summary with itself would not test `compare`):

* match (exit 0): every number moved within the tolerance;
* regression (exit 1): numbers moved beyond it, one diff line each, in the usual format;
* bad input (exit 2, one line naming the file and the key path): a metric that is not a number
  (string, null, list, boolean, object), a NaN/Infinity literal (not JSON), a malformed
  ``non_finite`` note, a document nested 100,000 deep, a 5,000-digit integer; and a negative
  or non-finite tolerance (a usage error).

An identity scenario with a reliability-1 sensor has an infinite DS log-loss: its summary.json,
`summary --json` and the recording's summary property must still be strict JSON (null plus a
``non_finite`` note), and Infinity in both files must compare equal -- and only to Infinity.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_helpers import cli, ok, one_line_error

from fusionlog.io.rrd import read_recording

ROOT = Path(__file__).resolve().parents[1]
AJGL = ROOT / "pipeline" / "ajgl2009.toml"
AIRCRAFT = ROOT / "pipeline" / "aircraft_identity.toml"
DROPOUT = ROOT / "pipeline" / "ajgl2009_dropout.toml"


def refuse_constant(name: str) -> None:
    raise AssertionError(f"{name} is not JSON")


def strict_loads(text: str) -> Any:
    """json.loads that fails on NaN / Infinity / -Infinity, as other languages' parsers do."""
    return json.loads(text, parse_constant=refuse_constant)


def map_floats(doc: Any, f: Callable[[float], float]) -> Any:
    """A copy of `doc` with f applied to every float (ints, null, strings kept)."""
    if isinstance(doc, dict):
        return {k: map_floats(v, f) for k, v in doc.items()}
    if isinstance(doc, list):
        return [map_floats(v, f) for v in doc]
    return f(doc) if isinstance(doc, float) else doc


def count_floats(doc: Any) -> int:
    if isinstance(doc, dict):
        return sum(count_floats(v) for v in doc.values())
    if isinstance(doc, list):
        return sum(count_floats(v) for v in doc)
    return int(isinstance(doc, float) and doc != 0.0)


def put(doc: dict, keys: tuple, value: Any) -> dict:
    out = copy.deepcopy(doc)
    d = out
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value
    return out


def write(path: Path, doc: Any) -> Path:
    path.write_text(json.dumps(doc, indent=2))  # Python's json: NaN / Infinity as literals
    return path


@pytest.fixture(scope="module")
def state_run(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("state") / "out"
    ok("run", AJGL, "--out-dir", d, "--runs", "100", "--steps", "8")
    return d


@pytest.fixture(scope="module")
def reliable_run(tmp_path_factory) -> Path:
    """The aircraft scenario with a reliability-1 ESM: in some run a report rules the true
    class out, so DS's log-loss is +inf (and its standard error NaN)."""
    tmp = tmp_path_factory.mktemp("identity")
    text = AIRCRAFT.read_text()
    assert text.count("reliability = 0.6") == 1
    sc = tmp / "reliable.toml"
    sc.write_text(text.replace("reliability = 0.6", "reliability = 1.0"))
    d = tmp / "out"
    ok("run", sc, "--out-dir", d, "--runs", "200")
    return d


@pytest.fixture(scope="module")
def dropout_run(tmp_path_factory) -> Path:
    """Sensors that drop measurements: `expected` is conditional on the drawn patterns and
    says so with ``"conditional": true`` (DESIGN.md, summary.json)."""
    d = tmp_path_factory.mktemp("dropout") / "out"
    ok("run", DROPOUT, "--out-dir", d, "--runs", "60", "--steps", "6", "--arch", "CKF",
       "--arch", "MSC")  # fmt: skip
    return d


@pytest.fixture(scope="module")
def sweep_run(tmp_path_factory) -> Path:
    """A sweep's summary.json: its architectures are per grid point, one point with dropouts
    (conditional expected values), one without."""
    d = tmp_path_factory.mktemp("sweep") / "out"
    vary = ["--vary", "scenario.steps=6", "--vary", "sensors.s1.dropout=0,0.2"]
    ok("sweep", DROPOUT, *vary, "--runs", "60", "--workers", "0", "--arch", "CKF", "--arch", "MSC",
       "--out-dir", d)  # fmt: skip
    return d


# ------------------------------------------------------------------------------------------
# strict JSON out
# ------------------------------------------------------------------------------------------


def test_identity_summary_with_infinite_log_loss_is_strict_json(reliable_run: Path) -> None:
    text = (reliable_run / "summary.json").read_text()
    doc = strict_loads(text)
    ds = doc["architectures"]["DS"]
    assert ds["log_loss"] is None and ds["stderr"]["log_loss"] is None
    assert doc["non_finite"] == {
        "architectures.DS.log_loss": "Infinity",
        "architectures.DS.stderr.log_loss": "NaN",
    }
    assert list(doc)[-1] == "non_finite"  # the note comes last; the rest keeps its order
    # the same document from the recording, through `summary --json` and the raw property
    assert strict_loads(ok("summary", reliable_run / "evaluation.rrd", "--json").stdout) == doc
    prop = read_recording(reliable_run / "evaluation.rrd")["properties"]["summary"]["json"]
    assert strict_loads(prop) == doc
    # the table shows the noted values, not a dash
    table = ok("summary", reliable_run / "evaluation.rrd").stdout
    row = next(ln for ln in table.splitlines() if ln.startswith("DS "))
    assert row.split()[5] == "inf", row


def test_state_summary_is_strict_json(state_run: Path) -> None:
    doc = strict_loads((state_run / "summary.json").read_text())
    assert "non_finite" not in doc  # nothing non-finite here: the file is as before
    assert strict_loads(ok("summary", state_run / "evaluation.rrd", "--json").stdout) == doc


# ------------------------------------------------------------------------------------------
# match and regression
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["state_run", "reliable_run", "dropout_run"])
def test_perturbed_copy_matches_within_tolerance_only(which: str, request, tmp_path: Path):
    golden = request.getfixturevalue(which) / "summary.json"
    doc = strict_loads(golden.read_text())
    moved = write(tmp_path / "moved.json", map_floats(doc, lambda v: v * (1 + 1e-9)))
    res = ok("compare", moved, golden)
    assert res.stdout.startswith(f"{moved} matches {golden} (rtol=1e-06, atol=1e-12)")
    res = cli("compare", moved, golden, "--rtol", "1e-12", "--atol", "0")
    assert res.exit_code == 1, res.output
    diff = res.stdout.splitlines()
    assert diff[0] == f"{moved} differs from {golden} (rtol=1e-12, atol=0):"
    assert len(diff) - 1 == count_floats(doc)  # every moved number, nothing else
    assert all("(rel. diff 1e-09)" in ln for ln in diff[1:]), diff


def test_regression_gives_one_diff_line_per_metric(state_run: Path, tmp_path: Path) -> None:
    golden = state_run / "summary.json"
    doc = strict_loads(golden.read_text())
    mse = doc["architectures"]["MSC"]["mse"]
    doc = put(doc, ("architectures", "MSC", "mse"), mse * 1.01)
    doc = put(doc, ("architectures", "CKF", "expected", "anees"), 2.5)
    doc = put(doc, ("architectures", "HKF", "mse_per_state", 1), 0.0)
    del doc["architectures"]["CI"]
    res = cli("compare", write(tmp_path / "a.json", doc), golden)
    assert res.exit_code == 1, res.output
    assert res.stdout.splitlines()[1:] == [  # in the golden's order
        "  CKF: expected.anees: actual 2.5, golden 2 (rel. diff 0.25)",
        "  HKF: mse_per_state[1]: actual 0, golden "
        f"{strict_loads(golden.read_text())['architectures']['HKF']['mse_per_state'][1]:.10g}"
        " (rel. diff 1)",
        f"  MSC: mse: actual {mse * 1.01:.10g}, golden {mse:.10g} (rel. diff 0.01)",
        "  CI: architecture missing (in golden, not in actual)",
    ]


def test_expected_may_be_null(state_run: Path, tmp_path: Path) -> None:
    """`expected` is null where no exact analysis exists: null in both is equal, null against
    a number is a difference (exit 1), not bad input."""
    golden = state_run / "summary.json"
    doc = strict_loads(golden.read_text())
    key = ("architectures", "CI", "expected", "mse")
    nulled = write(tmp_path / "null.json", put(doc, key, None))
    res = cli("compare", nulled, golden)
    assert res.exit_code == 1, res.output
    assert res.stdout.splitlines()[1].strip().startswith("CI: expected.mse: actual None, golden")
    assert cli("compare", golden, nulled).exit_code == 1
    moved = map_floats(put(doc, key, None), lambda v: v * (1 + 1e-9))
    ok("compare", write(tmp_path / "both.json", moved), nulled)


def test_infinity_in_both_files_is_equal_and_only_to_infinity(reliable_run: Path, tmp_path):
    golden = reliable_run / "summary.json"
    doc = strict_loads(golden.read_text())
    # Infinity (noted) in both, everything else moved within tolerance: a match
    ok("compare", write(tmp_path / "same.json", map_floats(doc, lambda v: v * (1 + 1e-9))), golden)
    # a finite log-loss against the golden's Infinity, either way round: a regression
    finite = put(doc, ("architectures", "DS", "log_loss"), 5.0)
    del finite["non_finite"]["architectures.DS.log_loss"]
    finite_path = write(tmp_path / "finite.json", finite)
    res = cli("compare", finite_path, golden)
    assert res.exit_code == 1, res.output
    assert res.stdout.splitlines()[1:] == ["  DS: log_loss: actual 5, golden inf (rel. diff inf)"]
    res = cli("compare", golden, finite_path, "--rtol", "1e300")  # rtol * inf accepts nothing
    assert res.exit_code == 1, res.output
    assert res.stdout.splitlines()[1:] == ["  DS: log_loss: actual inf, golden 5 (rel. diff inf)"]
    # -Infinity is not Infinity
    neg = put(doc, ("non_finite", "architectures.DS.log_loss"), "-Infinity")
    res = cli("compare", write(tmp_path / "neg.json", neg), golden)
    assert res.exit_code == 1 and "DS: log_loss: actual -inf, golden inf" in res.stdout


# ------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------

MALFORMED = {
    "string": "0.27",
    "null": None,
    "list": [0.27],
    "bool": True,
    "object": {"value": 0.27},
}
METRICS = [
    ("architectures", "CKF", "mse"),
    ("architectures", "MSC", "mse_per_state", 0),
    ("architectures", "HKF", "stderr", "anees"),
    ("architectures", "SKF", "excluded"),
    ("runs",),
]


def key_path(keys: tuple) -> str:
    out = ""
    for k in keys:
        out = f"{out}[{k}]" if isinstance(k, int) else (f"{out}.{k}" if out else k)
    return out


@pytest.mark.parametrize("side", ["actual", "golden"])
@pytest.mark.parametrize("keys", METRICS, ids=key_path)
@pytest.mark.parametrize("kind", list(MALFORMED))
def test_malformed_metric_is_bad_input(state_run, tmp_path, side, keys, kind) -> None:
    good = state_run / "summary.json"
    doc = strict_loads(good.read_text())
    bad = write(tmp_path / f"{kind}.json", put(doc, keys, MALFORMED[kind]))
    args = (bad, good) if side == "actual" else (good, bad)
    line = one_line_error(cli("compare", *args), str(bad), key_path(keys), "number")
    assert str(good) not in line


@pytest.mark.parametrize("side", ["actual", "golden"])
@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan], ids=str)
def test_non_finite_literal_is_bad_input(state_run, tmp_path, side, value) -> None:
    """A golden `"mse": Infinity` used to match anything; NaN/Infinity are not JSON."""
    good = state_run / "summary.json"
    doc = strict_loads(good.read_text())
    bad = write(tmp_path / "nonfinite.json", put(doc, ("architectures", "CKF", "mse"), value))
    assert "Infinity" in bad.read_text() or "NaN" in bad.read_text()
    args = (bad, good) if side == "actual" else (good, bad)
    token = {math.inf: "Infinity", -math.inf: "-Infinity"}.get(value, "NaN")
    one_line_error(cli("compare", *args), str(bad), "architectures.CKF.mse", token, "not JSON")


def test_conditional_expected_is_a_flag_not_a_metric(dropout_run, tmp_path) -> None:
    """`"conditional": true` beside the expected values is part of the schema (a dropout
    scenario's summary used to be refused as malformed); anything but a boolean there is not."""
    golden = dropout_run / "summary.json"
    doc = strict_loads(golden.read_text())
    assert doc["architectures"]["CKF"]["expected"]["conditional"] is True
    ok("compare", golden, golden)
    key = ("architectures", "MSC", "expected", "conditional")
    bad = write(tmp_path / "flag.json", put(doc, key, "yes"))
    one_line_error(cli("compare", bad, golden), str(bad), key_path(key), "number")
    res = cli("compare", write(tmp_path / "off.json", put(doc, key, False)), golden)
    assert res.exit_code == 1, res.output
    assert res.stdout.splitlines()[1:] == ["  MSC: expected.conditional: actual False, golden True"]


def test_sweep_summaries_compare_point_by_point(sweep_run, tmp_path) -> None:
    """`fusionlog sweep`'s summary.json is a summary too (it used to be refused: "not a
    fusionlog summary"): its grid points' metrics are compared, and checked, as a run's."""
    golden = sweep_run / "summary.json"
    doc = strict_loads(golden.read_text())
    assert doc["kind"] == "sweep" and "architectures" not in doc
    ok("compare", write(tmp_path / "same.json", map_floats(doc, lambda v: v * (1 + 1e-9))), golden)
    key = ("points", 1, "architectures", "CKF", "mse")
    mse = doc["points"][1]["architectures"]["CKF"]["mse"]
    res = cli("compare", write(tmp_path / "moved.json", put(doc, key, mse * 1.01)), golden)
    assert res.exit_code == 1, res.output
    assert res.stdout.splitlines()[1:] == [
        f"  points[1].architectures.CKF.mse: actual {mse * 1.01:.10g}, golden {mse:.10g}"
        " (rel. diff 0.01)"
    ]
    bad = write(tmp_path / "bad.json", put(doc, ("points", 0, "architectures", "MSC", "dm"), "1"))
    one_line_error(
        cli("compare", bad, golden), str(bad), "points[0].architectures.MSC.dm", "number"
    )
    bad = write(tmp_path / "points.json", put(doc, ("points",), {"0": {}}))
    one_line_error(cli("compare", golden, bad), str(bad), "points: an object", "list")


@pytest.mark.parametrize(
    "note, fragment",
    [
        ({"architectures.DS.log_loss": "inf"}, "non_finite.architectures.DS.log_loss"),
        ({"architectures.DS.log_loss": None}, "non_finite.architectures.DS.log_loss"),
        ({"architectures.DS.accuracy": "NaN"}, "names no null value"),
        ({"architectures.XX.mse": "NaN"}, "names no null value"),
        (["architectures.DS.log_loss"], "non_finite: must be an object"),
    ],
)
def test_malformed_note_is_bad_input(reliable_run, tmp_path, note, fragment) -> None:
    golden = reliable_run / "summary.json"
    doc = strict_loads(golden.read_text())
    if isinstance(note, dict):
        note = {**doc["non_finite"], **note}
    bad = write(tmp_path / "note.json", put(doc, ("non_finite",), note))
    one_line_error(cli("compare", bad, golden), str(bad), fragment)
    one_line_error(cli("compare", golden, bad), str(bad), fragment)


def test_null_without_note_is_bad_input(reliable_run, tmp_path) -> None:
    """Dropping the note leaves a bare null in a metric's place: malformed, not a match."""
    golden = reliable_run / "summary.json"
    doc = strict_loads(golden.read_text())
    del doc["non_finite"]
    bad = write(tmp_path / "nonote.json", doc)
    one_line_error(cli("compare", bad, golden), str(bad), "architectures.DS.log_loss", "null")


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
        ('{"architectures": {"CKF": {"mse": ' + "9" * 5000 + "}}}", "5000 digits"),
        ('{"architectures": {"CKF": {"mse": ' + "9" * 400 + "}}}", "architectures.CKF.mse"),
        ('{"architectures": {"CKF": {"mse": 1e999}}}', "architectures.CKF.mse: Infinity"),
        ('{"architectures": {}, "x": ' + "[" * 500 + "]" * 500 + "}", "nested more than"),
    ],
    ids=["deep-array", "5000-digit-int", "400-digit-int", "1e999", "deep-in-summary"],
)
def test_pathological_json_is_one_line(state_run, tmp_path, text, fragment) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    good = state_run / "summary.json"
    one_line_error(cli("compare", bad, good), str(bad), fragment)
    one_line_error(cli("compare", good, bad), str(bad), fragment)


@pytest.mark.parametrize(
    "option, value",
    [("--rtol", "-1e-9"), ("--atol", "-1"), ("--rtol", "nan"), ("--atol", "inf")],
)
def test_tolerance_must_be_finite_and_non_negative(state_run, tmp_path, option, value) -> None:
    golden = state_run / "summary.json"
    moved = map_floats(strict_loads(golden.read_text()), lambda v: v * 1.5)
    res = cli("compare", write(tmp_path / "m.json", moved), golden, option, value)
    assert res.exit_code == 2, res.output
    assert f"Invalid value for '{option}': must be a finite number >= 0" in res.stderr
    assert "Traceback" not in res.output and res.stdout == ""


# ------------------------------------------------------------------------------------------
# `summary` on a recording whose summary property is not a summary
# ------------------------------------------------------------------------------------------


def recording_with_summary(path: Path, text: str) -> Path:
    import rerun as rr

    rec = rr.RecordingStream("fusionlog", recording_id="x", send_properties=False)
    rec.save(path)
    rec.send_property("summary", rr.AnyValues(json=text))
    rec.log("a", rr.Scalars(1.0))
    rec.disconnect()
    return path


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[1, 2]", "not a JSON object (list)"),
        ('"text"', "not a JSON object (str)"),
        ("null", "not a JSON object (null)"),
        ("{not json", "summary property"),
        ('{"architectures": [1]}', "not a summary"),
    ],
)
@pytest.mark.parametrize("as_json", [False, True])
def test_summary_of_a_recording_with_a_bad_summary_property(tmp_path, text, fragment, as_json):
    rrd = recording_with_summary(tmp_path / "odd.rrd", text)
    args = ["summary", rrd] + (["--json"] if as_json else [])
    if as_json and fragment == "not a summary":  # an object: printed as it is, strict
        assert strict_loads(ok(*args).stdout) == {"architectures": [1]}
        return
    one_line_error(cli(*args), str(rrd), fragment)
