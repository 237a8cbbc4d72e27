"""Table I/II-style table and the golden-summary comparison."""

from __future__ import annotations

import copy

import pytest

from fusionlog.report import compare_summaries, format_table


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
