"""Identity scenarios (seed 004: BAYES and DS) through simulate / estimate / evaluate.

End to end through the CLI (click's CliRunner, in-process), plus the numbers against direct
computations: the BAYES posterior against a plain product of confusion-matrix entries, the DS
combination against the dict implementation of Dempster's rule, and the identity linking them
(the normalised DS plausibility is the Bayes posterior with a uniform prior and the reports'
contour functions as likelihoods). Small runs: the file takes well under 30 s.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, listing, ok, one_line_error

from fusionlog.compare import check_summary, compare_summaries
from fusionlog.identity import belief, dempster_combine, plausibility
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapFile, McapWriter
from fusionlog.io.rrd import read_recording, recording_id_for
from fusionlog.report import format_table
from fusionlog.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
AIRCRAFT = ROOT / "pipeline" / "aircraft_identity.toml"
BIN = Path(sys.executable).parent
RERUN = str(BIN / "rerun") if (BIN / "rerun").exists() else shutil.which("rerun")
SMALL = ["--runs", "300", "--steps", "20"]
OUTPUTS = ("sensors.mcap", "estimates.mcap", "evaluation.rrd", "summary.json")
CLASSES = ["Learjet", "Falcon", "Caravan"]


def write_toml(path: Path, text: str) -> Path:
    path.write_text(textwrap.dedent(text))
    return path


def read(path: Path) -> dict[str, np.ndarray]:
    f = McapFile(path)
    return f.read_all(sorted(f.topics))


@pytest.fixture(scope="module")
def aircraft(tmp_path_factory) -> tuple[Path, str]:
    """One `fusionlog run` of the aircraft scenario (300 runs, K = 20); its stdout."""
    d = tmp_path_factory.mktemp("aircraft") / "out"
    res = ok("run", AIRCRAFT, "--out-dir", d, *SMALL)
    return d, res.stdout


# ------------------------------------------------------------------------------------------
# end to end
# ------------------------------------------------------------------------------------------


def test_run_writes_outputs_and_prints_the_table(aircraft) -> None:
    d, stdout = aircraft
    assert listing(d) == sorted(OUTPUTS)  # no temp file left behind
    lines = stdout.splitlines()
    assert lines[0] == "aircraft_identity: M = 300 runs, K = 20, seed 2004"
    assert lines[1].split()[:3] == ["architecture", "accuracy", "accuracy"]
    assert [ln.split()[0] for ln in lines[3:5]] == ["BAYES", "DS"]
    assert "BAYES and DS decide differently" in lines[5]
    s = json.loads((d / "summary.json").read_text())
    assert s["kind"] == "identity" and s["scenario"] == "aircraft_identity" and s["seed"] == 2004
    assert (s["runs"], s["steps"], s["state_names"]) == (300, 20, CLASSES)
    assert list(s["architectures"]) == ["BAYES", "DS"]
    common = {"accuracy", "log_loss", "mean_p_true", "final", "stderr"}
    assert set(s["architectures"]["BAYES"]) == common
    ds = s["architectures"]["DS"]
    assert set(ds) == common | {
        "mean_belief_true",
        "mean_plausibility_true",
        "mean_conflict",
        "total_conflict",
    }
    assert set(ds["final"]) == {
        "accuracy",
        "log_loss",
        "mean_p_true",
        "mean_belief_true",
        "mean_plausibility_true",
        "accumulated_conflict",
    }
    assert ds["total_conflict"] == 0.0  # every reliability < 1
    assert ds["mean_belief_true"] <= ds["mean_p_true"] <= ds["mean_plausibility_true"]
    assert 0 < s["disagreement"] < 0.2 and 0 <= s["final_disagreement"] <= s["disagreement"]
    for a in ("BAYES", "DS"):
        e = s["architectures"][a]
        assert 0.8 < e["accuracy"] < e["final"]["accuracy"] <= 1
        assert e["final"]["log_loss"] < e["log_loss"]


def test_mcap_layout(aircraft) -> None:
    d, _ = aircraft
    sens, est = McapFile(d / "sensors.mcap"), McapFile(d / "estimates.mcap")
    assert sorted(sens.topics) == ["/sensors/esm", "/sensors/imager", "/sensors/radar", "/truth"]
    assert {sens.dim_of(t) for t in sens.topics} == {1}
    assert {sens.schema_of(t) for t in sens.topics} == {"fusionlog.Block"}
    assert (est.dim_of("/estimates/BAYES"), est.dim_of("/estimates/DS")) == (3, 8)
    assert {est.schema_of(t) for t in est.topics} == {"fusionlog.Block"}
    meta = sens.metadata["fusionlog.scenario"]
    assert meta["kind"] == "identity" and meta["runs"] == "300" and meta["steps"] == "20"
    assert json.loads(meta["identity"])["sets"] == {"fast": ["Learjet", "Falcon"]}
    cols = json.loads(est.metadata["fusionlog.provenance"]["columns"])
    assert cols["DS"] == [
        *(f"Bel({c})" for c in CLASSES),
        *(f"Pl({c})" for c in CLASSES),
        "conflict",
        "accumulated_conflict",
    ]
    data = read(d / "sensors.mcap")
    truth = data["/truth"][..., 0]
    assert (truth == truth[:, :1]).all() and set(np.unique(truth)) <= {0.0, 1.0, 2.0}
    assert set(np.unique(data["/sensors/radar"])) <= {0.0, 1.0, 2.0}
    e = read(d / "estimates.mcap")
    np.testing.assert_allclose(e["/estimates/BAYES"].sum(-1), 1.0, rtol=1e-12)
    bel, pl = e["/estimates/DS"][..., :3], e["/estimates/DS"][..., 3:6]
    assert (bel <= pl + 1e-12).all() and (bel.sum(-1) <= 1 + 1e-12).all()


@pytest.mark.skipif(RERUN is None, reason="rerun CLI missing")
def test_rerun_verify_accepts_the_recording(aircraft) -> None:
    d, _ = aircraft
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    proc = subprocess.run(
        [RERUN, "rrd", "verify", str(d / "evaluation.rrd")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr


def test_summary_reads_the_recording_back(aircraft) -> None:
    d, stdout = aircraft
    res = ok("summary", d / "evaluation.rrd")
    lines = res.stdout.splitlines()
    assert lines[0] == "aircraft_identity: M = 300 runs, K = 20"
    assert "\n".join(lines[1:]) in stdout  # the table `run` printed
    from_rrd = json.loads(ok("summary", d / "evaluation.rrd", "--json").stdout)
    assert from_rrd == json.loads((d / "summary.json").read_text())


def test_recording_series_match_the_summary(aircraft) -> None:
    d, _ = aircraft
    rec = read_recording(d / "evaluation.rrd")
    s = rec["summary"]
    assert rec["application_id"] == "fusionlog"
    assert rec["recording_id"] == recording_id_for("aircraft_identity", 2004)
    assert list(rec["steps"]) == list(range(21))
    np.testing.assert_allclose(rec["times"], np.arange(21.0))
    series = rec["series"]
    for c in CLASSES:
        for key in (f"identity/probability/{c}/BAYES", f"identity/belief/{c}/DS"):
            assert key in series
        assert f"identity/plausibility/{c}/DS" in series
        assert f"runs/0/probability/{c}/BAYES" in series
    for a in ("BAYES", "DS"):
        acc = series[f"metrics/accuracy/{a}"]
        e = s["architectures"][a]
        assert acc.mean() == pytest.approx(e["accuracy"], rel=1e-12)
        assert acc[-1] == pytest.approx(e["final"]["accuracy"], rel=1e-12)
        assert series[f"metrics/log_loss/{a}"][-1] == pytest.approx(e["final"]["log_loss"])
    assert series["metrics/conflict/DS"].mean() == pytest.approx(
        s["architectures"]["DS"]["mean_conflict"]
    )
    assert series["metrics/disagreement"].mean() == pytest.approx(s["disagreement"])
    assert set(rec["properties"]) >= {"scenario", "summary", "provenance", "identity"}


def test_compare_itself_and_a_regression(aircraft, tmp_path: Path) -> None:
    j = aircraft[0] / "summary.json"
    assert "matches" in ok("compare", j, j).stdout
    doc = json.loads(j.read_text())
    doc["architectures"]["DS"]["final"]["accuracy"] *= 0.99
    worse = tmp_path / "worse.json"
    worse.write_text(json.dumps(doc))
    res = cli("compare", worse, j)
    assert res.exit_code == 1
    assert "DS: final.accuracy" in res.stdout


# ------------------------------------------------------------------------------------------
# the numbers
# ------------------------------------------------------------------------------------------


def test_bayes_equals_a_direct_product(aircraft) -> None:
    """posterior_k(c) ∝ prior(c) prod_{t<=k} prod_s confusion_s[c, r_{s,t}], run by run."""
    d, _ = aircraft
    sc = load_scenario(AIRCRAFT).system
    sens, est = read(d / "sensors.mcap"), read(d / "estimates.mcap")
    post = est["/estimates/BAYES"]
    for m in range(5):
        p = np.array(sc.prior, dtype=float)
        for k in range(21):
            for s in sc.sensors:
                r = int(sens[f"/sensors/{s.name}"][m, k, 0])
                p = p * s.confusion[:, r]
            np.testing.assert_allclose(post[m, k], p / p.sum(), rtol=1e-12, atol=1e-15)


def _report_mass(sc, sensor, r: int) -> dict[frozenset, float]:
    subset = frozenset(c for j, c in enumerate(sc.classes) if sensor.subsets[r] >> j & 1)
    frame = frozenset(sc.classes)
    if subset == frame:
        return {frame: 1.0}
    return {subset: sensor.reliability, frame: 1.0 - sensor.reliability}


def test_ds_equals_the_dict_implementation_of_dempsters_rule(aircraft) -> None:
    """Bel, Pl and the conflicts against dempster_combine on {frozenset: mass} dicts."""
    d, _ = aircraft
    sc = load_scenario(AIRCRAFT).system
    sens, est = read(d / "sensors.mcap"), read(d / "estimates.mcap")
    ds = est["/estimates/DS"]
    frame = frozenset(sc.classes)
    for m in range(4):
        mass: dict[frozenset, float] = {frame: 1.0}
        acc = 0.0
        for k in range(21):
            reports = [
                _report_mass(sc, s, int(sens[f"/sensors/{s.name}"][m, k, 0])) for s in sc.sensors
            ]
            mass, conflict = dempster_combine(mass, *reports, frame=sc.classes)
            acc = 1 - (1 - acc) * (1 - conflict)
            want = [belief(mass, {c}) for c in sc.classes] + [
                plausibility(mass, {c}) for c in sc.classes
            ]
            np.testing.assert_allclose(ds[m, k, :6], want, atol=1e-12)
            assert ds[m, k, 6] == pytest.approx(conflict, abs=1e-12)
            assert ds[m, k, 7] == pytest.approx(acc, abs=1e-12)


def test_ds_plausibility_is_bayes_with_uniform_prior_and_contour_likelihoods(aircraft) -> None:
    """Dempster's rule multiplies contour functions: Pl_12({c}) = Pl_1({c}) Pl_2({c}) / (1-K).

    So the normalised DS plausibility equals the Bayes posterior with a uniform prior and, for
    each report R of reliability r, the likelihood pl(c | R) = 1 if c in R else 1 - r. Checked
    for every run and step.
    """
    d, _ = aircraft
    sc = load_scenario(AIRCRAFT).system
    sens, est = read(d / "sensors.mcap"), read(d / "estimates.mcap")
    lik = np.ones((300, 21, 3))
    for s in sc.sensors:
        contour = np.array(
            [[1.0 if b >> j & 1 else 1 - s.reliability for j in range(3)] for b in s.subsets]
        )
        lik *= contour[sens[f"/sensors/{s.name}"][..., 0].astype(int)]
    bayes_uniform = np.cumprod(lik, axis=1)
    bayes_uniform /= bayes_uniform.sum(-1, keepdims=True)
    pl = est["/estimates/DS"][..., 3:6]
    np.testing.assert_allclose(pl / pl.sum(-1, keepdims=True), bayes_uniform, rtol=1e-10)


RELIABLE = """\
[scenario]
name = "reliable"
steps = 8
runs = 400
seed = 11
dt = 0.5

