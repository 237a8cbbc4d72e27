"""The bound check (DESIGN.md "Unknown correlation and the bound check"): lambda_k =
lambda_max(P_k^-1 E[e_k e_k^T]), bias included, per instant, against the same ratio computed
here from the exact error moments of the references written from the papers (local KFs of
eq. 35, Millman, CI, ICI, EI) by superposition (`references.exact_by_superposition`) and a
generalised symmetric eigenproblem (scipy.linalg.eigh(E, P), no whitening); per run where the
runs' patterns differ; CKF's = 1 (a consistent filter), MSC's > 1 where its NEES leaves the
band, CI's <= 1 on correlated sensors; the Monte Carlo estimate of a model without an exact
analysis against the exact value; `[estimate] ci_criterion = "det"` against a brute-force
minimiser; summary.json, the table, sweep.parquet and the recording carrying it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from cli_helpers import cli, ok, one_line_error
from conditioning import EPS
from references import exact_by_superposition, local_filters, system_of
from scipy.optimize import minimize, minimize_scalar
from test_ei import ei_pair
from test_ici import XATOL, ici_pair, system

import fusionlog as fl
from fusionlog.core.architectures import build_plan, estimate, run_plan
from fusionlog.core.bound import BOUND_TOL, BoundSums
from fusionlog.core.exact import analyse
from fusionlog.core.simulate import simulate
from fusionlog.driver import conditional_sums

K = 8


def lam_max(E: np.ndarray, P: np.ndarray) -> np.ndarray:
    """lambda_max of the pencil (E, P) at every step (K+1,): E v = lambda P v."""
    return np.array(
        [scipy.linalg.eigh(e, p, eigvals_only=True)[-1] for e, p in zip(E, P, strict=True)]
    )


def pairwise(pair):
    """A reference `ref(filt, arch, Z, mask)` of a pairwise rule on the local KFs of eq. (35)
    (`references.local_filters`); `pair(xa (n, R), Pa, xb, Pb)` -> (x, P)."""

    def ref(filt, arch, Z, mask):
        xs, Js = local_filters(filt, Z, mask)  # (S, R, K+1, n), (K+1, S, S, n, n)
        S, R, K1, n = xs.shape
        mean, cov = np.empty((R, K1, n)), np.empty((K1, n, n))
        for k in range(K1):
            x, P = xs[0, :, k].T, Js[k, 0, 0]
            for j in range(1, S):
                x, P = pair(x, P, xs[j, :, k].T, Js[k, j, j])[:2]
            mean[:, k], cov[k] = x.T, P
        return mean, cov

    return ref


def ici_min(xa, Pa, xb, Pb, shift=0.0):
    """ICI with omega minimising tr P (scipy's bounded Brent), moved by `shift` (a tolerance's
    finite difference)."""
    w = minimize_scalar(lambda w: np.trace(ici_pair(xa, Pa, xb, Pb, w)[1]), bounds=(0.0, 1.0),
                        method="bounded", options={"xatol": XATOL}).x  # fmt: skip
    return ici_pair(xa, Pa, xb, Pb, min(max(w + shift, 0.0), 1.0))


REFERENCES = {
    "EI": pairwise(ei_pair),
    "ICI": pairwise(ici_min),
    "MSC": None,  # references.fuse
    "CI": None,
}


def masks(sys, runs: int, seed: int) -> np.ndarray:
    """Per-run patterns (runs, K+1, m): each sensor's reading lost with probability 1/4."""
    rng = np.random.default_rng(seed)
    lost = rng.random((runs, K + 1, len(sys.sensors))) < 0.25
    return np.repeat(~lost, [s.dim for s in sys.sensors], axis=2)


def tolerance(arch, sys, mask, lam):
    """What the reference's own inaccuracy allows: rounding amplified by the conditioning of
    the inverses (P and the locals' covariances, about 1e3 here) for the closed forms; for
    ICI also omega's, known to sqrt(eps) |w| + xatol (the minimiser), times lambda's slope in
    omega (a finite difference)."""
    tol = 1e4 * EPS * np.maximum(lam, 1.0)
    if arch == "ICI":
        h = 1e-6
        moved = pairwise(lambda *a: ici_min(*a, shift=h))
        _, E, P = exact_by_superposition(sys, sys, arch, mask, moved)
        slope = np.abs(lam_max(E, P) - lam) / h
        tol = tol + 3 * slope * (np.sqrt(EPS) + XATOL)
    return tol


