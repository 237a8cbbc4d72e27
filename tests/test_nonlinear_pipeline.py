"""Nonlinear scenarios through the CLI (DESIGN.md, "Nonlinear sensors and motion"): the two
pipeline scenarios run, the CKF's Monte Carlo MSE stands above the posterior Cramér-Rao bound
and its ANEES near n, `expected` is null and `pcrb` present, dropouts, multi-rate sensors and
irregular instants run, sweeps run, and each kind of bad input is one line."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error

from fusionlog.scenario import load_scenario, scenario_from_text, system_from_dict, system_to_dict

ROOT = Path(__file__).resolve().parent.parent
RADAR = ROOT / "pipeline" / "radar_tracking.toml"
TURN = ROOT / "pipeline" / "coordinated_turn.toml"


def _summary(d: Path) -> dict:
    return json.loads((d / "summary.json").read_text())


def test_radar_ckf_is_above_the_pcrb_and_consistent(tmp_path: Path) -> None:
    res = ok("run", RADAR, "--out-dir", tmp_path, "--runs", "400", "--arch", "CKF", "--arch", "MSC")
    s = _summary(tmp_path)
    ckf = s["architectures"]["CKF"]
    bound = s["pcrb"]["mse"]
    assert ckf["expected"] is None and s["architectures"]["MSC"]["expected"] is None
    # the bound holds for any estimator: the Monte Carlo MSE is above it up to its own error
    assert ckf["mse"] >= bound - 3 * ckf["stderr"]["mse"]
    assert len(s["pcrb"]["mse_per_state"]) == 4
    # ANEES of a consistent filter: n = 4 within a few of its standard errors
    assert abs(ckf["anees"] - 4.0) < 4 * ckf["stderr"]["anees"] + 0.05
    # MSC ignores the correlation of its locals' errors (the shared prior and process noise)
    assert s["architectures"]["MSC"]["anees"] > 4.5
    assert re.search(r"^PCRB \(bound\)\s+\d", res.stdout, re.M)
    table = ok("summary", tmp_path / "evaluation.rrd").stdout
    assert "PCRB (bound)" in table
    # a summary with null `expected` beside its PCRB is a valid summary to compare
    ok("compare", tmp_path / "summary.json", tmp_path / "summary.json")


def test_coordinated_turn_with_both_filters(tmp_path: Path) -> None:
    for filt in ("UKF", "EKF"):
        d = tmp_path / filt
        ok("run", TURN, "--out-dir", d, "--runs", "60", "--steps", "12", "--filter", filt,
           "--arch", "CKF", "--arch", "HKF", "--arch", "FBS")  # fmt: skip
        s = _summary(d)
        prov = json.loads(_provenance_model(d / "estimates.mcap"))
        assert prov["estimate"]["filter"] == filt
        a = s["architectures"]
        # HKF with feedback adds the locals' information: with EKF locals linearised at the
        # one fused prediction that is the CKF's stacked update; UKF locals each sample h alone
        rel = 1e-9 if filt == "EKF" else 0.05
        assert a["HKF"]["mse"] == pytest.approx(a["CKF"]["mse"], rel=rel)
        assert a["FBS"]["mse"] < a["CKF"]["mse"]
        assert s["pcrb"]["mse"] > 0


def _provenance_model(path: Path) -> str:
    from fusionlog.io.mcap import McapFile

    return McapFile(path).metadata["fusionlog.provenance"]["model"]


def test_estimate_filter_override_and_linear_scenarios_unchanged(tmp_path: Path) -> None:
    ok("simulate", RADAR, "-o", tmp_path / "s.mcap", "--runs", "20", "--steps", "8")
    ok("estimate", tmp_path / "s.mcap", "-o", tmp_path / "e.mcap", "--filter", "UKF")
    assert json.loads(_provenance_model(tmp_path / "e.mcap"))["estimate"]["filter"] == "UKF"
    paper = ROOT / "pipeline" / "ajgl2009.toml"
    ok("run", paper, "--out-dir", tmp_path / "kf", "--runs", "30", "--steps", "10")
    ok("run", paper, "--out-dir", tmp_path / "ekf", "--runs", "30", "--steps", "10",
       "--filter", "EKF")  # fmt: skip
    kf, ekf = _summary(tmp_path / "kf"), _summary(tmp_path / "ekf")
    assert kf["architectures"] == ekf["architectures"] and "pcrb" not in ekf


def _radar_text(**edits: str) -> str:
    text = RADAR.read_text()
    for old, new in edits.items():
        old = old.replace("_", " ")
        assert old in text, old
        text = text.replace(old, new)
    return text


def test_dropouts_multirate_and_irregular_instants(tmp_path: Path) -> None:
    """A radar that drops a fifth of its measurements, and one every 1.5 s from 0.5 s: the
    instants are the union of the sampling times (irregular)."""
    text = (
        RADAR.read_text()
        .replace("position = [5000.0, 0.0]", "position = [5000.0, 0.0]\nperiod = 1.5\noffset = 0.5")
        .replace("position = [0.0, 0.0]", "position = [0.0, 0.0]\ndropout = 0.2")
    )
    f = tmp_path / "radar.toml"
    f.write_text(text)
    sc = load_scenario(f)
    assert not sc.schedule.regular
    ok("run", f, "--out-dir", tmp_path / "o", "--runs", "200", "--steps", "12",
       "--arch", "CKF", "--arch", "MSC-GMF", "--arch", "FBS")  # fmt: skip
    s = _summary(tmp_path / "o")
    ckf = s["architectures"]["CKF"]
    assert ckf["mse"] >= s["pcrb"]["mse"] - 3 * ckf["stderr"]["mse"]
    assert abs(ckf["anees"] - 4.0) < 0.5


def test_sweep_over_a_radar_position(tmp_path: Path) -> None:
    ok("sweep", RADAR, "--vary", "sensors.radar2.position=[5000.0, 0.0],[2500.0, 500.0]",
       "--runs", "40", "--workers", "0", "--out-dir", tmp_path)  # fmt: skip
    import pyarrow.parquet as pq

    rows = pq.read_table(tmp_path / "sweep.parquet").to_pylist()
    assert len(rows) == 2 * 8
    assert all(r["expected_mse"] is None and r["mse"] > 0 for r in rows)
    # each point's PCRB is that of `fusionlog run` with the point's seed (the same runs)
    points = _summary(tmp_path)["points"]
    far = _radar_text().replace("position = [5000.0, 0.0]", "position = [2500.0, 500.0]")
    f = tmp_path / "point1.toml"
    f.write_text(far)
    ok("run", f, "--out-dir", tmp_path / "p1", "--runs", "40", "--seed", str(points[1]["seed"]),
       "--arch", "CKF")  # fmt: skip
    assert points[1]["pcrb"]["mse"] == pytest.approx(_summary(tmp_path / "p1")["pcrb"]["mse"])
    # no exact analysis: sweep.rrd's MSE view says its points are Monte Carlo dots only
    assert any("(dots: Monte Carlo, no exact values)" in t for t in _view_names(tmp_path))
    assert not any("lines: exact" in t for t in _view_names(tmp_path))


def _view_names(d: Path) -> list[str]:
    """The view titles of the default blueprint of `d`/sweep.rrd."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(d / "sweep.rrd"))
    return [
        ch.to_record_batch().column("ViewBlueprint:display_name").to_pylist()[0][0]
        for ch in reader.store(store=reader.blueprints()[0]).stream().to_chunks()
        if "ViewBlueprint:display_name" in ch.to_record_batch().schema.names
    ]


