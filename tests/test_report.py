"""Table I/II-style table and the golden-summary comparison."""

from __future__ import annotations

import copy
import json
import math

import pytest

from fusionlog.compare import check_summary, compare_summaries
from fusionlog.jsonout import dumps, resolve_non_finite, to_strict_json
from fusionlog.report import format_table


def summary() -> dict:
    def arch(mse: float, dm: float) -> dict:
        return {
            "mse": mse,
            "mse_per_state": [mse * 1.5, mse * 0.5],
            "mean_trace": 0.2,
            "anees": 2.01,
            "nees_fraction_inside": 0.952381,
            "dm": dm,
            "expected": {"mse": mse * 1.001, "anees": 2.0, "dm": 1.2533},
            "stderr": {"mse": 0.001, "anees": 0.01, "dm": 0.003},
            "excluded": 0,
        }

    return {
        "scenario": "ajgl2009",
        "seed": 1,
        "runs": 10000,
        "steps": 20,
        "state_names": ["x1", "x2"],
        "architectures": {
            "CKF": arch(0.1010, 1.2512),
            "HKF": arch(0.1010, 1.2512),
            "MSC-GMF": arch(0.1134, 1.2536),
            "MSC": arch(0.1134, 1.5204),
            "SKF": arch(0.1528, 1.2550),
        },
    }


def test_format_table_rows_columns_alignment() -> None:
    text = format_table(summary())
    lines = text.splitlines()
    header = lines[0].split()
    assert header == [
        "architecture",
        "MSE",
        "E[MSE]",
        "DM",
        "E[DM]",
        "ANEES",
        "E[ANEES]",
        "in",
        "band",
    ]
    assert [ln.split()[0] for ln in lines[2:]] == ["CKF", "HKF", "MSC-GMF", "MSC", "SKF"]
    msc = lines[5].split()
    assert msc[1] == "0.1134" and msc[3] == "1.5204" and msc[-2:] == ["95.2", "%"]
    # right-aligned numeric columns: every line ends at the same column
    assert len({len(ln) for ln in lines}) == 1
    # the architectures mapping alone works as well
    assert format_table(summary()["architectures"]) == text


def test_format_table_missing_expected_values() -> None:
    s = summary()
    s["architectures"]["SKF"]["expected"] = {"mse": None, "anees": None}
    row = format_table(s).splitlines()[-1].split()
    assert row[2] == "—" and row[4] == "—" and row[6] == "—"


def test_identical_summaries_pass() -> None:
    assert compare_summaries(summary(), summary()) == []
    assert compare_summaries(summary(), copy.deepcopy(summary()), rtol=0, atol=0) == []


def test_one_perturbed_metric_gives_one_line() -> None:
    actual = summary()
    actual["architectures"]["MSC"]["dm"] *= 1.01
    lines = compare_summaries(actual, summary(), rtol=1e-3)
    assert len(lines) == 1
    line = lines[0]
    assert line.startswith("MSC: dm:")
    assert "1.535604" in line and "1.5204" in line and "rel. diff 0.01" in line


def test_within_tolerance_passes() -> None:
    actual = summary()
    actual["architectures"]["CKF"]["mse"] *= 1 + 1e-8
    assert compare_summaries(actual, summary(), rtol=1e-6) == []
    assert len(compare_summaries(actual, summary(), rtol=1e-10)) == 1
    # atol rescues values near zero
    g = summary()
    g["architectures"]["CKF"]["mean_trace"] = 0.0
    a = copy.deepcopy(g)
    a["architectures"]["CKF"]["mean_trace"] = 1e-14
    assert compare_summaries(a, g, rtol=1e-6, atol=1e-12) == []
    assert compare_summaries(a, g, rtol=1e-6, atol=0.0) == [
        "CKF: mean_trace: actual 1e-14, golden 0 (rel. diff inf)"
    ]


def test_nested_list_and_expected_keys() -> None:
    actual = summary()
    actual["architectures"]["HKF"]["mse_per_state"][1] = 9.0
    actual["architectures"]["HKF"]["expected"]["anees"] = 3.0
    lines = compare_summaries(actual, summary())
    assert lines == [
        "HKF: mse_per_state[1]: actual 9, golden 0.0505 (rel. diff 177)",
        "HKF: expected.anees: actual 3, golden 2 (rel. diff 0.5)",
    ]


