"""The evaluation stage on the paper's example: the recording read back against summary.json,
and the structural results of Tables I and II."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from fusionlog.io.rrd import entity_path, read_recording
from fusionlog.scenario import load_scenario
from fusionlog.stages.estimate import run_estimate
from fusionlog.stages.evaluate import run_evaluate
from fusionlog.stages.simulate import run_simulate

PAPER = Path(__file__).parents[1] / "pipeline" / "ajgl2009.toml"
CONSISTENT = ("CKF", "HKF", "MSC-GMF", "SKF", "FBS")


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory):
    """The paper's example at its full size, M = 10^4 runs, K = 20, seed 2009."""
    d = tmp_path_factory.mktemp("paper")
    sc = load_scenario(PAPER)
    run_simulate(sc, d / "sensors.mcap")
    run_estimate(d / "sensors.mcap", d / "estimates.mcap")
    res = run_evaluate(
        d / "sensors.mcap", d / "estimates.mcap", d / "evaluation.rrd", summary_path=d / "s.json"
    )
    return d, res.summary


def test_recording_series_match_summary(paper_run):
    d, summary = paper_run
    rec = read_recording(d / "evaluation.rrd")
    assert rec["summary"] == json.loads((d / "s.json").read_text())
    states = summary["state_names"]
    np.testing.assert_array_equal(rec["steps"], np.arange(summary["steps"] + 1))
    for arch, s in summary["architectures"].items():
        mse = np.stack([rec["series"][entity_path("metrics", "mse", st, arch)] for st in states])
        assert math.isclose(mse.mean(), s["mse"], rel_tol=1e-12)
        np.testing.assert_allclose(mse.mean(axis=1), s["mse_per_state"], rtol=1e-12)
        nees = rec["series"][entity_path("metrics", "nees", arch)]
        assert math.isclose(nees.mean(), s["anees"], rel_tol=1e-12)
        dm = rec["series"][entity_path("metrics", "dm", arch)]
        assert math.isclose(dm.mean(), s["dm"], rel_tol=1e-12)
        trace = rec["series"][entity_path("metrics", "trace", arch)]
        assert math.isclose(trace.mean(), s["mean_trace"], rel_tol=1e-12)
        lo = rec["series"][entity_path("metrics", "nees", "bounds", "lower")]
        hi = rec["series"][entity_path("metrics", "nees", "bounds", "upper")]
        inside = np.mean((nees >= lo) & (nees <= hi))
        assert math.isclose(inside, s["nees_fraction_inside"], rel_tol=1e-12)
        if arch != "CKF":
            diff = rec["series"][entity_path("metrics", "mse_minus_ckf", states[0], arch)]
            ckf = rec["series"][entity_path("metrics", "mse", states[0], "CKF")]
            np.testing.assert_allclose(diff, mse[0] - ckf, atol=1e-12)


def test_paper_tables_structure(paper_run):
    _, summary = paper_run
    a = summary["architectures"]
    assert a["CKF"]["mse"] == pytest.approx(a["HKF"]["mse"], rel=1e-9)
    assert a["CKF"]["dm"] == pytest.approx(a["HKF"]["dm"], rel=1e-9)
    assert a["MSC"]["mse"] == pytest.approx(a["MSC-GMF"]["mse"], rel=1e-9)
    # MSC: over-confident, NEES outside the band on most steps, DM far above sqrt(pi/2).
    assert a["MSC"]["nees_fraction_inside"] < 0.1
    assert a["MSC"]["dm"] > 1.3 * math.sqrt(math.pi / 2)
    for arch in CONSISTENT:
        assert a[arch]["nees_fraction_inside"] >= 0.9, arch
        assert a[arch]["expected"]["anees"] == pytest.approx(2.0, rel=1e-9)


def test_monte_carlo_within_four_standard_errors(paper_run):
    _, summary = paper_run
    for arch, s in summary["architectures"].items():
        for key in ("mse", "anees", "dm"):
            assert abs(s[key] - s["expected"][key]) < 4 * s["stderr"][key], (arch, key)


GUSTAFSSON = Path(__file__).parents[1] / "pipeline"


