"""Issue 32, `fusionlog identify`: noise from the data by maximum likelihood.

References written here, never the code's own output: the likelihood against the dense normal
density of the stacked readings (the state-space model written as one Gaussian vector, scipy's
`multivariate_normal`) and, for a one-dimensional model, statsmodels' state-space likelihood;
the estimates against the values simulated (within 4 standard errors) and the standard errors
against the spread of the estimates over independent seeds; the cost's exact MSE and ANEES
against a Monte Carlo run with the identified values as the truth (within 4 SE).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import textwrap
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error
from scipy.stats import multivariate_normal

import fusionlog as fl
from fusionlog.core.likelihood import Noise, loglik

TWO_SENSORS = """
[scenario]
name = "two"
description = "a constant-velocity target, two position sensors of different noise"
steps = {steps}
runs = {runs}
seed = 7
dt = 1.0
state_names = ["position", "velocity"]

[model]
kind = "constant-velocity"
n0 = {n0}

[prior]
mean = [0.0, 1.0]
cov = [[4.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "s1"
H = [[1.0, 0.0]]
R = {r1}
{s1_extra}

[[sensors]]
name = "s2"
H = [[1.0, 0.0]]
R = {r2}
{s2_extra}

{extra}

[estimate]
architectures = ["CKF", "MSC", "SKF"]
"""


def scenario(tmp_path: Path, name: str = "two.toml", **kw) -> Path:
    values = dict(steps=30, runs=200, n0=0.3, r1=0.5, r2=2.0, s1_extra="", s2_extra="", extra="")
    values.update(kw)
    p = tmp_path / name
    p.write_text(textwrap.dedent(TWO_SENSORS.format(**values)))
    return p


# -- the likelihood against independent computations -------------------------------------------


def dense_loglik(system, times, z, truth_rows=None) -> float:
    """log N(z; H mu, H Sigma H' + R) of each run's present readings, the states x_0..x_K
    stacked into one Gaussian vector: mean F_k..F_1 m0, covariances from x_k = F_k x_{k-1}
    + w_k (cov(x_i, x_j) = F_j..F_{i+1} var(x_i) for j > i), summed over the runs. With
    `truth_rows`, z's last columns are those states themselves (rows of the identity, no
    noise): the joint density of readings and truth."""
    s = system.on_times(times)
    if truth_rows is not None:
        s = _WithTruth(s, truth_rows)
    n, K1 = s.n, len(times)
    means, var = [s.prior.mean], [s.prior.cov]
    for k in range(1, K1):
        F = s.F_at(k)
        means.append(F @ means[-1])
        var.append(F @ var[-1] @ F.T + s.GQG_at(k))
    cov = np.zeros((K1 * n, K1 * n))
    for i in range(K1):
        block = var[i]
        for j in range(i, K1):
            if j > i:
                block = s.F_at(j) @ block
            cov[j * n : (j + 1) * n, i * n : (i + 1) * n] = block
            cov[i * n : (i + 1) * n, j * n : (j + 1) * n] = block.T
    H = np.kron(np.eye(K1), s.H)
    R = np.zeros((K1 * s.m, K1 * s.m))
    for k in range(K1):
        R[k * s.m : (k + 1) * s.m, k * s.m : (k + 1) * s.m] = s.R_at(k)
    zm, zc = H @ np.concatenate(means), H @ cov @ H.T + R
    total = 0.0
    for run in z:
        v = run.ravel()
        keep = ~np.isnan(v)
        total += multivariate_normal(zm[keep], zc[np.ix_(keep, keep)]).logpdf(v[keep])
    return total


def test_loglik_equals_the_dense_normal_density_of_the_stacked_readings(tmp_path):
    """Correlated sensors, a sensor at half rate with an offset (irregular instants: a
    transition per interval), dropouts: the prediction-error decomposition equals the
    density of all readings at once."""
    extra = '[[correlations]]\nsensors = ["s1", "s2"]\ncov = [[0.3]]'
    p = scenario(tmp_path, steps=7, runs=4, s2_extra="period = 2.0\noffset = 0.5\ndropout = 0.3",
                 extra=extra, s1_extra="dropout = 0.2")  # fmt: skip
    sc = fl.load(p)
    sim = fl.simulate(sc)
    s = sim.on_instants(sc.system)
    z = sim.stacked(s)
    assert np.isnan(z).any() and len(sim.times) > 8  # lost readings, irregular instants
    K = len(sim.times) - 1
    Qs = np.array([s.GQG_at(k) for k in range(1, K + 1)])
    noise = Noise(s.prior.cov[None], Qs[None], np.arange(K), s.R[None, None], np.zeros(K + 1, int))
    want = dense_loglik(sc.system, sim.times, z)
    assert loglik(s, z, noise)[0] == pytest.approx(want, rel=1e-10, abs=1e-9)


class _WithTruth:
    """A system whose readings are followed by the states `rows` themselves (no noise)."""

    def __init__(self, system, rows):
        self._s = system
        self.H = np.vstack([system.H, np.eye(system.n)[rows]])
        self.m = self.H.shape[0]

    def R_at(self, k):
        R = np.zeros((self.m, self.m))
        R[: self._s.m, : self._s.m] = self._s.R_at(k)
        return R

    def __getattr__(self, name):
        return getattr(self._s, name)


def _noise_of(systems, K):
    """The candidates' `Noise`, each model on its instants: its Q per interval and R per
    instant (no sharing assumed)."""
    P0 = np.array([s.prior.cov for s in systems])
    Q = np.array([[s.GQG_at(k) for k in range(1, K + 1)] for s in systems])
    R = np.array([[s.R_at(k) for k in range(K + 1)] for s in systems])
    return Noise(P0, Q, np.arange(K), R, np.arange(K + 1))


def test_the_one_run_loglik_of_several_candidates_equals_the_dense_density(tmp_path):
    """One recorded run (the one-run path of a replayed log): a sensor at half rate with an
    offset (irregular instants), dropouts, correlated sensors, three candidate noise models
    at once; alone and with a truth of the position only, lost at some instants (the joint
    density of readings and truth)."""
    extra = '[[correlations]]\nsensors = ["s1", "s2"]\ncov = [[{c}]]'
    kw = dict(steps=12, runs=1, s2_extra="period = 2.0\noffset = 0.5\ndropout = 0.3",
              s1_extra="dropout = 0.2")  # fmt: skip
    sim = fl.simulate(fl.load(scenario(tmp_path, extra=extra.format(c=0.3), **kw)), seed=5)
    z = sim.stacked(sim.scenario.system)
    assert np.isnan(z).any() and len(sim.times) > 13 and z.shape[0] == 1
    cands = [(0.5, 2.0, 0.3, 0.3), (1.7, 0.4, 0.05, -0.2), (0.2, 3.0, 1.2, 0.0)]
    models = [fl.load(scenario(tmp_path, f"c{i}.toml", r1=a, r2=b, n0=q, extra=extra.format(c=c),
                               **kw)).system for i, (a, b, q, c) in enumerate(cands)]  # fmt: skip
    systems = [sim.on_instants(m) for m in models]
    K = len(sim.times) - 1
    got = loglik(systems[0], z, _noise_of(systems, K))
    want = [dense_loglik(m, sim.times, z) for m in models]
    assert got == pytest.approx(want, rel=1e-10)
    truth = sim.truth[..., :1].copy()
    truth[0, [0, 3, 4, 9]] = np.nan
    rows = np.array([0])
    got = loglik(systems[0], z, _noise_of(systems, K), truth, rows)
    both = np.concatenate([z, truth], axis=-1)
    want = [dense_loglik(m, sim.times, both, rows) for m in models]
    assert got == pytest.approx(want, rel=1e-10)


def test_identified_loglik_is_the_dense_density_at_the_identified_values(tmp_path):
    """fl.identify's log-likelihood at its optimum is the dense density with the values it
    reports (the tuned scenario's model), with and without the truth (then the joint
    density of readings and states)."""
    p = scenario(tmp_path, steps=10, runs=40)
    sc = fl.load(p)
    sim = fl.simulate(sc)
    res = fl.identify(sc, sim, ["sensors.s1.R", "model.n0"], cost=False)
    tuned = res.scenario.system
    assert tuned.sensors[0].R[0, 0] == res.values["sensors.s1.R"]
    want = dense_loglik(tuned, sim.times, sim.stacked(tuned))
    assert res.loglik == pytest.approx(want, rel=1e-10)
    # with the truth: p(x, z) = p(x) p(z | x), x_0 from the prior, the increments from Q
    res = fl.identify(sc, sim, ["sensors.s1.R", "model.n0"], with_truth=True, cost=False)
    s = res.scenario.system
    want = 0.0
    for x, z in zip(sim.truth, sim.stacked(s), strict=True):
        want += multivariate_normal(s.prior.mean, s.prior.cov).logpdf(x[0])
        for k in range(1, len(x)):
            want += multivariate_normal(s.F @ x[k - 1], s.GQG).logpdf(x[k])
        for k in range(len(x)):
            want += multivariate_normal(s.H @ x[k], s.R).logpdf(z[k])
    assert res.loglik == pytest.approx(want, rel=1e-9)


def test_loglik_equals_statsmodels_for_a_one_dimensional_model(tmp_path):
    """A random walk seen by one sensor, with gaps: statsmodels' MLEModel (known initial
    state) gives the same log-likelihood."""
    sm = pytest.importorskip("statsmodels.tsa.statespace.mlemodel")
    p = tmp_path / "walk.toml"
    p.write_text(
        textwrap.dedent("""
        [scenario]
        name = "walk"
        description = "a random walk"
        steps = 60
        runs = 1
        seed = 3
        dt = 1.0
        state_names = ["x"]
        [model]
        F = [[1.0]]
        Q = [[0.2]]
        [prior]
        mean = [1.0]
        cov = [[2.0]]
        [[sensors]]
        name = "s"
        H = [[1.0]]
        R = 0.7
        dropout = 0.2
    """)
    )
    sc = fl.load(p)
    sim = fl.simulate(sc)
    y = sim.measurements["s"][0, :, 0]
    assert np.isnan(y).any()
    mod = sm.MLEModel(y, k_states=1)
    mod["design"] = np.ones((1, 1))
    mod["transition"] = np.ones((1, 1))
    mod["selection"] = np.ones((1, 1))
    mod["state_cov"] = np.array([[0.2]])
    mod["obs_cov"] = np.array([[0.7]])
    mod.initialize_known(np.array([1.0]), np.array([[2.0]]))
    s = sc.system
    K = len(y) - 1
    noise = Noise(s.prior.cov[None], s.GQG[None, None], np.zeros(K, int), s.R[None, None],
                  np.zeros(K + 1, int))  # fmt: skip
    assert loglik(s, sim.stacked(s), noise)[0] == pytest.approx(mod.ssm.loglike(), rel=1e-10)


# -- the estimates and their standard errors ---------------------------------------------------


def test_a_large_simulation_recovers_r_and_n0_within_4_standard_errors(tmp_path):
    p = scenario(tmp_path, steps=30, runs=400, n0=0.3, r1=0.5, r2=2.0)
    sc = fl.load(p)
    res = fl.identify(sc, fl.simulate(sc), ["sensors.s1.R", "sensors.s2.R", "model.n0"],
                      cost=False)  # fmt: skip
    for key, true in (("sensors.s1.R", 0.5), ("sensors.s2.R", 2.0), ("model.n0", 0.3)):
        v, se = res.values[key], res.stderr[key]
        assert 0 < se < 0.1 * true, (key, se)  # informative: 12,400 readings
        assert abs(v - true) < 4 * se, (key, v, se)


def test_a_matrix_is_estimated_whole_with_the_stderr_of_each_entry(tmp_path):
    """A 2-D sensor's full R (correlated components) through its Cholesky factor: every
    entry within 4 standard errors, the estimate symmetric positive definite."""
    p = tmp_path / "xy.toml"
    p.write_text(
        textwrap.dedent("""
        [scenario]
        name = "xy"
        description = "a 2-D constant-velocity target, one position sensor with correlated noise"
        steps = 25
        runs = 300
        seed = 11
        dt = 1.0
        state_names = ["x", "vx", "y", "vy"]
        [model]
        kind = "constant-velocity"
        axes = 2
        n0 = 0.2
        [prior]
        mean = [0.0, 1.0, 0.0, -1.0]
        cov = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
               [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
        [[sensors]]
        name = "gps"
        H = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
        R = [[1.0, 0.6], [0.6, 2.0]]
    """)
    )
    sc = fl.load(p)
    res = fl.identify(sc, fl.simulate(sc), ["sensors.gps.R"], cost=False)
    v, se = np.array(res.values["sensors.gps.R"]), np.array(res.stderr["sensors.gps.R"])
    assert np.allclose(v, v.T) and np.linalg.eigvalsh(v)[0] > 0
    assert se.shape == (2, 2) and (se > 0).all() and se[0, 1] == pytest.approx(se[1, 0])
    assert (np.abs(v - np.array([[1.0, 0.6], [0.6, 2.0]])) < 4 * se).all(), (v, se)


def test_the_standard_errors_match_the_spread_over_20_seeds(tmp_path):
    """The observed information's standard error against the standard deviation of the
    estimates over 20 independent simulations: their ratio within the sampling band of a
    standard deviation from 20 values (relative SE 1/sqrt(38) = 0.16; 3 of them)."""
    p = scenario(tmp_path, steps=20, runs=40, n0=0.3, r1=0.5)
    sc = fl.load(p)
    est, ses = [], []
    for seed in range(20):
        res = fl.identify(sc, fl.simulate(sc, seed=100 + seed), ["sensors.s1.R", "model.n0"],
                          cost=False)  # fmt: skip
        est.append([res.values["sensors.s1.R"], res.values["model.n0"]])
        ses.append([res.stderr["sensors.s1.R"], res.stderr["model.n0"]])
    spread = np.std(est, axis=0, ddof=1)
    ratio = spread / np.mean(ses, axis=0)
    assert ((ratio > 1 - 3 * 0.16) & (ratio < 1 + 3 * 0.16)).all(), ratio
    # and the estimates are unbiased to within their spread
    assert (np.abs(np.mean(est, axis=0) - [0.5, 0.3]) < 4 * spread / np.sqrt(20)).all()


# -- the cost -----------------------------------------------------------------------------------


def test_the_cost_is_the_monte_carlo_mse_with_the_identified_values_as_the_truth(tmp_path):
    """mse_given / anees_given: the filters built on the file's values run on data simulated
    with the identified ones (10^4 runs), within 4 SE; mse_tuned / anees_tuned likewise with
    the identified values on both sides. The file's R of s1 is 8x too large."""
    p = scenario(tmp_path, steps=15, runs=300, r1=4.0, r2=2.0)
    sc = fl.load(p)
    data = fl.simulate(fl.load(scenario(tmp_path, "truth.toml", steps=15, runs=300, r1=0.5)))
    res = fl.identify(sc, data, ["sensors.s1.R"])
    tuned = res.scenario
    sim = fl.simulate(tuned, runs=10_000, seed=5)
    for model, which in ((sc, "given"), (tuned, "tuned")):
        est = fl.estimate(model, sim, ["CKF", "MSC", "SKF"])
        for a, e in est.items():
            err = e.mean - sim.truth  # (M, K+1, n)
            sq = (err**2).mean(axis=2).mean(axis=1)  # per run: eq. 45's average
            P = np.broadcast_to(e.cov, err.shape + (err.shape[-1],))
            nees = np.einsum("mki,mkij,mkj->mk", err, np.linalg.inv(P), err).mean(axis=1)
            c = res.cost[a]
            for got, mc in ((c[f"mse_{which}"], sq), (c[f"anees_{which}"], nees)):
                se = mc.std(ddof=1) / np.sqrt(len(mc))
                assert abs(got - mc.mean()) < 4 * se, (a, which, got, mc.mean(), se)
    assert res.cost["CKF"]["mse_given"] > res.cost["CKF"]["mse_tuned"]
    assert res.cost["CKF"]["anees_tuned"] == pytest.approx(2.0, rel=1e-9)  # n: consistent


# -- the command --------------------------------------------------------------------------------


def test_identify_writes_a_tuned_file_that_runs_and_the_report(tmp_path):
    p = scenario(tmp_path, steps=20, runs=100, r1=3.0)
    text = p.read_text()
    out, rep = tmp_path / "out" / "tuned.toml", tmp_path / "report.json"
    res = ok("identify", p, "--param", "sensors.s1.R", "--param", "model.n0", "-o", out,
             "--report", rep)  # fmt: skip
    assert "sensors.s1.R" in res.stdout and "MSE given" in res.stdout
    report = json.loads(rep.read_text())
    assert report["method"] == "ml" and report["with_truth"] is False
    assert set(report["parameters"]) == {"sensors.s1.R", "model.n0"}
    r1 = report["parameters"]["sensors.s1.R"]
    assert r1["given"] == 3.0 and set(r1) == {"value", "stderr", "given"}
    assert set(report["cost"]["CKF"]) == {"mse_given", "mse_tuned", "anees_given", "anees_tuned"}
    tuned = fl.load(out)
    assert tuned.system.sensors[0].R[0, 0] == r1["value"]
    # the rest of the file as it was: only the two values' lines differ
    changed = [a for a, b in zip(text.splitlines(), out.read_text().splitlines(), strict=True)
               if a != b]  # fmt: skip
    assert len(changed) == 2 and any(line.startswith("R = 3.0") for line in changed)
    ok("run", out, "--out-dir", tmp_path / "run", "--runs", "20")
    one_line_error(cli("identify", p, "--param", "model.n0", "-o", out), "exists")


def test_bad_input_is_one_line(tmp_path):
    p = scenario(tmp_path, steps=10, runs=20)
    out = tmp_path / "t.toml"

    def refused(*args, fragments):
        one_line_error(cli("identify", p, *args, "-o", out), *fragments)
        assert not out.exists()

    refused("--param", "sensors.nope.R", fragments=["--param sensors.nope.R", "no element"])
    refused("--param", "model.q", fragments=["--param model.q", "has no model.q"])
    refused("--param", "scenario.name", fragments=["not a number or a square matrix"])
    refused("--param", "estimate.architectures", fragments=["not a number"])
    refused("--param", "model.n0", "--with-truth", tmp_path / "missing.mcap",
            fragments=["missing.mcap"])  # fmt: skip
    one_line_error(cli("identify", p, "-o", out), "--param")  # click: required
    # no [prior]: the filters start from no information there (no diffuse likelihood)
    text = p.read_text()
    prior = text[text.index("[prior]") : text.index("[[sensors]]")]
    p.write_text(text.replace(prior, "") + '\n[truth]\ninitial_mean = [0.0, 1.0]\n'
                 "initial_cov = [[4.0, 0.0], [0.0, 1.0]]\n")  # fmt: skip
    refused("--param", "sensors.s1.R", fragments=[str(p), "needs a [prior]", "diffuse"])


def test_a_sensor_whose_readings_are_all_lost_is_not_identifiable(tmp_path):
    """s2 loses each reading with probability 1 - 1e-7: none of its 550 is left (asserted),
    nothing tells its R (the likelihood does not depend on it)."""
    p = scenario(tmp_path, steps=10, runs=50, s2_extra="dropout = 0.9999999")
    assert np.isnan(fl.simulate(fl.load(p)).measurements["s2"]).all()
    one_line_error(
        cli("identify", p, "--param", "sensors.s2.R", "--param", "model.n0", "-o",
            tmp_path / "t.toml"),
        "--param sensors.s2.R", "not identifiable",
    )  # fmt: skip


def test_no_data_and_a_likelihood_not_finite_at_the_start(tmp_path):
    p = scenario(tmp_path, steps=10, runs=5)
    sc = fl.load(p)
    sim = fl.simulate(sc)
    for z in sim.measurements.values():
        z[:] = np.nan
    with pytest.raises(fl.FusionlogError, match="no data"):
        fl.identify(sc, sim, ["model.n0"])
    # a process noise without any in the position: the true increments (simulated with n0)
    # are off its support, so the truth's density is zero at the file's values
    q = tmp_path / "singular.toml"
    singular = "F = [[1.0, 1.0], [0.0, 1.0]]\nQ = [[0.0, 0.0], [0.0, 0.1]]"
    q.write_text(p.read_text().replace('kind = "constant-velocity"\nn0 = 0.3', singular))
    with pytest.raises(fl.FusionlogError, match="not finite at the file's values"):
        fl.identify(fl.load(q), fl.simulate(sc), ["sensors.s1.R"], with_truth=True)
    log = tmp_path / "s.mcap"
    ok("simulate", p, "-o", log)
    one_line_error(
        cli("identify", q, log, "--param", "sensors.s1.R", "--with-truth", "-o", tmp_path / "t"),
        "not finite at the file's values",
    )
    assert not (tmp_path / "t").exists()


def test_one_entry_of_a_matrix_is_a_parameter_and_written_back_in_its_matrix(tmp_path):
    """sensors.gps.R.1.1 (the sweep's key of one entry): a positive scalar, the tuned file's
    matrix holds it and keeps the other entries."""
    p = tmp_path / "xy.toml"
    p.write_text(
        textwrap.dedent("""
        [scenario]
        name = "xy"
        description = "two axes"
        steps = 20
        runs = 100
        seed = 4
        dt = 1.0
        state_names = ["x", "vx", "y", "vy"]
        [model]
        kind = "constant-velocity"
        axes = 2
        n0 = 0.2
        [prior]
        mean = [0.0, 1.0, 0.0, -1.0]
        cov = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
               [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
        [[sensors]]
        name = "gps"
        H = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
        R = [[1.0, 0.0],
             [0.0, 2.0]]   # per axis
        [estimate]
        architectures = ["CKF"]
    """)
    )
    out = tmp_path / "tuned.toml"
    ok("identify", p, "--param", "sensors.gps.R.1.1", "-o", out, "--report", tmp_path / "r.json")
    rep = json.loads((tmp_path / "r.json").read_text())["parameters"]["sensors.gps.R.1.1"]
    R = fl.load(out).system.sensors[0].R
    assert R[1, 1] == rep["value"] and R[0, 0] == 1.0 and R[0, 1] == 0.0
    assert abs(rep["value"] - 2.0) < 4 * rep["stderr"]
    assert "# per axis" in out.read_text()


def test_a_likelihood_without_a_maximum_is_refused(tmp_path):
    """s2's readings are s1's, copied: with R1 = R2 = their cross-covariance the difference
    of the two has variance 0, which it has, so the likelihood grows without bound towards
    that singular R; what the optimiser stops at is no maximum, and is refused (one line
    naming a parameter), not reported with standard errors."""
    extra = '[[correlations]]\nsensors = ["s1", "s2"]\ncov = [[0.0]]'
    sc = fl.load(scenario(tmp_path, runs=20, r1=1.0, r2=1.0, extra=extra))
    sim = fl.simulate(sc, seed=1)
    sim.measurements["s2"] = sim.measurements["s1"].copy()
    keys = ["sensors.s1.R", "sensors.s2.R", "correlations.0.cov"]
    with pytest.raises(fl.FusionlogError) as err:
        fl.identify(sc, sim, keys, cost=False)
    msg = str(err.value)
    assert "\n" not in msg and any(msg.startswith(f"--param {k}: not identifiable") for k in keys)
    assert "not a maximum" in msg or "flat" in msg, msg


def test_a_cross_covariance_of_sensors_that_never_measure_together_is_refused(tmp_path):
    """s1 at even seconds, s2 at odd ones: their cross-covariance never enters a reading's
    density (it acts only between readings of one instant), refused before optimising."""
    extra = '[[correlations]]\nsensors = ["s1", "s2"]\ncov = [[0.0]]'
    p = scenario(tmp_path, steps=20, runs=30, s1_extra="period = 2.0",
                 s2_extra="period = 2.0\noffset = 1.0", extra=extra)  # fmt: skip
    one_line_error(
        cli("identify", p, "--param", "sensors.s1.R", "--param", "correlations.0.cov", "-o",
            tmp_path / "t.toml"),
        "--param correlations.0.cov", "not identifiable",
    )  # fmt: skip


# -- recorded logs --------------------------------------------------------------------------------

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "tutorials" / "identify.md"


def test_a_replay_identifies_from_its_recordings_and_the_tuned_file_reads_them(tmp_path):
    """pipeline/replay_tum.toml: a SLAM track whose readings are the motion-capture positions
    plus N(0, 0.02^2) per axis (pipeline/data/make_more_logs.py), with the interpolated truth
    of the positions: R = 0.0004 I within 4 SE entry by entry; TUNED.toml, written in another
    folder, reads the same recordings (its sources made relative to it) and runs."""
    out = tmp_path / "elsewhere" / "tuned.toml"
    rep = tmp_path / "r.json"
    ok("identify", REPO / "pipeline" / "replay_tum.toml", "--param", "sensors.slam.R",
       "--with-truth", "-o", out, "--report", rep)  # fmt: skip
    r = json.loads(rep.read_text())["parameters"]["sensors.slam.R"]
    v, se = np.array(r["value"]), np.array(r["stderr"])
    assert (np.abs(v - 0.0004 * np.eye(3)) < 4 * se).all(), (v, se)
    assert json.loads(rep.read_text())["with_truth"] is True
    tuned = fl.load(out)
    assert np.array_equal(tuned.system.sensors[0].R, v)
    ok("run", out, "--out-dir", tmp_path / "run")


# the shared real logs beside the checkout (tests/test_replay_real_logs.py reads them there too)
EVO_BAG = Path(__file__).resolve().parents[2] / "shared" / "data" / "logs" / "evo_ROS_example.bag"


@pytest.mark.skipif(not EVO_BAG.exists(), reason="evo's ROS_example.bag is not available")
def test_evo_bag_the_two_slam_systems_cross_covariance_is_refused(tmp_path):
    """evo's ROS_example.bag (docs/tutorials/identify.md): ORB-SLAM and S-PTAM never stamp a
    pose at the same instant, so the cross-covariance of their errors is not in the data."""
    toml_text = EVO_REPLAY.format(bag=EVO_BAG)
    toml_text += '\n[[correlations]]\nsensors = ["orb", "sptam"]\n'
    toml_text += "cov = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]\n"
    p = tmp_path / "evo.toml"
    p.write_text(toml_text)
    one_line_error(
        cli("identify", p, "--param", "correlations.0.cov", "-o", tmp_path / "t.toml"),
        "--param correlations.0.cov",
        "not identifiable",
    )


def _commands(doc: str) -> list[tuple[str, str]]:
    """(command, the output shown) of each console block of the page's evo section."""
    out = []
    for block in re.findall(r"```console\n(.*?)```", doc[doc.index("## A recorded log") :], re.S):
        lines = block.splitlines()
        cmd, i = lines[0][2:], 1
        while cmd.endswith("\\"):
            cmd, i = cmd[:-1] + " " + lines[i].strip(), i + 1
        out.append((cmd, "\n".join(lines[i:])))
    return out


_PARAM = re.compile(r"^  (\S+)\s+(\S+)  \+- (\S+)  \(given \S+\)$", re.M)


@pytest.mark.skipif(not EVO_BAG.exists(), reason="evo's ROS_example.bag is not available")
@pytest.mark.skipif(
    os.environ.get("FUSIONLOG_WALKTHROUGHS") != "1",
    reason="about 6 CPU-minutes (two identifications on 13,801 instants): `make walkthroughs`",
)
def test_the_evo_walkthrough(tmp_path, monkeypatch):
    """docs/tutorials/identify.md on evo's bag (its commands, marked skip there for their
    time): the values it shows are those identified (within 0.1 of their standard error:
    the optimiser's stopping point, not the page's rounding), the tables of `fusionlog run`
    are what it prints. Independent of the code: with the truth, each diagonal R entry is
    the mean square of the track's distance from the motion capture on that axis, up to what
    the readings without a truth sample (6 % of ORB-SLAM's, 7 % of S-PTAM's) move it; the
    fused track with the identified R is no worse than the better system alone (it was
    worse before); the innovations are not white (the drift)."""
    doc = DOC.read_text()
    toml_text = re.search(r"```toml\n(# evo_example.toml\n.*?)```", doc, re.S).group(1)
    (tmp_path / "evo_example.toml").write_text(toml_text)
    (tmp_path / "ROS_example.bag").symlink_to(EVO_BAG)
    monkeypatch.chdir(tmp_path)
    printed = {}
    for cmd, shown in _commands(doc):
        res = ok(*shlex.split(cmd)[1:])
        printed[cmd] = res.stdout
        if " identify " in cmd:
            got = {k: (float(v), float(se)) for k, v, se in _PARAM.findall(res.stdout)}
            want = {k: (float(v), float(se)) for k, v, se in _PARAM.findall(shown)}
            assert want and set(got) == set(want), cmd
            for k, (v, se) in want.items():
                assert abs(got[k][0] - v) <= 0.1 * se, (cmd, k, got[k], v)
                assert got[k][1] == pytest.approx(se, rel=0.05), (cmd, k)
            assert re.findall(r"p = (\S+)", res.stdout) == ["0", "0"]  # neither is white
        else:  # the rows of the tables
            for line in shown.splitlines():
                if line.startswith(("CKF", "SKF", "  ")) and "%" in line:
                    assert line in res.stdout.splitlines(), (cmd, line)
    sc = fl.load("evo_example.toml")
    sim = fl.simulate(sc)
    report = json.loads(Path("evo_report_truth.json").read_text())["parameters"]
    for name, rows in (("orb", [0, 2, 4]), ("sptam", [0, 2, 4])):
        z, t = sim.measurements[name][0], sim.truth[0][:, rows]
        both = np.isfinite(z).all(axis=1) & np.isfinite(t).all(axis=1)
        assert 0.9 < both.sum() / np.isfinite(z).all(axis=1).sum() < 0.95
        mean_square = ((z[both] - t[both]) ** 2).mean(axis=0)
        for j in range(3):
            got = report[f"sensors.{name}.R.{j}.{j}"]["value"]
            assert got == pytest.approx(mean_square[j], rel=0.1), (name, j)
    mse = {}
    for out in ("before", "after"):
        arch = json.loads(Path(out, "summary.json").read_text())["architectures"]
        mse[out] = {a: e["mse"] for a, e in arch.items()}
    assert mse["before"]["CKF"] > mse["before"]["SKF:orb"]
    # S-PTAM's R is 5e4 times ORB-SLAM's or more: its weight moves the fused MSE by ~1e-5
    assert mse["after"]["CKF"] <= mse["after"]["SKF:orb"] * (1 + 1e-4)
    assert mse["after"]["CKF"] < mse["before"]["CKF"]


EVO_REPLAY = """
[scenario]
name = "evo_ros_example"
description = "evo's ROS_example.bag: ORB-SLAM and S-PTAM positions against the ground truth"
state_names = ["x", "vx", "y", "vy", "z", "vz"]

[model]
kind = "constant-velocity"
axes = 3
n0 = 0.01

[prior]
mean = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
cov = [[0.01, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
       [0.0, 0.0, 0.01, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
       [0.0, 0.0, 0.0, 0.0, 0.01, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]]

[[sensors]]
name = "orb"
source = "{bag}"
topic = "ORB-SLAM"
values = ["pose.position.x", "pose.position.y", "pose.position.z"]
time = "header.stamp"
R = [[0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01]]
H = [[1.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
     [0.0, 0.0, 0.0, 0.0, 1.0, 0.0]]

[[sensors]]
name = "sptam"
source = "{bag}"
topic = "S-PTAM"
values = ["pose.position.x", "pose.position.y", "pose.position.z"]
time = "header.stamp"
R = [[0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01]]
H = [[1.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
     [0.0, 0.0, 0.0, 0.0, 1.0, 0.0]]

[truth]
source = "{bag}"
topic = "groundtruth"
values = ["pose.position.x", "pose.position.y", "pose.position.z"]
time = "header.stamp"
states = ["x", "y", "z"]
match = "nearest"
max_diff = 0.05

[estimate]
architectures = ["CKF", "SKF:orb", "SKF:sptam"]
"""


def test_a_nonlinear_model_is_identified_by_the_ekf_approximation_without_a_cost():
    """pipeline/radar_tracking.toml (range-bearing radars, EKF): R of the first radar and
    n0 within 4 SE of the values simulated; no exact analysis, so the cost is null."""
    sc = fl.load(REPO / "pipeline" / "radar_tracking.toml")
    res = fl.identify(sc, fl.simulate(sc, runs=100, seed=3), ["sensors.0.R", "model.n0"])
    assert res.exact is False and "EKF" in res.table()
    v, se = np.array(res.values["sensors.0.R"]), np.array(res.stderr["sensors.0.R"])
    assert (np.abs(v - np.diag([100.0, 3.0e-4])) < 4 * se).all(), (v, se)
    assert abs(res.values["model.n0"] - 0.5) < 4 * res.stderr["model.n0"]
    assert res.report["cost"] and all(c is None for c in res.report["cost"].values())


def test_the_estimates_of_one_run_are_statsmodels_maximum_likelihood(tmp_path):
    """Two position sensors with correlated noise, one run of 31 instants: R1, R2, their
    cross-covariance and n0 maximise statsmodels' likelihood of the same model too (its own
    filter and optimiser), to the optimisers' tolerance."""
    sm = pytest.importorskip("statsmodels.tsa.statespace.mlemodel")
    extra = '[[correlations]]\nsensors = ["s1", "s2"]\ncov = [[0.3]]'
    sim = fl.simulate(fl.load(scenario(tmp_path, "t.toml", runs=1, extra=extra)), seed=2)
    believed = '[[correlations]]\nsensors = ["s1", "s2"]\ncov = [[0.0]]'
    sc = fl.load(scenario(tmp_path, "m.toml", runs=1, r1=1.0, r2=1.0, n0=0.16, extra=believed))
    keys = ["sensors.s1.R", "sensors.s2.R", "correlations.0.cov", "model.n0"]
    res = fl.identify(sc, sim, keys, cost=False)

    class CV(sm.MLEModel):
        def __init__(self, endog):
            super().__init__(endog, k_states=2)
            self["design"] = np.array([[1.0, 0.0], [1.0, 0.0]])
            self["transition"] = np.array([[1.0, 1.0], [0.0, 1.0]])
            self["selection"] = np.eye(2)
            self.initialize_known(np.array([0.0, 1.0]), np.diag([4.0, 1.0]))

        @property
        def start_params(self):
            return np.array([1.0, 1.0, 0.0, 0.16])

        def transform_params(self, u):
            return np.array([np.exp(u[0]), np.exp(u[1]), u[2], np.exp(u[3])])

        def untransform_params(self, p):
            return np.array([np.log(p[0]), np.log(p[1]), p[2], np.log(p[3])])

        def update(self, params, **kwargs):
            r1, r2, c, n0 = super().update(params, **kwargs)
            self["obs_cov"] = np.array([[r1, c], [c, r2]])
            self["state_cov"] = n0 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])

    y = np.concatenate([sim.measurements["s1"][0], sim.measurements["s2"][0]], axis=1)
    theirs = CV(y).fit(disp=False, maxiter=500)
    ours = [float(np.ravel(res.values[k])[0]) for k in keys]
    assert np.allclose(ours, theirs.params, rtol=1e-3, atol=1e-4), (ours, theirs.params)
    assert res.loglik == pytest.approx(theirs.llf, rel=1e-8)