def test_missing_and_extra_architectures_and_keys() -> None:
    actual = summary()
    del actual["architectures"]["SKF"]
    actual["architectures"]["CI"] = copy.deepcopy(actual["architectures"]["CKF"])
    del actual["architectures"]["CKF"]["expected"]["anees"]
    actual["architectures"]["CKF"]["new_metric"] = 1.0
    actual["runs"] = 100
    lines = compare_summaries(actual, summary())
    assert "runs: actual 100, golden 10000 (rel. diff 0.99)" in lines
    assert "SKF: architecture missing (in golden, not in actual)" in lines
    assert "CI: architecture extra (in actual, not in golden)" in lines
    assert "CKF: expected.anees: missing (golden 2)" in lines
    assert "CKF: new_metric: extra (actual 1, not in golden)" in lines
    assert len(lines) == 5


@pytest.mark.parametrize(
    ("a", "g", "n_lines"),
    [(None, None, 0), (None, 1.0, 1), (float("nan"), float("nan"), 0), (float("nan"), 1.0, 1)],
)
def test_null_and_nan_leaves(a, g, n_lines) -> None:
    actual, golden = summary(), summary()
    actual["architectures"]["CKF"]["expected"]["dm"] = a
    golden["architectures"]["CKF"]["expected"]["dm"] = g
    assert len(compare_summaries(actual, golden)) == n_lines


def test_string_leaves() -> None:
    actual = summary()
    actual["scenario"] = "other"
    actual["state_names"] = ["p", "v"]
    lines = compare_summaries(actual, summary())
    assert "scenario: actual 'other', golden 'ajgl2009'" in lines
    assert "state_names[0]: actual 'p', golden 'x1'" in lines


# ------------------------------------------------------------------------------------------
# strict JSON (fusionlog.jsonout) and what the table and the comparison make of its notes
# ------------------------------------------------------------------------------------------


def _refuse(name: str) -> None:
    raise AssertionError(f"{name} is not JSON")


def test_dumps_replaces_non_finite_values_by_null_and_notes_them() -> None:
    s = summary()
    s["architectures"]["MSC"]["anees"] = math.inf
    s["architectures"]["MSC"]["mse_per_state"][1] = -math.inf
    s["architectures"]["SKF"]["stderr"]["dm"] = math.nan
    text = dumps(s, indent=2)
    doc = json.loads(text, parse_constant=_refuse)
    assert doc["architectures"]["MSC"]["anees"] is None
    assert doc["architectures"]["MSC"]["mse_per_state"] == [0.1701, None]
    assert doc["non_finite"] == {
        "architectures.MSC.anees": "Infinity",
        "architectures.MSC.mse_per_state[1]": "-Infinity",
        "architectures.SKF.stderr.dm": "NaN",
    }
    assert list(doc)[:-1] == list(s)  # order kept, the note last
    # finite documents are written exactly as json.dumps writes them
    assert dumps(summary(), indent=2) == json.dumps(summary(), indent=2)
    # the reader puts the values back and drops the note
    back = resolve_non_finite(doc)
    assert back["architectures"]["MSC"]["anees"] == math.inf
    assert back["architectures"]["MSC"]["mse_per_state"][1] == -math.inf
    assert math.isnan(back["architectures"]["SKF"]["stderr"]["dm"])
    assert "non_finite" not in back
    # writing a document read back keeps its note (merged with new ones)
    doc["architectures"]["CKF"]["dm"] = math.nan
    again = json.loads(dumps(doc), parse_constant=_refuse)
    assert again["non_finite"] == {**doc["non_finite"], "architectures.CKF.dm": "NaN"}


def test_to_strict_json_and_dumps_edge_cases() -> None:
    clean, notes = to_strict_json([1.0, math.nan, {"a": (math.inf,)}])
    assert clean == [1.0, None, {"a": [None]}]
    assert notes == {"[1]": "NaN", "[2].a[0]": "Infinity"}
    assert dumps([math.nan]) == "[null]"  # no object to put a note in
    with pytest.raises(ValueError, match="Out of range float"):  # a slip raises, never NaN
        dumps({"x": object()}, default=lambda o: math.nan)
    deep: list = []
    for _ in range(200):
        deep = [deep]
    with pytest.raises(ValueError, match="nested more than 64 levels"):
        to_strict_json(deep)