def test_distributed_run_has_the_plain_runs_pcrb(tmp_path: Path) -> None:
    """`run --workers 0` (blocks computed apart, merged as sums): the PCRB of all the runs,
    as a plain run's."""
    ok("run", RADAR, "--out-dir", tmp_path / "d", "--runs", "300", "--workers", "0",
       "--block-runs", "64", "--arch", "CKF")  # fmt: skip
    ok("run", RADAR, "--out-dir", tmp_path / "p", "--runs", "300", "--arch", "CKF")
    d, p = _summary(tmp_path / "d"), _summary(tmp_path / "p")
    assert d["pcrb"]["mse"] == pytest.approx(p["pcrb"]["mse"], rel=1e-12)
    assert d["architectures"]["CKF"]["mse"] == pytest.approx(p["architectures"]["CKF"]["mse"])


def test_the_system_round_trips_through_its_record() -> None:
    for path in (RADAR, TURN):
        system = load_scenario(path).system
        back = system_from_dict(json.loads(json.dumps(system_to_dict(system))))
        assert back.filter == system.filter and back.ukf == system.ukf
        assert type(back.motion) is type(system.motion)
        for a, b in zip(back.sensors, system.sensors, strict=True):
            assert (a.kind, a.name) == (b.kind, b.name)
            np.testing.assert_array_equal(a.R, b.R)
            x = np.ones(system.n)
            np.testing.assert_array_equal(a.jacobian(x), b.jacobian(x))