[identity]
classes = ["Learjet", "Falcon", "Caravan"]

[[identity_sensors]]
name = "a"
reports = ["Learjet", "Falcon", "Caravan"]
confusion = [[0.94, 0.03, 0.03], [0.03, 0.94, 0.03], [0.03, 0.03, 0.94]]
reliability = 1.0

[[identity_sensors]]
name = "b"
reports = ["Learjet", "Falcon", "Caravan"]
confusion = [[0.9, 0.05, 0.05], [0.05, 0.9, 0.05], [0.05, 0.05, 0.9]]
reliability = 1.0
"""


def test_reliability_one_singletons_is_bayes_with_uniform_prior_and_01_likelihoods(
    tmp_path: Path,
) -> None:
    """With reliability 1 and singleton reports every report is a categorical mass function:
    DS is Bayes' rule with a uniform prior and 0/1 likelihoods. While every report so far
    names the same class c, Bel = Pl = indicator(c) and the conflict is 0; at the first
    disagreement the evidence is contradictory (Bayes: zero for every class; DS: total
    conflict K = 1), and DS stays undefined (NaN) from there on."""
    sc = write_toml(tmp_path / "reliable.toml", RELIABLE)
    d = tmp_path / "out"
    ok("run", sc, "--out-dir", d)
    sens, est = read(d / "sensors.mcap"), read(d / "estimates.mcap")
    r = np.stack([sens["/sensors/a"][..., 0], sens["/sensors/b"][..., 0]], axis=-1)  # (M, K1, 2)
    ds = est["/estimates/DS"]
    first = r[:, :1, :1]
    agree = np.logical_and.accumulate((r == first).all(-1), axis=1)  # all reports so far agree
    onehot = (np.arange(3) == first[..., 0, None]).astype(float)  # (M, 1, 3)
    lik01 = np.where(agree[..., None], np.broadcast_to(onehot, (400, 9, 3)), 0.0)
    defined = np.isfinite(ds[..., 0])
    assert (defined == agree).all()
    np.testing.assert_array_equal(ds[..., :3][agree], lik01[agree])  # Bel
    np.testing.assert_array_equal(ds[..., 3:6][agree], lik01[agree])  # Pl
    assert (ds[..., 6][agree] == 0).all() and (ds[..., 7][agree] == 0).all()
    broke = agree[:, :-1] & ~agree[:, 1:]  # the step where the first disagreement comes
    assert (ds[:, 1:, 6][broke] == 1).all()
    assert (ds[..., 7][~agree] == 1).all()
    assert np.isnan(ds[:, 1:, 6][~agree[:, 1:] & ~broke]).all()
    assert 0.2 < (~agree[:, -1]).mean() < 0.9  # the test really exercises total conflict
    # strict JSON: a non-finite value is null, listed in the note check_summary resolves
    s = check_summary(json.loads((d / "summary.json").read_text()), strict=True)
    assert s["architectures"]["DS"]["total_conflict"] == pytest.approx((~agree[:, -1]).mean())
    # a run in total conflict decides nothing: DS accuracy at K is at most the defined share
    assert s["architectures"]["DS"]["final"]["accuracy"] <= agree[:, -1].mean() + 1e-12
    # undefined runs are left out of the log-loss; it is infinite iff, in some run, every
    # report so far named the same wrong class: a reliability-1 sensor excluded the truth
    truth = sens["/truth"][:, :, 0]
    excluded = (agree & (first[..., 0] != truth)).any()
    assert np.isfinite(s["architectures"]["DS"]["log_loss"]) == (not excluded)
    assert s["architectures"]["BAYES"]["final"]["accuracy"] > 0.99
    if RERUN is not None:
        proc = subprocess.run(
            [RERUN, "rrd", "verify", str(d / "evaluation.rrd")],
            capture_output=True,
            text=True,
            env={**os.environ, "RERUN_ANALYTICS": "0"},
            timeout=120,
            check=False,
        )
        assert proc.returncode == 0, proc.stderr


INFORMATIVE = RELIABLE.replace("reliability = 1.0", "reliability = 0.8").replace(
    "steps = 8", "steps = 20"
)


def test_accuracy_grows_with_time_and_approaches_one(tmp_path: Path) -> None:
    sc = write_toml(tmp_path / "informative.toml", INFORMATIVE)
    d = tmp_path / "out"
    ok("run", sc, "--out-dir", d)
    series = read_recording(d / "evaluation.rrd")["series"]
    for a in ("BAYES", "DS"):
        acc = series[f"metrics/accuracy/{a}"]
        assert acc.shape == (21,)
        assert acc[0] < 0.97 and acc[-1] >= 0.995, (a, acc)
        # non-decreasing up to Monte Carlo noise (Bayes: exactly, in expectation)
        assert (acc[3:] >= acc[:-3] - 0.01).all(), (a, acc)
        ll = series[f"metrics/log_loss/{a}"]
        assert ll[-1] < ll[0] / 10, (a, ll)


# ------------------------------------------------------------------------------------------
# determinism, stages, options
# ------------------------------------------------------------------------------------------


def test_block_runs_does_not_change_the_numbers(tmp_path: Path) -> None:
    arrays, summaries = {}, {}
    small = ["--runs", "150", "--steps", "12"]
    for b in ("7", None):
        tag = b or "default"
        s, e = tmp_path / f"s{tag}.mcap", tmp_path / f"e{tag}.mcap"
        opt = ["--block-runs", b] if b else []
        ok("simulate", AIRCRAFT, "-o", s, *small, *opt)
        ok("estimate", s, "-o", e, *opt)
        j = tmp_path / f"sum{tag}.json"
        ok("evaluate", s, e, "-o", tmp_path / f"ev{tag}.rrd", "--summary", j, *opt)
        arrays[tag] = {**read(s), **read(e)}
        summaries[tag] = json.loads(j.read_text())
    assert McapFile(tmp_path / "s7.mcap").topics["/truth"] == 13 * 22  # really 22 blocks
    a, b = arrays["7"], arrays["default"]
    assert a.keys() == b.keys()
    for k in a:
        if k.startswith("/estimates/"):
            np.testing.assert_allclose(a[k], b[k], rtol=1e-12, atol=1e-13, err_msg=k)
        else:
            assert np.array_equal(a[k], b[k]), k
    assert compare_summaries(summaries["7"], summaries["default"], rtol=1e-12) == []


def test_stages_separately_force_and_arch(tmp_path: Path) -> None:
    s, e, ev = tmp_path / "s.mcap", tmp_path / "e.mcap", tmp_path / "ev.rrd"
    ok("simulate", AIRCRAFT, "-o", s, "--runs", "40", "--steps", "5", "--seed", "3")
    assert McapFile(s).metadata["fusionlog.provenance"]["seed"] == "3"
    res = ok("estimate", s, "-o", e, "--arch", "DS")
    assert "DS on 40 runs" in res.stdout
    res = ok("evaluate", s, e, "-o", ev)
    assert "DS" in res.stdout and "BAYES" not in res.stdout and "differently" not in res.stdout
    for args, target in (
        (["simulate", AIRCRAFT, "-o", s], s),
        (["estimate", s, "-o", e], e),
        (["evaluate", s, e, "-o", ev], ev),
    ):
        before = target.read_bytes()
        one_line_error(cli(*args), str(target), "exists", "--force")
        assert target.read_bytes() == before
    ok("estimate", s, "-o", e, "--force")
    assert sorted(McapFile(e).topics) == ["/estimates/BAYES", "/estimates/DS"]
    out = tmp_path / "out"
    one_line_error(cli("run", AIRCRAFT, "--out-dir", out, "--arch", "CKF"), "CKF", "BAYES")
    one_line_error(cli("estimate", s, "-o", out / "x.mcap", "--arch", "MSC"), "MSC")
    assert listing(out) == []


def test_estimate_with_a_mismatched_model(tmp_path: Path) -> None:
    s = tmp_path / "s.mcap"
    ok("simulate", AIRCRAFT, "-o", s, "--runs", "30", "--steps", "4")
    text = AIRCRAFT.read_text()
    # the fusion node believes the ESM receiver is better than it is
    model = write_toml(
        tmp_path / "model.toml",
        text.replace("[0.50, 0.20, 0.05, 0.25]", "[0.70, 0.05, 0.00, 0.25]"),
    )
    ok("estimate", s, "-o", tmp_path / "e.mcap")
    ok("estimate", s, "-o", tmp_path / "m.mcap", "--model", model, "--arch", "BAYES")
    a = read(tmp_path / "e.mcap")["/estimates/BAYES"]
    b = read(tmp_path / "m.mcap")["/estimates/BAYES"]
    assert not np.allclose(a, b)
    prov = McapFile(tmp_path / "m.mcap").metadata["fusionlog.provenance"]
    assert prov["model_source"] == str(model)
    bad = write_toml(
        tmp_path / "bad.toml",
        text.replace('["Learjet", "Falcon", "Caravan"]', '["Falcon", "Learjet", "Caravan"]', 1),
    )
    one_line_error(
        cli("estimate", s, "-o", tmp_path / "x.mcap", "--model", bad), str(bad), "classes"
    )
    # a model under which some report is impossible for every class: no posterior exists
    never = text
    for row, new_row in (
        ("[0.50, 0.20, 0.05, 0.25]", "[0.50, 0.25, 0.00, 0.25]"),
        ("[0.20, 0.50, 0.05, 0.25]", "[0.25, 0.50, 0.00, 0.25]"),
        ("[0.05, 0.05, 0.65, 0.25]", "[0.35, 0.40, 0.00, 0.25]"),
    ):
        never = never.replace(row, new_row)
    never_path = write_toml(tmp_path / "never.toml", never)
    one_line_error(
        cli("estimate", s, "-o", tmp_path / "x.mcap", "--model", never_path, "--arch", "BAYES"),
        str(s),
        "zero likelihood for every class",
    )
    state_model = ROOT / "pipeline" / "ajgl2009.toml"
    one_line_error(
        cli("estimate", s, "-o", tmp_path / "x.mcap", "--model", state_model),
        str(state_model),
        "[identity]",
    )
    assert not (tmp_path / "x.mcap").exists()


def test_missing_reports_in_a_log_are_no_evidence(tmp_path: Path) -> None:
    """A real log may lack a report at some steps (NaN): BAYES and DS skip it."""
    s = tmp_path / "s.mcap"
    ok("simulate", AIRCRAFT, "-o", s, "--runs", "20", "--steps", "6")
    src = McapFile(s)
    data = read(s)
    esm = data["/sensors/esm"].copy()
    esm[:, 2:4] = np.nan
    holes = tmp_path / "holes.mcap"
    with Outputs([holes]) as outs:
        with McapWriter(outs.open(holes)) as w:
            for name, meta in src.metadata.items():  # fusionlog.layout: the writer's own
                w.add_metadata(name, meta)
            for k in range(7):
                for t in sorted(data):
                    v = esm if t == "/sensors/esm" else data[t]
                    w.write_values(t, k, float(k), 0, v[:, k])
        outs.commit()
    ok("estimate", holes, "-o", tmp_path / "e.mcap")
    post = read(tmp_path / "e.mcap")["/estimates/BAYES"]
    sc = load_scenario(AIRCRAFT).system
    for m in range(3):
        p = np.array(sc.prior)
        for k in range(7):
            for sensor in sc.sensors:
                r = (esm if sensor.name == "esm" else data[f"/sensors/{sensor.name}"])[m, k, 0]
                if not np.isnan(r):
                    p = p * sensor.confusion[:, int(r)]
            np.testing.assert_allclose(post[m, k], p / p.sum(), rtol=1e-12)
    ok("evaluate", holes, tmp_path / "e.mcap", "-o", tmp_path / "ev.rrd")


def test_format_table_of_an_identity_summary() -> None:
    summary = {
        "kind": "identity",
        "architectures": {
            "BAYES": {"accuracy": 0.9, "log_loss": 0.2, "final": {"accuracy": 1.0}},
            "DS": {"accuracy": 0.8, "mean_conflict": 0.3},
        },
        "disagreement": 0.05,
        "final_disagreement": 0.0,
    }
    lines = format_table(summary).splitlines()
    assert lines[0].split() == [
        "architecture",
        "accuracy",
        "accuracy",
        "at",
        "K",
        "log-loss",
        "log-loss",
        "at",
        "K",
        "P(true)",
        "Bel(true)",
        "Pl(true)",
        "conflict",
    ]
    assert lines[2].split()[:5] == ["BAYES", "90.0", "%", "100.0", "%"]
    assert lines[3].split()[-1] == "0.3000"
    assert lines[4] == "BAYES and DS decide differently: 5.0 % of runs and steps, 0.0 % at K"
    # just the architectures mapping is recognised too
    assert format_table(summary["architectures"]).splitlines()[0] == lines[0]


# ------------------------------------------------------------------------------------------
# validation: exit 2, one line naming file and key, nothing written
# ------------------------------------------------------------------------------------------

BASE = """\
[scenario]
name = "tiny"
steps = 3
runs = 10
seed = 1
dt = 1.0