def test_format_table_shows_noted_values() -> None:
    s = summary()
    s["architectures"]["MSC"]["anees"] = None
    s["architectures"]["SKF"]["dm"] = None
    s["non_finite"] = {"architectures.MSC.anees": "Infinity"}
    rows = {ln.split()[0]: ln.split() for ln in format_table(s).splitlines()[2:]}
    assert rows["MSC"][5] == "inf"
    assert rows["SKF"][3] == "—"  # a null nothing explains stays a dash


def test_check_summary_strict_and_in_memory() -> None:
    s = summary()
    s["architectures"]["CKF"]["mse"] = math.inf
    assert check_summary(s)["architectures"]["CKF"]["mse"] == math.inf  # in memory: a value
    with pytest.raises(ValueError, match=r"^architectures\.CKF\.mse: Infinity is not JSON"):
        check_summary(s, strict=True)  # a file: not JSON
    s = summary()
    s["architectures"]["CKF"]["mse"] = None
    s["non_finite"] = {"architectures.CKF.mse": "NaN"}
    assert math.isnan(check_summary(s, strict=True)["architectures"]["CKF"]["mse"])


@pytest.mark.parametrize(
    ("keys", "value", "message"),
    [
        (("architectures", "CKF", "mse"), "0.1", "architectures.CKF.mse: a string ('0.1')"),
        (("architectures", "CKF", "mse"), None, "architectures.CKF.mse: null where"),
        (("architectures", "CKF", "anees"), [2.0], "architectures.CKF.anees: a list where"),
        (("architectures", "CKF", "dm"), False, "architectures.CKF.dm: a boolean (false)"),
        (("architectures", "CKF", "excluded"), {}, "architectures.CKF.excluded: an object"),
        (
            ("architectures", "CKF", "mse_per_state"),
            0.1,
            "architectures.CKF.mse_per_state: a number (0.1) where a list",
        ),
        (
            ("architectures", "CKF", "mse_per_state", 0),
            None,
            "architectures.CKF.mse_per_state[0]: null",
        ),
        (("architectures", "CKF", "stderr", "dm"), "x", "architectures.CKF.stderr.dm: a string"),
        (
            ("architectures", "CKF", "expected"),
            None,
            "architectures.CKF.expected: null where an object",
        ),
        (
            ("architectures", "CKF", "expected", "dm"),
            "x",
            "architectures.CKF.expected.dm: a string",
        ),
        (("architectures", "CKF"), 1.0, "architectures.CKF: a number (1.0) where an object"),
        (("runs",), "10000", "runs: a string ('10000') where a number"),
        (("seed",), 10**400, "seed: a number too large for a double"),
        (("state_names",), ["x1", 2], "state_names: a list where a list of strings"),
        (("scenario",), 1, "scenario: a number (1) where a string"),
    ],
)
def test_malformed_summary_is_bad_input_not_a_regression(keys, value, message) -> None:
    g = summary()
    d = g
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value
    with pytest.raises(ValueError) as info:
        check_summary(g)
    assert str(info.value).startswith(message), str(info.value)
    with pytest.raises(ValueError, match=r"^golden: "):
        compare_summaries(summary(), g)
    with pytest.raises(ValueError, match=r"^actual: "):
        compare_summaries(g, summary())


def test_infinity_matches_only_infinity() -> None:
    """A golden Infinity once matched anything, because rtol * inf accepts every value."""
    g = summary()
    g["architectures"]["CKF"]["mse"] = math.inf
    assert compare_summaries(summary(), g, rtol=1e-3) == [
        "CKF: mse: actual 0.101, golden inf (rel. diff inf)"
    ]
    assert compare_summaries(copy.deepcopy(g), g, rtol=0, atol=0) == []


@pytest.mark.parametrize("tol", [-1e-9, math.inf, math.nan])
@pytest.mark.parametrize("name", ["rtol", "atol"])
def test_tolerances_must_be_finite_and_non_negative(name, tol) -> None:
    with pytest.raises(ValueError, match=f"{name} must be a finite number >= 0"):
        compare_summaries(summary(), summary(), **{name: tol})