@pytest.mark.parametrize(
    ("edit", "fragments"),
    [
        ({'filter = "EKF"': ""}, ["estimate.filter", "EKF", "UKF"]),
        ({'filter = "EKF"': 'filter = "PF"'}, ["estimate.filter", "'PF'"]),
        (
            {'position = [0.0, 0.0]': 'position = [0.0, 0.0]\nposition_states = ["x", "z"]'},
            ["sensors[0].position_states", "no state 'z'"],
        ),
        ({"position = [0.0, 0.0]": "position = [0.0]"},
         ["sensors[0].position", "expected 2 (the sensor's x and y)"]),
        ({"R = [[100.0, 0.0], [0.0, 3.0e-4]]": "R = [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]]\n#"},
         ["sensors[0].R", "expected 2x2"]),
        ({'filter = "EKF"': 'filter = "UKF"\nukf = {alpha = 0.5, kappa = -4.0}'},
         ["estimate.ukf.kappa", "<= 0"]),
        ({'filter = "EKF"': 'filter = "UKF"\nukf = {beta = 2.0, gamma = 1.0}'},
         ["estimate.ukf", "gamma"]),
        ({'filter = "EKF"': 'filter = "UKF"\nukf = {alpha = 1e200}'},
         ["estimate.ukf.alpha", "overflows"]),  # was an internal OverflowError, exit 3
        ({'filter = "EKF"': 'filter = "UKF"\nukf = {alpha = 1e-300}'},
         ["estimate.ukf.alpha", "underflows"]),  # it named kappa
        ({'filter = "EKF"': 'filter = "UKF"\nukf = {alpha = 1e153}'},
         ["estimate.ukf.alpha", "must be in (0, 1]"]),  # accepted; failed in the filter
        ({'filter = "EKF"': 'filter = "UKF"\nukf = {kappa = 1e308}'},
         ["estimate.ukf.kappa", "must be in (-4, 75.5023]"]),  # accepted; failed in the filter
    ],
)  # fmt: skip
def test_bad_input_is_one_line(tmp_path: Path, edit: dict, fragments: list[str]) -> None:
    text = RADAR.read_text()
    for old, new in edit.items():
        assert old in text, old
        text = text.replace(old, new)
    f = tmp_path / "bad.toml"
    f.write_text(text)
    one_line_error(cli("simulate", f, "-o", tmp_path / "s.mcap"), str(f), *fragments)


#: A target due west of a bearing sensor and a radar at the origin: bearings about +-pi.
WEST = """
[scenario]
name = "west"
steps = 3
runs = 500
seed = 1
dt = 1.0
[model]
kind = "constant-velocity"
axes = 2
n0 = 0.001
[prior]
mean = [-100.0, 0.0, 0.0, 0.0]
cov = [[1.0, 0, 0, 0], [0, 0.01, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 0.01]]
[[sensors]]
name = "cam"
kind = "bearing"
position = [0.0, 0.0]
R = 1e-2
[[sensors]]
name = "radar"
kind = "range-bearing"
position = [0.0, 0.0]
R = [[1.0, 0.0], [0.0, 1e-2]]
[estimate]
filter = "EKF"
architectures = ["CKF"]
"""


def test_simulated_bearings_are_in_the_half_open_interval(tmp_path: Path) -> None:
    """A bearing read with its noise is an angle in (-pi, pi] like the noise-free one (they
    were h + v, up to pi + 0.35 and below -pi here); the estimates are unchanged by it."""
    from fusionlog.io.mcap import McapFile

    f = tmp_path / "west.toml"
    f.write_text(WEST)
    ok("run", f, "--out-dir", tmp_path / "o")
    mf = McapFile(tmp_path / "o" / "sensors.mcap")
    ((_, _, data),) = mf.iter_run_blocks(["/sensors/cam", "/sensors/radar"], 500)
    for b in (data["/sensors/cam"][..., 0], data["/sensors/radar"][..., 1]):
        assert np.all(b > -np.pi) and np.all(b <= np.pi)
        assert (b > 3.0).mean() > 0.3 and (b < -3.0).mean() > 0.3  # both sides of +-pi
    s = _summary(tmp_path / "o")["architectures"]["CKF"]
    assert abs(s["anees"] - 4.0) < 4 * s["stderr"]["anees"] + 0.05


def test_a_sensor_at_the_target_is_refused_with_run_and_instant(tmp_path: Path) -> None:
    text = RADAR.read_text().replace("position = [0.0, 0.0]", "position = [2000.0, 3000.0]")
    f = tmp_path / "on_target.toml"
    f.write_text(text)
    ok("simulate", f, "-o", tmp_path / "s.mcap", "--runs", "3", "--steps", "2")
    res = cli("estimate", tmp_path / "s.mcap", "-o", tmp_path / "e.mcap", "--arch", "CKF")
    one_line_error(res, "radar1", "range 0", "run 0", "instant 0")