@pytest.mark.parametrize("arch", list(REFERENCES))
def test_per_run_ratio_equals_the_references_and_the_worst_run(arch):
    sys = system() if arch in ("EI", "ICI") else system_of(5, [1, 2], correlated=True)
    present = masks(sys, 3, 21)
    plan = build_plan(sys, arch, K, present)
    assert plan.per_run
    ex = analyse(plan, sys)
    want = []
    for r in range(len(present)):
        _, E, P = exact_by_superposition(sys, sys, arch, present[r], REFERENCES[arch])
        lam = lam_max(E, P)
        tol = tolerance(arch, sys, present[r], lam)
        assert (np.abs(ex.bound[r] - lam) <= tol).all(), (r, ex.bound[r], lam)
        want.append(lam)
    # the run average's bound (dropouts: per run, conditional) is the worst run's
    cond = conditional_sums({arch: plan}, sys, len(present))[arch]
    np.testing.assert_array_equal(cond.bound, ex.bound.max(axis=0))
    assert np.abs(cond.bound - np.max(want, axis=0)).max() <= 1e-6


def test_ckf_bound_is_one():
    """A Kalman filter on the true model reports its error covariance: lambda = 1 at every
    instant, in our analysis and in the reference's moments."""
    sys = system_of(3, [2, 1, 1], correlated=True)
    mask = np.ones((K + 1, sys.m), bool)
    ex = analyse(build_plan(sys, "CKF", K), sys)
    assert np.abs(ex.bound - 1).max() <= BOUND_TOL
    _, E, P = exact_by_superposition(sys, sys, "CKF", mask)
    assert np.abs(lam_max(E, P) - 1).max() <= BOUND_TOL


def test_msc_exceeds_one_where_its_nees_leaves_the_band():
    sc = fl.load("tests/golden/small.toml")
    sim = fl.simulate(sc, runs=500)
    ev = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["MSC", "CKF"]))
    msc = ev.series["MSC"]
    lower, upper = ev.nees_bounds
    outside = (msc["nees"] > upper) | (msc["nees"] < lower)
    assert outside.any()
    assert (msc["bound"][outside] > 1).all()
    # lambda_max is at least the mean eigenvalue, the expected NEES over n
    assert (msc["bound"] >= msc["expected_nees"] / sc.system.n * (1 - 1e-12)).all()
    b = ev.summary["architectures"]["MSC"]["bound"]
    assert b["holds"] is False and b["worst"] > 1
    assert ev.summary["architectures"]["CKF"]["bound"]["holds"] is True


def test_ci_keeps_its_bound_on_correlated_sensors():
    """Correlated sensor noise (pipeline/heterogeneous.toml, and a random two-sensor system by
    the reference): CI's lambda <= 1 at every instant, where MSC's is not."""
    sc = fl.load("pipeline/heterogeneous.toml")
    sim = fl.simulate(sc, runs=50, steps=30)
    ev = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CI", "MSC"]))
    archs = ev.summary["architectures"]
    assert archs["CI"]["bound"]["holds"] is True
    assert archs["CI"]["bound"]["worst"] <= 1 + BOUND_TOL
    assert archs["MSC"]["bound"]["holds"] is False
    sys = system_of(5, [1, 2], correlated=True)
    _, E, P = exact_by_superposition(sys, sys, "CI", np.ones((K + 1, sys.m), bool))
    assert (lam_max(E, P) <= 1 + BOUND_TOL).all()


def test_monte_carlo_estimate_agrees_with_the_exact_ratio():
    """`BoundSums` (what a model without an exact analysis gets) on a linear model: within four
    of its standard errors of the exact lambda at every instant, for a consistent filter (1)
    and an over-confident one (MSC)."""
    sys = system()
    M = 4000
    x, z = simulate(sys, K, 17, 0, M)
    for arch in ("CKF", "MSC"):
        plan = build_plan(sys, arch, K)
        e = run_plan(plan, z)
        acc = BoundSums(K + 1, sys.n)
        acc.add(x[:2000], e.mean[:2000], e.cov)
        acc.merge(_sums(sys, x[2000:], e.mean[2000:], e.cov))
        lam, se = acc.ratio()
        exact = analyse(plan, sys).bound
        assert (np.abs(lam - exact) <= 4 * se).all(), (arch, lam, exact, se)


def _sums(sys, x, mean, cov):
    acc = BoundSums(K + 1, sys.n)
    acc.add(x, mean, cov)
    return acc


def test_nonlinear_models_get_a_monte_carlo_estimate_said_to_be_one():
    sc = fl.load("pipeline/radar_tracking.toml")
    sim = fl.simulate(sc, runs=40, steps=10)
    ev = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF", "CI"], filter="EKF"))
    for a in ("CKF", "CI"):
        b = ev.summary["architectures"][a]["bound"]
        assert b["monte_carlo"] is True and b["stderr"] > 0 and b["worst"] > 0
        assert ev.series[a]["bound"][b["worst_step"]] == b["worst"]