[identity]
classes = ["Learjet", "Falcon", "Caravan"]
prior = [0.5, 0.4, 0.1]
sets = { fast = ["Learjet", "Falcon"] }

[[identity_sensors]]
name = "a"
reports = ["Learjet", "Falcon", "Caravan", "fast", "unknown"]
confusion = [
    [0.5, 0.1, 0.0, 0.3, 0.1],
    [0.1, 0.5, 0.0, 0.3, 0.1],
    [0.0, 0.1, 0.7, 0.0, 0.2],
]
reliability = 0.7

[estimate]
architectures = ["BAYES", "DS"]
"""


def test_base_identity_scenario_is_valid(tmp_path: Path) -> None:
    ok("simulate", write_toml(tmp_path / "ok.toml", BASE), "-o", tmp_path / "s.mcap")


@pytest.mark.parametrize(
    "old, new, fragments",
    [
        ("[0.0, 0.1, 0.7, 0.0, 0.2]", "[0.0, 0.1, 0.7, 0.0, 0.1]", ["confusion[2]", "sums to 0.9"]),
        ('"Caravan", "fast"', '"Carvan", "fast"', ["reports[2]", "'Carvan'", "'Caravan'"]),
        ("[0.5, 0.1, 0.0, 0.3, 0.1],", "[0.5, 0.1, 0.0, 0.4],", ["confusion", "different lengths"]),
        (
            "    [0.0, 0.1, 0.7, 0.0, 0.2],\n",
            "",
            ["identity_sensors[0].confusion", "shape 2x5", "expected 3x5"],
        ),
        ("[0.5, 0.1, 0.0, 0.3, 0.1]", "[0.7, -0.1, 0.0, 0.3, 0.1]", ["confusion[0][1]", ">= 0"]),
        ("prior = [0.5, 0.4, 0.1]", "prior = [0.5, 0.4, 0.2]", ["identity.prior", "sums to"]),
        ("prior = [0.5, 0.4, 0.1]", "prior = [0.5, 0.5]", ["identity.prior", "length 2"]),
        ("reliability = 0.7", "reliability = 0.0", ["reliability", "(0, 1]"]),
        ("reliability = 0.7", "reliability = 1.5", ["reliability", "(0, 1]"]),
        ('fast = ["Learjet", "Falcon"]', 'fast = ["Learjet", "Concorde"]', ["sets.fast[1]"]),
        ('sets = { fast = ["Learjet"', 'sets = { Falcon = ["Learjet"', ["already a class"]),
        ('sets = { fast = ["Learjet"', 'sets = { unknown = ["Learjet"', ["implicit"]),
        ('"Falcon", "Caravan"]\nprior', '"Falcon", "Falcon"]\nprior', ["classes[2]", "duplicate"]),
        ('"Falcon", "Caravan"]\nprior', '"Falcon", "unknown"]\nprior', ["classes[2]", "reserved"]),
        ("reliability = 0.7", 'reliability = 0.7\ncolour = "red"', ["unknown key 'colour'"]),
        ('["BAYES", "DS"]', '["BAYES", "CKF"]', ["architectures[1]", "'CKF'", "BAYES, DS"]),
        ("[[identity_sensors]]", "[[sensors]]", ["unknown section 'sensors'", "identity_sensors"]),
        ("[estimate]", "[evaluate]\nconfidence = 0.9\n[estimate]", ["unknown key 'confidence'"]),
        ('"fast", "unknown"]', '"fast", "fast"]', ["reports[4]", "duplicate report"]),
        ("runs = 10", "runs = 0", ["scenario.runs", ">= 1"]),
        ("dt = 1.0", "", ["scenario.dt", "missing"]),
        ('classes = ["Learjet", "Falcon", "Caravan"]', 'classes = ["Learjet"]', ["two classes"]),
    ],
    ids=[
        "row-sum",
        "unknown-report",
        "ragged",
        "rows",
        "negative",
        "prior-sum",
        "prior-length",
        "reliability-0",
        "reliability-big",
        "set-member",
        "set-is-class",
        "set-unknown",
        "duplicate-class",
        "class-unknown",
        "unknown-key",
        "state-arch",
        "state-sensors",
        "evaluate-key",
        "duplicate-report",
        "zero-runs",
        "no-dt",
        "one-class",
    ],
)
def test_invalid_identity_scenario(tmp_path: Path, old: str, new: str, fragments) -> None:
    assert old in BASE
    sc = write_toml(tmp_path / "bad.toml", BASE.replace(old, new, 1))
    out = tmp_path / "out"
    out.mkdir()
    for cmd in (["simulate", sc, "-o", out / "s.mcap"], ["run", sc, "--out-dir", out]):
        one_line_error(cli(*cmd), str(sc), *fragments)
        assert listing(out) == []


def test_invalid_override(tmp_path: Path) -> None:
    sc = write_toml(tmp_path / "ok.toml", BASE)
    one_line_error(cli("simulate", sc, "-o", tmp_path / "s.mcap", "--runs", "0"), "--runs", ">= 1")
    assert not (tmp_path / "s.mcap").exists()
