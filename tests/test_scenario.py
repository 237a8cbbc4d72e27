"""Scenario files and their loader: the pipeline files, every validation failure, overrides,
the system <-> dict round trip and model-only files."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from fusionlog.core.model import ajgl2009
from fusionlog.core.names import STATE_ARCHITECTURES
from fusionlog.errors import FusionlogError, ValidationError
from fusionlog.scenario import (
    Scenario,
    load_model,
    load_scenario,
    model_from_text,
    scenario_from_text,
    scenario_with,
    system_from_dict,
    system_to_dict,
)

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = ROOT / "pipeline"
SRC = "bad.toml"

# A small valid scenario; the failure tests edit one thing in it.
BASE = """\
[scenario]
name = "base"
description = "two sensors"
steps = 5
runs = 10
seed = 1
dt = 1.0
state_names = ["position", "velocity"]

[model]
kind = "constant-velocity"
n0 = 0.16

[prior]
mean = [0.0, 1.0]
cov = [[1.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "a"
H = [[1.0, 0.0]]
R = 1.0

[[sensors]]
name = "b"
H = [[1.0, 0.0], [0.0, 1.0]]
R = [[2.0, 0.1], [0.1, 0.5]]
"""

EXPLICIT_MODEL = """\
[model]
F = [[1.0, 1.0], [0.0, 1.0]]
Q = [[0.25, 0.5], [0.5, 1.0]]
"""


def edit(old: str, new: str, text: str = BASE) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


def fails(text: str, *parts: str, model: bool = False) -> str:
    """Load `text`, expect a ValidationError whose one-line message starts with the file name
    and contains every part; return the message."""
    loader = model_from_text if model else scenario_from_text
    with pytest.raises(ValidationError) as info:
        loader(text, SRC)
    msg = str(info.value)
    assert "\n" not in msg and "\r" not in msg, msg
    assert msg.startswith(f"{SRC}: "), msg
    for p in parts:
        assert p in msg, f"{p!r} not in {msg!r}"
    return msg


def test_base_is_valid() -> None:
    s = scenario_from_text(BASE, SRC)
    assert s.system.m == 3
    assert s.architectures == STATE_ARCHITECTURES
    assert s.confidence == 0.95 and s.sample_runs == 3
    assert s.path is None and s.source == BASE


# ---------------------------------------------------------------------------------------------
# The pipeline files


def test_ajgl2009_matches_the_paper() -> None:
    s = load_scenario(PIPELINE / "ajgl2009.toml")
    assert isinstance(s, Scenario)
    assert s.name == "ajgl2009"
    assert (s.steps, s.runs, s.dt) == (20, 10000, 1.0)
    assert s.state_names == ("position", "velocity")
    assert s.architectures == ("CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "FBS")
    assert s.confidence == 0.95 and s.sample_runs == 3
    assert s.path == str(PIPELINE / "ajgl2009.toml")
    assert s.source == (PIPELINE / "ajgl2009.toml").read_text()
    sy = s.system
    np.testing.assert_array_equal(sy.F, [[1.0, 1.0], [0.0, 1.0]])
    np.testing.assert_allclose(sy.Q, np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]]) * 0.16, rtol=1e-15)
    assert sy.G is None
    assert [x.name for x in sy.sensors] == ["s1", "s2", "s3"]
    for x in sy.sensors:
        np.testing.assert_array_equal(x.H, [[1.0, 0.0]])
        np.testing.assert_array_equal(x.R, [[1.0]])
    assert sy.cross_R == {}
    np.testing.assert_array_equal(sy.R, np.eye(3))
    np.testing.assert_array_equal(sy.prior.mean, [100.0, -1.0])
    np.testing.assert_array_equal(sy.prior.cov, np.eye(2))
    assert sy.initial is None and sy.truth_initial is sy.prior
    # Same as the hand-written reference in core.model.
    ref = ajgl2009()
    for name in ("F", "Q", "H", "R"):
        np.testing.assert_allclose(getattr(sy, name), getattr(ref, name), rtol=1e-15)


def test_heterogeneous_file() -> None:
    s = load_scenario(PIPELINE / "heterogeneous.toml")
    sy = s.system
    assert s.steps >= 100 and s.runs < 10000
    assert set(s.architectures) == set(STATE_ARCHITECTURES)
    dt = s.dt
    np.testing.assert_allclose(
        sy.Q, np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]) * 0.16 * dt, rtol=1e-15
    )
    Hs = {x.name: x.H for x in sy.sensors}
    Rs = {x.name: x.R for x in sy.sensors}
    assert len({x.H.tobytes() + x.R.tobytes() for x in sy.sensors}) == len(sy.sensors)
    # One sensor measures velocity only; a position sensor with a larger R than the others.
    assert any(np.array_equal(H, [[0.0, 1.0]]) for H in Hs.values())
    pos_R = [Rs[k][0, 0] for k, H in Hs.items() if np.array_equal(H, [[1.0, 0.0]])]
    assert len(pos_R) >= 2 and max(pos_R) > 4 * min(pos_R)
    assert sy.cross_R, "expected correlated sensor noises"
    for (i, j), C in sy.cross_R.items():
        assert i < j
        assert C.shape == (sy.sensors[i].dim, sy.sensors[j].dim)
    R = sy.R
    np.testing.assert_array_equal(R, R.T)
    assert np.linalg.eigvalsh(R).min() > 0
    assert R.shape == (sy.m, sy.m) and sy.m == 5


def test_matrices_are_read_only() -> None:
    sy = load_scenario(PIPELINE / "ajgl2009.toml").system
    with pytest.raises(ValueError):
        sy.prior.cov[0, 0] = 2.0
    with pytest.raises(ValueError):
        sy.sensors[0].R[0, 0] = 2.0


# ---------------------------------------------------------------------------------------------
# Failure classes: each message names the file, the key and the reason, on one line.


def test_toml_syntax_error_has_line() -> None:
    text = edit("steps = 5", "steps = ")
    msg = fails(text, "line 4, column", "invalid TOML")
    assert re.match(r"bad\.toml: line 4, column 9: invalid TOML: ", msg)


def test_missing_file() -> None:
    with pytest.raises(FusionlogError, match="nope.toml: cannot read"):
        load_scenario("nope.toml")


@pytest.mark.parametrize(
    ("old", "new", "where", "key", "allowed"),
    [
        ("[model]", "colour = 1\n[model]", "scenario", "colour", "name, description, steps"),
        ("n0 = 0.16", "n0 = 0.16\nNO = 1", "model", "NO", "kind, n0, axes, A, Qc, F, Q, G"),
        (
            "cov = [[1.0, 0.0], [0.0, 1.0]]",
            "cov = [[1.0, 0.0], [0.0, 1.0]]\nmu = 1",
            "prior",
            "mu",
            "mean, cov",
        ),
        ('name = "b"', 'name = "b"\nRr = 1', "sensors[1]", "Rr", "name, H, R"),
    ],
)
def test_unknown_keys(old: str, new: str, where: str, key: str, allowed: str) -> None:
    fails(edit(old, new), f"{SRC}: {where}: unknown key {key!r} (allowed: {allowed}")


def test_unknown_key_suggests() -> None:
    fails(edit('name = "b"', 'name = "b"\nRr = 1'), "did you mean 'R'?")


def test_unknown_keys_other_sections() -> None:
    fails(
        BASE + "[truth]\ninitial_mu = [0, 0]\n",
        "truth: unknown key 'initial_mu'",
        "initial_mean, initial_cov",
    )
    fails(
        BASE + '[[correlations]]\nsensors = ["a", "b"]\ncov = [0.1, 0.0]\nrho = 1\n',
        "correlations[0]: unknown key 'rho'",
        "sensors, cov",
    )
    fails(BASE + "[estimate]\narchs = []\n", "estimate: unknown key 'archs'", "architectures")
    fails(
        BASE + "[evaluate]\nalpha = 0.1\n",
        "evaluate: unknown key 'alpha'",
        "confidence, sample_runs",
    )
    fails(BASE + "[plots]\nx = 1\n", "(top level): unknown section 'plots'", "scenario, model")
    fails("extra = 1\n" + BASE, "(top level): unknown section 'extra'")


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("steps = 5\n", "", "scenario.steps"),
        ("runs = 10\n", "", "scenario.runs"),
        ("seed = 1\n", "", "scenario.seed"),
        ("dt = 1.0\n", "", "scenario.dt"),
        ('name = "base"\n', "", "scenario.name"),
        ("mean = [0.0, 1.0]\n", "", "prior.mean"),
        ('name = "a"\n', "", "sensors[0].name"),
        ("R = 1.0\n", "", "sensors[0].R"),
        ("n0 = 0.16\n", "", "model.n0"),
    ],
)
def test_missing_required_keys(old: str, new: str, key: str) -> None:
    fails(edit(old, new), f"{SRC}: {key}: missing required key")


def test_missing_sections() -> None:
    fails(BASE.split("[model]")[0], "model: missing required section [model]")
    no_scenario = BASE[BASE.index("[model]") :]
    fails(no_scenario, "scenario: missing required section [scenario]")
    fails(BASE.split("[[sensors]]")[0], "sensors: missing", "at least one")
    msg = fails(edit('kind = "constant-velocity"\nn0 = 0.16\n', "F = [[1.0]]\n"), "model.Q")
    assert "missing required key" in msg


@pytest.mark.parametrize(
    ("old", "new", "key", "reason"),
    [
        ("steps = 5", 'steps = "5"', "scenario.steps", "expected an integer, got string '5'"),
        (
            "runs = 10",
            "runs = 1e4",
            "scenario.runs",
            "expected an integer, got float 10000 (write 10000)",
        ),
        ("seed = 1", "seed = true", "scenario.seed", "expected an integer, got boolean true"),
        ("dt = 1.0", 'dt = "1s"', "scenario.dt", "expected a number, got string"),
        ('name = "base"', "name = 3", "scenario.name", "expected a string, got integer 3"),
        ("n0 = 0.16", "n0 = [0.16]", "model.n0", "expected a number, got an array"),
        ("R = 1.0", 'R = "one"', "sensors[0].R", "expected a matrix"),
        (
            "cov = [[1.0, 0.0], [0.0, 1.0]]",
            "cov = [[1.0, 0.0], [0.0, true]]",
            "prior.cov[1][1]",
            "expected a number, got boolean",
        ),
        ("mean = [0.0, 1.0]", 'mean = [0.0, "x"]', "prior.mean[1]", "expected a number"),
        (
            'state_names = ["position", "velocity"]',
            'state_names = "pv"',
            "scenario.state_names",
            "expected a list of names",
        ),
    ],
)
def test_wrong_types(old: str, new: str, key: str, reason: str) -> None:
    fails(edit(old, new), f"{SRC}: {key}: {reason}")


def test_section_must_be_a_table() -> None:
    no_prior = BASE.replace("[prior]\nmean = [0.0, 1.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n", "")
    fails("prior = 1\n" + no_prior, f"{SRC}: prior: expected a table ([prior]), got integer 1")


def test_sensors_must_be_array_of_tables() -> None:
    text = BASE.split("[[sensors]]")[0] + '[sensors]\nname = "a"\nH = [1.0, 0.0]\nR = 1.0\n'
    fails(text, "sensors: expected an array of tables ([[sensors]])")


@pytest.mark.parametrize(
    ("old", "new", "key", "value"),
    [
        (
            "cov = [[1.0, 0.0], [0.0, 1.0]]",
            "cov = [[nan, 0.0], [0.0, 1.0]]",
            "prior.cov[0][0]",
            "nan",
        ),
        ("mean = [0.0, 1.0]", "mean = [inf, 1.0]", "prior.mean[0]", "inf"),
        ("n0 = 0.16", "n0 = -inf", "model.n0", "-inf"),
        ("dt = 1.0", "dt = nan", "scenario.dt", "nan"),
        ("R = 1.0", "R = inf", "sensors[0].R", "inf"),
        ("H = [[1.0, 0.0]]", "H = [[1.0, nan]]", "sensors[0].H[0][1]", "nan"),
    ],
)
def test_non_finite(old: str, new: str, key: str, value: str) -> None:
    fails(edit(old, new), f"{SRC}: {key}: not finite ({value})")


def explicit(F: str, Q: str, G: str | None = None, names: str | None = None) -> str:
    text = edit('kind = "constant-velocity"\nn0 = 0.16\n', f"F = {F}\nQ = {Q}\n")
    if G is not None:
        text = edit("[prior]", f"G = {G}\n\n[prior]", text)
    if names is not None:
        text = edit('state_names = ["position", "velocity"]', f"state_names = {names}", text)
    return text


def test_explicit_model_loads() -> None:
    s = scenario_from_text(explicit("[[1.0, 1.0], [0.0, 1.0]]", "0.16", G="[[0.5], [1.0]]"), SRC)
    np.testing.assert_array_equal(s.system.G, [[0.5], [1.0]])
    np.testing.assert_array_equal(s.system.Q, [[0.16]])
    np.testing.assert_allclose(s.system.GQG, [[0.04, 0.08], [0.08, 0.16]])
    s = scenario_from_text(explicit("[[1.0, 1.0], [0.0, 1.0]]", "[[0.1, 0.0], [0.0, 0.2]]"), SRC)
    assert s.system.G is None


@pytest.mark.parametrize(
    ("text", "key", "reason"),
    [
        (
            explicit("[[1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]", "[[1.0]]"),
            "model.F",
            "must be square, got 2x3",
        ),
        (
            explicit("[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]", "[[1.0]]"),
            "model.F",
            "shape 3x3 does not match the 2 scenario.state_names",
        ),
        (
            explicit("[[1.0, 1.0], [0.0, 1.0]]", "[[1.0, 0.0, 0.0]]"),
            "model.Q",
            "shape 1x3, expected 2x2 (n x n, as F)",
        ),
        (
            explicit("[[1.0, 1.0], [0.0, 1.0]]", "[[1.0, 0.0], [0.0, 1.0]]", G="[[0.5], [1.0]]"),
            "model.Q",
            "shape 2x2, expected 1x1 (q x q, q = 1 columns of G)",
        ),
        (
            explicit("[[1.0, 1.0], [0.0, 1.0]]", "1.0", G="[[0.5, 1.0]]"),
            "model.G",
            "shape 1x2, expected 2 rows",
        ),
        (explicit("[[1.0, 1.0], [1.0]]", "1.0"), "model.F", "rows have different lengths"),
        (
            explicit("[1.0, 1.0]", "1.0"),
            "model.F",
            "expected a matrix (a list of rows, e.g. [[1.0, 0.0], [0.0, 1.0]]), got a flat list",
        ),
        (
            edit("H = [[1.0, 0.0]]", "H = [[1.0, 0.0, 0.0]]"),
            "sensors[0].H",
            "shape 1x3, expected 1x2 (m x n)",
        ),
        (
            edit("R = 1.0", "R = [[1.0, 0.0], [0.0, 1.0]]"),
            "sensors[0].R",
            "shape 2x2, expected 1x1 (H has 1 row)",
        ),
        (edit("R = [[2.0, 0.1], [0.1, 0.5]]", "R = 2.0"), "sensors[1].R", "expected a matrix"),
        (edit("mean = [0.0, 1.0]", "mean = [0.0, 1.0, 2.0]"), "prior.mean", "length 3, expected 2"),
        (
            edit("cov = [[1.0, 0.0], [0.0, 1.0]]", "cov = [[1.0]]"),
            "prior.cov",
            "shape 1x1, expected 2x2",
        ),
        (
            edit('state_names = ["position", "velocity"]', 'state_names = ["x", "y", "z"]'),
            "scenario.state_names",
            "kind = 'constant-velocity' with 1 axis has 2 states ([p, v] per axis), got 3 names",
        ),
        (
            BASE + '[[correlations]]\nsensors = ["a", "b"]\ncov = 0.1\n',
            "correlations[0].cov",
            "shape 1x1, expected 1x2",
        ),
        (
            BASE + "[truth]\ninitial_cov = [[1.0, 0.0]]\n",
            "truth.initial_cov",
            "shape 1x2, expected 2x2",
        ),
    ],
)
def test_shapes(text: str, key: str, reason: str) -> None:
    fails(text, f"{SRC}: {key}: {reason}")


def test_flat_H_and_scalar_R_for_one_row() -> None:
    s = scenario_from_text(edit("H = [[1.0, 0.0]]", "H = [1.0, 0.0]"), SRC)
    np.testing.assert_array_equal(s.system.sensors[0].H, [[1.0, 0.0]])
    np.testing.assert_array_equal(s.system.sensors[0].R, [[1.0]])


@pytest.mark.parametrize(
    ("text", "key"),
    [
        (edit("R = [[2.0, 0.1], [0.1, 0.5]]", "R = [[2.0, 0.6], [0.1, 0.5]]"), "sensors[1].R"),
        (edit("cov = [[1.0, 0.0], [0.0, 1.0]]", "cov = [[1.0, 0.2], [0.0, 1.0]]"), "prior.cov"),
        (explicit("[[1.0, 1.0], [0.0, 1.0]]", "[[1.0, 0.3], [0.2, 1.0]]"), "model.Q"),
        (BASE + "[truth]\ninitial_cov = [[1.0, 0.0], [1e-3, 1.0]]\n", "truth.initial_cov"),
    ],
)
def test_symmetry(text: str, key: str) -> None:
    msg = fails(text, f"{SRC}: {key}: not symmetric (max |")
    label = key.rsplit(".", 1)[-1]
    assert f"{label} - {label}^T| = " in msg


def test_symmetry_is_relative() -> None:
    # An asymmetry of 1e-14 on entries of size 1e3 is rounding, not an error.
    s = scenario_from_text(
        edit("cov = [[1.0, 0.0], [0.0, 1.0]]", "cov = [[1000.0, 0.5], [0.50000000000001, 1.0]]"),
        SRC,
    )
    np.testing.assert_array_equal(s.system.prior.cov, s.system.prior.cov.T)
    # ... but the same asymmetry on entries of size 1e-6 is not.
    fails(
        edit("R = 1.0", "R = [[1e-6]]").replace(
            "R = [[2.0, 0.1], [0.1, 0.5]]", "R = [[2e-6, 1e-7], [1.2e-7, 5e-7]]"
        ),
        "sensors[1].R: not symmetric",
    )


@pytest.mark.parametrize(
    ("text", "key", "reason"),
    [
        (edit("R = 1.0", "R = 0.0"), "sensors[0].R", "not positive definite"),
        (
            edit("R = [[2.0, 0.1], [0.1, 0.5]]", "R = [[1.0, 1.0], [1.0, 1.0]]"),
            "sensors[1].R",
            "not positive definite (smallest eigenvalue",
        ),
        (
            edit("cov = [[1.0, 0.0], [0.0, 1.0]]", "cov = [[1.0, 2.0], [2.0, 1.0]]"),
            "prior.cov",
            "not positive definite (smallest eigenvalue -1)",
        ),
        (
            # singular: a filter covariance must be invertible
            edit("cov = [[1.0, 0.0], [0.0, 1.0]]", "cov = [[0.0, 0.0], [0.0, 1.0]]"),
            "prior.cov",
            "not positive definite",
        ),
        (
            explicit("[[1.0, 1.0], [0.0, 1.0]]", "[[-0.1, 0.0], [0.0, 1.0]]"),
            "model.Q",
            "not positive semidefinite",
        ),
        (
            BASE + "[truth]\ninitial_cov = [[-1.0, 0.0], [0.0, 0.0]]\n",
            "truth.initial_cov",
            "not positive semidefinite",
        ),
        (edit("n0 = 0.16", "n0 = -0.16"), "model.n0", "must be >= 0"),
    ],
)
def test_definiteness(text: str, key: str, reason: str) -> None:
    fails(text, f"{SRC}: {key}: {reason}")


def test_semidefinite_is_allowed_where_it_should_be() -> None:
    # Rank-one process noise (G Q G^T written out) and a point-mass truth: both fine.
    s = scenario_from_text(
        explicit("[[1.0, 1.0], [0.0, 1.0]]", "[[0.25, 0.5], [0.5, 1.0]]")
        + "[truth]\ninitial_mean = [3.0, 0.0]\ninitial_cov = [[0.0, 0.0], [0.0, 0.0]]\n",
        SRC,
    )
    np.testing.assert_array_equal(s.system.truth_initial.cov, np.zeros((2, 2)))
    np.testing.assert_array_equal(s.system.truth_initial.mean, [3.0, 0.0])


def test_full_block_R_must_be_positive_definite() -> None:
    three = BASE + '[[sensors]]\nname = "c"\nH = [1.0, 0.0]\nR = 1.0\n'
    # One pair alone already breaks it: blamed on that correlation.
    fails(
        three + '[[correlations]]\nsensors = ["a", "c"]\ncov = 1.0\n',
        f"{SRC}: correlations[0].cov: makes the joint noise covariance of 'a' and 'c' not "
        "positive definite",
    )
    # Each pair is fine (|rho| = 0.9) but together they are not: rho_ab = rho_ac = 0.9,
    # rho_bc = -0.9 cannot all hold.
    text = edit("R = [[2.0, 0.1], [0.1, 0.5]]", "R = 1.0", three).replace(
        "H = [[1.0, 0.0], [0.0, 1.0]]", "H = [[1.0, 0.0]]"
    )
    text += '[[correlations]]\nsensors = ["a", "b"]\ncov = 0.9\n'
    text += '[[correlations]]\nsensors = ["a", "c"]\ncov = 0.9\n'
    text += '[[correlations]]\nsensors = ["b", "c"]\ncov = -0.9\n'
    fails(
        text,
        f"{SRC}: correlations: the full measurement noise covariance R",
        "not positive definite",
    )


def test_duplicate_sensor_names() -> None:
    fails(
        edit('name = "b"', 'name = "a"'),
        f"{SRC}: sensors[1].name: duplicate sensor name 'a'",
        "sensors[0]",
    )


def test_invalid_names() -> None:
    fails(edit('name = "b"', 'name = "b/c"'), "sensors[1].name: invalid name")
    fails(edit('name = "a"', 'name = "a:1"'), "sensors[0].name: invalid name")
    fails(edit('name = "base"', 'name = "../x"'), "scenario.name: invalid name")
    fails(edit('["position", "velocity"]', '["p", "p"]'), "scenario.state_names[1]: duplicate")


@pytest.mark.parametrize(
    ("old", "new", "key", "reason"),
    [
        ("steps = 5", "steps = -1", "scenario.steps", "must be >= 0, got -1"),
        ("runs = 10", "runs = -3", "scenario.runs", "must be >= 1, got -3"),
        ("seed = 1", "seed = -1", "scenario.seed", "must be >= 0, got -1"),
        ("dt = 1.0", "dt = 0.0", "scenario.dt", "must be > 0, got 0"),
        ("dt = 1.0", "dt = -0.5", "scenario.dt", "must be > 0, got -0.5"),
    ],
)
def test_ranges(old: str, new: str, key: str, reason: str) -> None:
    fails(edit(old, new), f"{SRC}: {key}: {reason}")


@pytest.mark.parametrize("value", ["0.0", "1.0", "1.5", "-0.1"])
def test_confidence_range(value: str) -> None:
    fails(
        BASE + f"[evaluate]\nconfidence = {value}\n",
        f"{SRC}: evaluate.confidence: must be in (0, 1)",
    )


def test_evaluate_values() -> None:
    s = scenario_from_text(BASE + "[evaluate]\nconfidence = 0.99\nsample_runs = 0\n", SRC)
    assert (s.confidence, s.sample_runs) == (0.99, 0)
    fails(BASE + "[evaluate]\nsample_runs = -1\n", "evaluate.sample_runs: must be >= 0")


def test_architectures() -> None:
    s = scenario_from_text(BASE + '[estimate]\narchitectures = ["CKF", "SKF:b", "SKF"]\n', SRC)
    assert s.architectures == ("CKF", "SKF:b", "SKF")
    fails(
        BASE + '[estimate]\narchitectures = ["CKF", "EKF"]\n',
        f"{SRC}: estimate.architectures[1]: unknown architecture 'EKF' (known: CKF",
    )
    fails(
        BASE + '[estimate]\narchitectures = ["SKF:zz"]\n',
        "estimate.architectures[0]: architecture 'SKF:zz': no sensor 'zz'",
    )
    fails(
        BASE + '[estimate]\narchitectures = ["CKF", "CKF"]\n',
        "estimate.architectures[1]: duplicate architecture 'CKF'",
    )
    fails(BASE + "[estimate]\narchitectures = []\n", "estimate.architectures: empty")
    fails(BASE + '[estimate]\narchitectures = "CKF"\n', "estimate.architectures: expected a list")


@pytest.mark.parametrize(
    ("pair", "reason"),
    [
        ('["a", "zz"]', "unknown sensor 'zz' (sensors: a, b)"),
        ('["a", "a"]', "a sensor cannot be correlated with itself ('a')"),
        ('["a"]', "expected two sensor names"),
        ('"a"', "expected two sensor names"),
    ],
)
def test_correlation_sensors(pair: str, reason: str) -> None:
    fails(
        BASE + f"[[correlations]]\nsensors = {pair}\ncov = 0.1\n",
        f"{SRC}: correlations[0].sensors: {reason}",
    )


def test_correlation_duplicate_pair() -> None:
    text = BASE + '[[correlations]]\nsensors = ["a", "b"]\ncov = [0.1, 0.0]\n'
    text += '[[correlations]]\nsensors = ["b", "a"]\ncov = [[0.1], [0.0]]\n'
    fails(text, "correlations[1].sensors: pair ('b', 'a') already correlated in correlations[0]")


def test_correlation_given_reversed_is_transposed() -> None:
    forward = scenario_from_text(
        BASE + '[[correlations]]\nsensors = ["a", "b"]\ncov = [[0.3, 0.1]]\n', SRC
    )
    reverse = scenario_from_text(
        BASE + '[[correlations]]\nsensors = ["b", "a"]\ncov = [[0.3], [0.1]]\n', SRC
    )
    for s in (forward, reverse):
        assert list(s.system.cross_R) == [(0, 1)]
        np.testing.assert_array_equal(s.system.cross_R[(0, 1)], [[0.3, 0.1]])
    np.testing.assert_array_equal(forward.system.R, reverse.system.R)
    np.testing.assert_array_equal(forward.system.R[0, 1:], [0.3, 0.1])


def test_prior_or_truth_required() -> None:
    no_prior = BASE.replace("[prior]\nmean = [0.0, 1.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n", "")
    fails(no_prior, f"{SRC}: prior: missing: give [prior]", "[truth]")
    fails(
        no_prior + "[truth]\ninitial_mean = [0.0, 0.0]\n",
        f"{SRC}: truth.initial_cov: missing required key (there is no [prior]",
    )
    s = scenario_from_text(
        no_prior + "[truth]\ninitial_mean = [5.0, 0.0]\ninitial_cov = [[0.0, 0.0], [0.0, 0.0]]\n",
        SRC,
    )
    assert s.system.prior is None
    np.testing.assert_array_equal(s.system.truth_initial.mean, [5.0, 0.0])


def test_truth_defaults_to_prior_per_key() -> None:
    s = scenario_from_text(BASE + "[truth]\ninitial_mean = [1.0, 2.0]\n", SRC)
    np.testing.assert_array_equal(s.system.initial.mean, [1.0, 2.0])
    np.testing.assert_array_equal(s.system.initial.cov, s.system.prior.cov)


def test_messages_are_single_line_even_with_newlines_in_values() -> None:
    fails(edit('name = "b"', 'name = "b\\nc"'), "sensors[1].name: invalid name")
    fails(edit("steps = 5", 'steps = """\nfive\n"""'), "scenario.steps: expected an integer")


# ---------------------------------------------------------------------------------------------
# CLI-style overrides


def test_overrides() -> None:
    path = PIPELINE / "ajgl2009.toml"
    s = load_scenario(path, runs=100, steps=5, seed=42)
    assert (s.runs, s.steps, s.seed) == (100, 5, 42)
    base = load_scenario(path)
    t = scenario_with(base, runs=7)
    assert (t.runs, t.steps, t.seed) == (7, base.steps, base.seed)
    assert base.runs == 10000  # unchanged
    assert scenario_with(base) is base
    assert t.source == base.source and t.system is base.system


@pytest.mark.parametrize(
    ("kwargs", "reason"),
    [
        ({"runs": 0}, "--runs: must be >= 1, got 0"),
        ({"steps": -1}, "--steps: must be >= 0, got -1"),
        ({"seed": -5}, "--seed: must be >= 0, got -5"),
        (
            {"runs": 2.5},
            "--runs: expected an integer, got float 2.5",
        ),
        ({"seed": True}, "--seed: expected an integer, got boolean true"),
    ],
)
def test_bad_overrides(kwargs: dict, reason: str) -> None:
    path = PIPELINE / "ajgl2009.toml"
    with pytest.raises(ValidationError) as info:
        load_scenario(path, **kwargs)
    assert str(info.value) == f"{path}: {reason}"


def test_load_scenario_reports_the_path(tmp_path: Path) -> None:
    p = tmp_path / "x.toml"
    p.write_text(edit("R = 1.0", "R = -1.0"))
    with pytest.raises(ValidationError, match=re.escape(f"{p}: sensors[0].R: not positive")):
        load_scenario(p)


# ---------------------------------------------------------------------------------------------
# system_to_dict / system_from_dict


def _assert_same_system(a, b) -> None:
    for name in ("F", "Q", "H", "R"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert (a.G is None) == (b.G is None)
    if a.G is not None:
        np.testing.assert_array_equal(a.G, b.G)
    assert [s.name for s in a.sensors] == [s.name for s in b.sensors]
    assert a.dt == b.dt and a.state_names == b.state_names
    assert a.cross_R.keys() == b.cross_R.keys()
    for p, q in ((a.prior, b.prior), (a.initial, b.initial)):
        assert (p is None) == (q is None)
        if p is not None:
            np.testing.assert_array_equal(p.mean, q.mean)
            np.testing.assert_array_equal(p.cov, q.cov)


@pytest.mark.parametrize(
    "text",
    [
        (PIPELINE / "ajgl2009.toml").read_text(),
        (PIPELINE / "heterogeneous.toml").read_text(),
        explicit("[[1.0, 1.0], [0.0, 1.0]]", "0.16", G="[[0.5], [1.0]]")
        + "[truth]\ninitial_mean = [1.0, 2.0]\ninitial_cov = [[0.0, 0.0], [0.0, 0.0]]\n",
    ],
)
def test_system_dict_round_trip(text: str) -> None:
    system = scenario_from_text(text, SRC).system
    d = system_to_dict(system)
    again = system_from_dict(json.loads(json.dumps(d)))
    _assert_same_system(system, again)
    assert system_to_dict(again) == d


def test_system_dict_is_a_model_file() -> None:
    system = load_scenario(PIPELINE / "heterogeneous.toml").system
    d = system_to_dict(system)
    assert d["sensors"][1]["R"] == [[4.0, 0.2], [0.2, 0.25]]
    assert {tuple(c["sensors"]) for c in d["correlations"]} == {
        ("laser", "beacon"),
        ("gnss", "odometer"),
    }


def test_system_from_dict_validates() -> None:
    d = system_to_dict(ajgl2009())
    d["sensors"][0]["R"] = [[-1.0]]
    with pytest.raises(ValidationError, match=r"^meta: sensors\[0\]\.R: not positive definite"):
        system_from_dict(d, "meta")


# ---------------------------------------------------------------------------------------------
# Model-only files


def test_load_model_file(tmp_path: Path) -> None:
    p = tmp_path / "model.toml"
    p.write_text(
        EXPLICIT_MODEL
        + '[[sensors]]\nname = "s1"\nH = [1.0, 0.0]\nR = 2.0\n'
        + '[[sensors]]\nname = "s2"\nH = [0.0, 1.0]\nR = 0.5\n'
    )
    system = load_model(p)
    np.testing.assert_array_equal(system.F, [[1.0, 1.0], [0.0, 1.0]])
    np.testing.assert_array_equal(system.R, np.diag([2.0, 0.5]))
    assert system.prior is None and system.initial is None
    assert system.state_names == ("x1", "x2") and system.dt == 1.0


def test_load_model_constant_velocity_needs_dt() -> None:
    text = '[model]\nkind = "constant-velocity"\nn0 = 0.16\n'
    text += '[[sensors]]\nname = "a"\nH = [1.0, 0.0]\nR = 1.0\n'
    fails(text, f"{SRC}: scenario.dt: missing required key", model=True)
    system = model_from_text("[scenario]\ndt = 2.0\n" + text, SRC)
    np.testing.assert_allclose(system.Q, np.array([[8 / 3, 2.0], [2.0, 2.0]]) * 0.32)


def test_load_model_accepts_a_scenario_file() -> None:
    system = load_model(PIPELINE / "ajgl2009.toml")
    _assert_same_system(system, load_scenario(PIPELINE / "ajgl2009.toml").system)


def test_load_model_still_validates() -> None:
    fails(
        EXPLICIT_MODEL + '[[sensors]]\nname = "a"\nH = [1.0]\nR = 1.0\n',
        "sensors[0].H: shape 1x1",
        model=True,
    )
    fails(
        "[scenario]\nsteps = -1\n" + BASE[BASE.index("[model]") :],
        "scenario.steps: must be >= 0",
        model=True,
    )
    fails("[scenario]\nfoo = 1\n" + EXPLICIT_MODEL, "scenario: unknown key 'foo'", model=True)


def test_pipeline_files_are_plain_toml() -> None:
    files = sorted(PIPELINE.glob("*.toml"))
    assert len(files) >= 5
    kinds = set()
    for p in files:
        tomllib.loads(p.read_text())
        kinds.add(load_scenario(p).kind)
    assert kinds == {"state", "identity"}


def test_no_prior_needs_an_invertible_f() -> None:
    text = """
[scenario]
name = "x"
steps = 3
runs = 2
seed = 0
dt = 1.0
[model]
F = [[1.0, 1.0], [0.0, 0.0]]
Q = [[1.0, 0.0], [0.0, 1.0]]
[truth]
initial_mean = [0.0, 0.0]
initial_cov = [[1.0, 0.0], [0.0, 1.0]]
[[sensors]]
name = "a"
H = [1.0, 0.0]
R = 1.0
"""
    with pytest.raises(ValidationError, match="model.F: must be invertible when there is no"):
        scenario_from_text(text, SRC)