def det_brute_force(Ps: np.ndarray) -> float:
    """min over the simplex of log det (sum_i w_i P_i^-1)^-1, by Nelder-Mead on softmax
    weights from several starts (no gradient, nothing shared with the code's Newton)."""
    Ys = np.linalg.inv(Ps)

    def cost(t):
        w = np.exp(t - t.max())
        w /= w.sum()
        return -np.linalg.slogdet(np.tensordot(w, Ys, 1))[1]

    best = np.inf
    for start in np.eye(len(Ps)) * 3:
        r = minimize(cost, start, method="Nelder-Mead",
                     options={"xatol": 1e-12, "fatol": 1e-15, "maxiter": 20000})  # fmt: skip
        best = min(best, r.fun)
    return best


def test_ci_criterion_det_minimises_the_determinant(tmp_path):
    import dataclasses

    sys = dataclasses.replace(system(), ci_criterion="det")
    _, z = simulate(sys, K, 5, 0, 2)
    det_cov = estimate(sys, z, "CI").cov
    tr_cov = estimate(dataclasses.replace(sys, ci_criterion="trace"), z, "CI").cov
    xs, Js = local_filters(sys, z, np.ones((K + 1, sys.m), bool))
    S = len(sys.sensors)
    for k in range(1, K + 1):
        Ps = np.array([Js[k, j, j] for j in range(S)])
        got = np.linalg.slogdet(det_cov[k])[1]
        brute = det_brute_force(Ps)
        # the optimum's cost to the minimiser's accuracy (fatol), and no worse
        assert got <= brute + 1e-9, (k, got, brute)
        assert np.linalg.slogdet(tr_cov[k])[1] >= got - 1e-12  # trace's weights: not better
        assert np.trace(tr_cov[k]) <= np.trace(det_cov[k]) * (1 + 1e-12)


def test_ci_criterion_is_read_sweepable_and_refused_when_unknown(tmp_path):
    text = Path("tests/golden/small.toml").read_text()
    path = tmp_path / "c.toml"
    path.write_text(text.replace('"FBS"]', '"FBS"]\nci_criterion = "det"'))
    assert fl.load(path).system.ci_criterion == "det"
    path.write_text(text.replace('"FBS"]', '"FBS"]\nci_criterion = "volume"'))
    one_line_error(cli("run", path, "--out-dir", tmp_path / "o"), "c.toml",
                   "estimate.ci_criterion", "volume", "trace, det")  # fmt: skip
    res = cli("sweep", "tests/golden/small.toml", "--vary", "estimate.ci_criterion=trace,det",
              "--exact-only", "--arch", "CI", "--out-dir", tmp_path / "s")  # fmt: skip
    assert res.exit_code == 0, res.output
    res = cli("sweep", "tests/golden/small.toml", "--vary", "estimate.ci_criterion=trace,cov",
              "--exact-only", "--arch", "CI", "--out-dir", tmp_path / "s2")  # fmt: skip
    one_line_error(res, "estimate.ci_criterion", "cov")


def test_summary_table_sweep_and_recording_carry_it(tmp_path):
    from fusionlog.io.rrd import read_recording

    res = ok("run", "tests/golden/small.toml", "--runs", "100", "--arch", "CKF", "--arch", "MSC",
             "--arch", "EI", "--out-dir", tmp_path / "r")  # fmt: skip
    header = res.output.splitlines()[1].split()
    assert header[-1] == "bound"
    assert "fails at k=" in res.output and " ok" in res.output
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    for a, e in summary["architectures"].items():
        assert set(e["bound"]) == {"holds", "worst", "worst_step"}, a
    rec = read_recording(tmp_path / "r" / "evaluation.rrd")
    for a in ("CKF", "MSC", "EI"):
        series = rec["series"][f"metrics/bound/{a}"]
        b = summary["architectures"][a]["bound"]
        assert np.nanmax(series) == pytest.approx(b["worst"], rel=1e-12)
    assert np.all(rec["series"]["metrics/bound/limit"] == 1.0)
    res = ok("sweep", "tests/golden/small.toml", "--vary", "sensors.s1.R=0.5,2", "--exact-only",
             "--arch", "CKF", "--arch", "MSC", "--out-dir", tmp_path / "s")  # fmt: skip
    import pyarrow.parquet as pq

    table = pq.read_table(tmp_path / "s" / "sweep.parquet").to_pylist()
    points = json.loads((tmp_path / "s" / "summary.json").read_text())["points"]
    by = {(r["sensors.s1.R"], r["architecture"]): r["bound_worst"] for r in table}
    for p in points:
        for a, e in p["architectures"].items():
            assert by[p["values"]["sensors.s1.R"], a] == e["bound"]["worst"]
    assert by[0.5, "MSC"] > 1 and by[0.5, "CKF"] == pytest.approx(1, abs=BOUND_TOL)