@pytest.mark.parametrize("name", ["gustafsson_triangulation", "gustafsson_correlated"])
def test_gustafsson_scenarios(tmp_path, name):
    """The slides' example: WLS variance 0.018 per axis against 0.05 for the average; with
    correlated errors MSC-GMF (Bar-Shalom-Campo) is optimal, Millman over-confident, CI safe."""
    sc = load_scenario(GUSTAFSSON / f"{name}.toml", runs=4000)
    run_simulate(sc, tmp_path / "s.mcap")
    run_estimate(tmp_path / "s.mcap", tmp_path / "e.mcap")
    res = run_evaluate(tmp_path / "s.mcap", tmp_path / "e.mcap", tmp_path / "ev.rrd")
    a = res.summary["architectures"]
    if name == "gustafsson_triangulation":
        for arch in ("CKF", "MSC", "MSC-GMF"):
            np.testing.assert_allclose(a[arch]["expected"]["mse"], 0.018, rtol=1e-12)
            assert a[arch]["expected"]["anees"] == pytest.approx(2.0, rel=1e-12)
        np.testing.assert_allclose(a["AVG"]["expected"]["mse"], 0.05, rtol=1e-12)
        np.testing.assert_allclose(a["SKF:s1"]["expected"]["mse"], 0.1, rtol=1e-12)
    else:
        assert a["MSC-GMF"]["expected"]["mse"] == pytest.approx(a["CKF"]["expected"]["mse"])
        assert a["MSC"]["expected"]["anees"] > 2.5  # ignores the correlation
        assert a["CI"]["expected"]["anees"] < 2.0  # safe without knowing it
    for arch, s in a.items():
        assert abs(s["mse"] - s["expected"]["mse"]) < 4 * s["stderr"]["mse"], arch
    # The state-plane view (points and line strips, not scalars): read the chunk store.
    paths = {
        str(ch.entity_path)
        for ch in RrdReader(str(tmp_path / "ev.rrd")).store().stream().to_chunks()
    }
    assert "/plane/truth" in paths
    assert "/" + entity_path("plane", "ellipses", "input s1") in paths
    assert "/plane/estimates/AVG" in paths
    rerun = Path(sys.executable).parent / "rerun"
    verify = subprocess.run(
        [str(rerun), "rrd", "verify", str(tmp_path / "ev.rrd")],
        capture_output=True,
        env={**os.environ, "RERUN_ANALYTICS": "0"},
    )
    assert verify.returncode == 0, verify.stderr


def _tampered(src: Path, dst: Path, change) -> None:
    """A copy of an estimates file with `change(topic, block)` applied to each decoded message,
    written with the plain mcap writer (as another tool would)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer
    from mcap_protobuf.decoder import DecoderFactory

    with open(src, "rb") as f, open(dst, "wb") as g:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        info = r.get_summary()
        w = Writer(g)
        w.start()
        schemas = {
            i: w.register_schema(x.name, x.encoding, x.data) for i, x in info.schemas.items()
        }
        channels = {
            i: w.register_channel(c.topic, c.message_encoding, schemas[c.schema_id])
            for i, c in info.channels.items()
        }
        for m in r.iter_metadata():
            w.add_metadata(m.name, m.metadata)
        for _, ch, msg, block in r.iter_decoded_messages(log_time_order=False):
            change(ch.topic, block)
            w.add_message(channels[ch.id], msg.log_time, block.SerializeToString(), msg.log_time)
        w.finish()


def test_estimates_that_are_not_what_fusionlog_writes_are_refused(tmp_path: Path) -> None:
    """Estimates files (damaged, or from another tool) with the sensors file's sha256: a CKF
    covariance of all -1 at step 3 gave a negative NEES and a DM of 0 (exit 0); a step 4 at
    100 s (4 s in the sensors file) failed in the exact analysis, naming no file. Each is now
    one line naming the file, and no output."""
    from cli_helpers import cli, ok, one_line_error

    s, e, bad = tmp_path / "s.mcap", tmp_path / "e.mcap", tmp_path / "bad.mcap"
    ok("simulate", PAPER, "-o", s, "--runs", "20", "--steps", "6")
    ok("estimate", s, "-o", e, "--arch", "CKF", "--arch", "MSC")

    def negative(topic, block) -> None:
        if topic == "/estimates/CKF" and block.step == 3:
            block.covariance[:] = [-1.0] * len(block.covariance)

    def late(topic, block) -> None:
        if block.step == 4:
            block.time = 100.0

    for change, line in [
        (negative, f"{bad}: /estimates/CKF: step 3: a covariance with a negative variance"),
        (late, f"{bad}: step 4 is at 100.0 s, in {s} at 4.0 s"),
    ]:
        _tampered(e, bad, change)
        one_line_error(cli("evaluate", s, bad, "-o", tmp_path / "ev.rrd", "--force"), line)
        assert not (tmp_path / "ev.rrd").exists()
