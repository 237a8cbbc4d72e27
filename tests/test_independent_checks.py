"""Checks of numbers the pipeline reports against computations made here from their definitions:
the NIS chi-square band (dof = the summed measurement dimensions), `mean_trace` (the mean over
instants of tr P read back from estimates.mcap, with and without truth), and the no-clobber
commit against a real competitor that writes the target just after the commit-time check.

Each one catches a realistic bug that the rest of the suite let through (a mutation check,
issue "make test fails on a fresh machine"): a band with count x n dof, `mean_trace` summed over
instants, a commit by plain rename.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy import stats

from fusionlog.core.model import Prior, Sensor, System
from fusionlog.io import atomic
from fusionlog.stages.consistency import NisAccumulator

ROOT = Path(__file__).resolve().parents[1]
AJGL = ROOT / "pipeline" / "ajgl2009.toml"
REPLAY = ROOT / "pipeline" / "replay_robot.toml"


# ------------------------------------------------------------------ NIS band: summed dof


def test_nis_band_has_the_summed_measurement_dof():
    """Two sensors of sizes 1 and 2 on a 3-state system, readings missing at random: at each
    instant the band of the run-averaged NIS is chi2.ppf(q, D) / N, where D sums the sizes of
    the readings present over the N runs that have any (not N times the state dimension)."""
    rng = np.random.default_rng(4)
    n, M, K1 = 3, 40, 6
    sensors = (
        Sensor("a", rng.standard_normal((1, n)), np.array([[0.5]])),
        Sensor("b", rng.standard_normal((2, n)), np.diag([0.3, 0.7])),
    )
    prior = Prior(np.zeros(n), np.eye(n))  # a prediction at k = 0 too
    system = System(F=np.eye(n), Q=0.1 * np.eye(n), sensors=sensors, prior=prior)
    z = rng.standard_normal((M, K1, 3))
    z[rng.random(z.shape) < 0.3] = np.nan
    z[:, 2] = np.nan  # an instant without any reading
    mean = rng.standard_normal((M, K1, n))
    cov = np.broadcast_to(np.eye(n), (K1, n, n)).copy()
    acc = NisAccumulator(system, ["CKF", "MSC"], K1)
    acc.add(z, {"CKF": (mean, cov), "MSC": (mean, cov)})
    conf = 0.95
    series = acc.series(conf)
    present = np.isfinite(z)
    # every architecture per sensor (issue 22: the CKF's centralised innovation split by sensor)
    parts = {"CKF": {"a": [0], "b": [1, 2]}, "MSC": {"a": [0], "b": [1, 2]}}
    for arch, by_part in parts.items():
        for part, rows in by_part.items():
            dims = present[:, :, rows].sum(axis=2)  # (M, K1): the reading's size per run
            runs = (dims > 0).sum(axis=0)
            dof = dims.sum(axis=0)
            avg, lo, hi = series[arch][part]
            have = runs > 0
            assert np.isnan(avg[~have]).all() and np.isnan(lo[~have]).all()
            assert not have[2] and have.sum() == K1 - 1
            np.testing.assert_allclose(lo[have], stats.chi2.ppf(0.025, dof[have]) / runs[have])
            np.testing.assert_allclose(hi[have], stats.chi2.ppf(0.975, dof[have]) / runs[have])
            s = acc.summary(conf)[arch]
            entry = s if part == "all" else s[part]
            assert entry["dof"] == pytest.approx(dof.sum() / runs.sum(), rel=1e-12)


# ---------------------------------------------------------------- mean_trace from the file


def _estimate_traces(path: Path) -> dict[str, np.ndarray]:
    """{ARCH: (K+1,) run-averaged tr P} from an estimates file, read with the plain mcap
    reader and its protobuf decoder (DESIGN.md: no fusionlog needed)."""
    sums: dict[str, dict[int, list[float]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, msg in reader.iter_decoded_messages():
            arch = channel.topic.removeprefix("/estimates/")
            n = msg.dim
            cov = np.asarray(msg.covariance, dtype=float)
            if cov.size == n * n:  # the same for every run of the message
                tr, count = float(np.trace(cov.reshape(n, n))) * msg.runs, msg.runs
            else:
                tr = float(np.trace(cov.reshape(msg.runs, n, n), axis1=1, axis2=2).sum())
                count = msg.runs
            acc = sums.setdefault(arch, {}).setdefault(msg.step, [0.0, 0])
            acc[0] += tr
            acc[1] += count
    return {
        a: np.array([s / c for _, (s, c) in sorted(by_step.items())]) for a, by_step in sums.items()
    }


def _mean_traces_agree(out: Path) -> None:
    summary = json.loads((out / "summary.json").read_text())["architectures"]
    traces = _estimate_traces(out / "estimates.mcap")
    assert set(traces) == set(summary)
    for arch, tr in traces.items():
        want = float(np.mean(tr[np.isfinite(tr)]))
        assert summary[arch]["mean_trace"] == pytest.approx(want, rel=1e-9), arch


def test_mean_trace_is_the_mean_of_the_traces_with_truth(tmp_path):
    ok("run", AJGL, "--runs", "30", "--steps", "8", "--out-dir", tmp_path / "o")
    _mean_traces_agree(tmp_path / "o")


def _without_truth(tmp_path: Path) -> Path:
    """pipeline/replay_robot.toml without its [truth] table, its sources made absolute."""
    text = REPLAY.read_text()
    text = re.sub(r"\n\[truth\]\n(?:[^\[\n][^\n]*\n)*", "\n", text)
    assert "[truth]" not in text
    text = text.replace('source = "data/', f'source = "{REPLAY.parent / "data"}/')
    p = tmp_path / "replay_no_truth.toml"
    p.write_text(text)
    return p


def test_mean_trace_is_the_mean_of_the_traces_without_truth(tmp_path):
    """A truth-free replay (one run, a covariance shared by the run): the mean over instants,
    not their sum."""
    out = tmp_path / "o"
    ok("run", _without_truth(tmp_path), "--arch", "CKF", "--arch", "MSC", "--out-dir", out)
    _mean_traces_agree(out)


# ------------------------------------------------------ no-clobber against a real competitor

COMPETITOR = b"a competitor's bytes\n"


def test_commit_refuses_a_target_written_after_its_last_check(tmp_path, monkeypatch):
    """Another process writes the target between the commit-time check and the commit: the
    command refuses (exit 2, one line), the competitor's bytes stay, no temporary is left."""
    target = tmp_path / "s.mcap"
    real_check = atomic.check_target
    raced = []

    def check_then_compete(path, **kw):
        real_check(path, **kw)
        ours = [p for p in tmp_path.iterdir() if p.name.startswith(".s.mcap.")]
        if Path(path) == target and ours and not raced:
            # Our temporary exists: this is the commit-time check. A separate process writes
            # the target now, before the commit.
            code = f"open({str(target)!r}, 'xb').write({COMPETITOR!r})"
            subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
            raced.append(True)

    monkeypatch.setattr(atomic, "check_target", check_then_compete)
    res = cli("simulate", AJGL, "-o", target, "--runs", "5", "--steps", "3")
    assert raced, "the commit-time check was never reached"
    one_line_error(res, str(target), "exists")
    assert target.read_bytes() == COMPETITOR
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.mcap"]