@pytest.mark.parametrize("ukf", ["alpha = 1e-8"])
def test_a_filter_that_fails_names_the_file_the_architecture_and_the_step(
    tmp_path: Path, ukf: str
) -> None:
    """A predicted covariance that is not positive definite (accepted parameters, hopeless
    numbers): one line naming the sensors file, the architecture and the step, as the linear
    filters' failures do (it was an internal error with numpy's warnings, or a line naming
    none of them), no estimates file. (alpha = 1e153 and kappa = 1e308, which spread the
    sigma points past the float range, are now refused when loaded: test_bad_input_is_one_line.)"""
    f = tmp_path / "ukf.toml"
    f.write_text(RADAR.read_text().replace('filter = "EKF"', f'filter = "UKF"\nukf = {{{ukf}}}'))
    ok("simulate", f, "-o", tmp_path / "s.mcap", "--runs", "5", "--steps", "3")
    res = cli("estimate", tmp_path / "s.mcap", "-o", tmp_path / "e.mcap")
    one_line_error(res, "s.mcap: architecture ", ", step ")
    assert not (tmp_path / "e.mcap").exists()


def test_turn_scenario_errors() -> None:
    text = TURN.read_text()
    with pytest.raises(Exception, match=r"model.q_turn.*> 0"):
        scenario_from_text(text.replace("q_turn = 1.0e-5", "q_turn = 0.0"))
    with pytest.raises(Exception, match=r"model.n0.*not allowed"):
        scenario_from_text(text.replace("q_turn = 1.0e-5", "q_turn = 1.0e-5\nn0 = 1.0"))
    # q is per axis, not per state (it said "expected 2 (the number of states)" of 5 states)
    with pytest.raises(Exception, match=r"model.q: length 1, expected 2 \(\[qx, qy\]: one per"):
        scenario_from_text(text.replace("q = [0.05, 0.05]", "q = [0.05]"))
    with pytest.raises(Exception, match=r"prior.*EKF and UKF start from"):
        start = text.index("[prior]")
        end = text.index("[[sensors]]")
        cov = "[[1.0, 0, 0, 0, 0], [0, 1.0, 0, 0, 0], [0, 0, 1.0, 0, 0], [0, 0, 0, 1.0, 0], " + (
            "[0, 0, 0, 0, 1e-4]]"
        )
        truth = f"[truth]\ninitial_mean = [0.0, 15.0, 500.0, 0.0, 0.05]\ninitial_cov = {cov}\n"
        scenario_from_text(text[:start] + truth + text[end:])


def test_python_api_gives_the_cli_numbers_on_irregular_instants(tmp_path: Path) -> None:
    """`fl.load/simulate/estimate/evaluate` on a nonlinear scenario with a radar every 1.5 s
    from 0.5 s (irregular instants) and dropouts: the CLI's summary and CKF estimates."""
    import fusionlog as fl
    from fusionlog.io.mcap import McapFile

    text = (
        RADAR.read_text()
        .replace("position = [5000.0, 0.0]", "position = [5000.0, 0.0]\nperiod = 1.5\noffset = 0.5")
        .replace("position = [0.0, 0.0]", "position = [0.0, 0.0]\ndropout = 0.1")
    )
    f = tmp_path / "radar.toml"
    f.write_text(text)
    ok("run", f, "--out-dir", tmp_path / "cli", "--runs", "50", "--steps", "9",
       "--arch", "CKF", "--arch", "MSC-GMF")  # fmt: skip
    cli_summary = _summary(tmp_path / "cli")
    sc = fl.load(f)
    sim = fl.simulate(sc, runs=50, seed=sc.seed, steps=9)
    est = fl.estimate(sc, sim, ["CKF", "MSC-GMF"])
    ev = fl.evaluate(sc, sim, est)
    assert ev.summary["pcrb"]["mse"] == pytest.approx(cli_summary["pcrb"]["mse"], rel=1e-12)
    for a in ("CKF", "MSC-GMF"):
        assert ev.summary["architectures"][a]["mse"] == pytest.approx(
            cli_summary["architectures"][a]["mse"], rel=1e-12
        )
    mf = McapFile(tmp_path / "cli" / "estimates.mcap")
    _, _, data = next(mf.iter_run_blocks(["/estimates/CKF"], 10**6))
    mean, cov = data["/estimates/CKF"]
    np.testing.assert_allclose(est["CKF"].mean, mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(est["CKF"].cov, cov, rtol=0, atol=1e-9)
