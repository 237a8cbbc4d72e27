"""EI, ellipsoidal intersection (DESIGN.md "Unknown correlation and the bound check"; Sijs and
Lazar 2012), in every backend: against local Kalman filters and the pairwise EI written here
from the paper's equations (8), (11)-(16) with general matrices (inverses and solves, the
mutual mean in the paper's transformed coordinates), per run; its exact expected MSE against
Monte Carlo; with EKF and UKF locals; a model with one sensor refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import cli, one_line_error
from conditioning import EPS
from local_filters import local_kfs
from test_ici import ONE_SENSOR, dropped, system

import fusionlog as fl
from fusionlog.core.architectures import build_plan, estimate, run_plan
from fusionlog.core.architectures.ei import ZETA
from fusionlog.core.architectures.replay import replay_estimates
from fusionlog.core.exact import analyse
from fusionlog.core.nonlinear import estimate as lanes_estimate
from fusionlog.core.simulate import simulate


def ei_pair(xa, Pa, xb, Pb):
    """Sijs and Lazar's EI of two estimates, step by step as the paper writes it."""
    n = len(xa)
    da, Sa = np.linalg.eigh(Pa)  # (12a)
    Da_half = np.diag(np.sqrt(da))
    Da_mhalf = np.diag(1 / np.sqrt(da))
    d, Sb = np.linalg.eigh(Da_mhalf @ Sa.T @ Pb @ Sa @ Da_mhalf)
    T = Sa @ Da_half @ Sb  # (12b)
    DG = np.diag(np.maximum(d, 1.0))  # (11)
    Gamma = T @ DG @ T.T  # Theorem 6
    Pa_i, Pb_i, G_i = np.linalg.inv(Pa), np.linalg.inv(Pb), np.linalg.inv(Gamma)
    P = np.linalg.inv(Pa_i + Pb_i - G_i)  # (8)
    mua, mub = np.linalg.solve(T, xa), np.linalg.solve(T, xb)  # (13)
    eta = ZETA if (np.abs(1 - d) <= 10 * ZETA).any() else 0.0  # (16c)
    Wa = np.diag(1 / d) - np.linalg.inv(DG) + eta * np.eye(n)  # (16b)
    Wb = np.eye(n) - np.linalg.inv(DG) + eta * np.eye(n)
    mug = np.linalg.solve(Wa + Wb, Wa @ mua + Wb @ mub)  # (16a)
    gamma = T @ mug
    x = P @ (Pa_i @ xa + Pb_i @ xb - G_i @ gamma)  # (7)
    return x, (P + P.T) / 2, np.linalg.cond(Pa) * np.linalg.cond(Pb)


def ei_reference(xs: np.ndarray, Ps: np.ndarray):
    """((1 + 2) + 3) ...; with the product of the locals' condition numbers along the way,
    which bounds how much the inverses above amplify rounding."""
    x, P, cond = xs[0], Ps[0], 1.0
    for j in range(1, len(xs)):
        x, P, c = ei_pair(x, P, xs[j], Ps[j])
        cond = max(cond, c)
    return x, P, cond


def reference(sys, z):
    """EI of the local KFs of every run of z (M, K+1, m), and each result's tolerance: rounding
    amplified by the conditioning of the inverses the formulas take (a few hundred ulps of
    margin for the dozen products between them)."""
    out = [[ei_reference(*lk) for lk in zip(*local_kfs(sys, run), strict=True)] for run in z]
    x = np.array([[o[0] for o in run] for run in out])
    P = np.array([[o[1] for o in run] for run in out])
    cond = np.array([[o[2] for o in run] for run in out])
    tol_x = 300 * EPS * cond[..., None] * (1 + np.abs(x).max(axis=-1, keepdims=True))
    tol_P = 300 * EPS * cond[..., None, None] * np.abs(P).max(axis=(-2, -1), keepdims=True)
    return x, P, tol_x, tol_P


def check(got_mean, got_cov, sys, z):
    x, P, tx, tP = reference(sys, z)
    cov = got_cov if got_cov.ndim == 4 else np.broadcast_to(got_cov, P.shape)
    assert (np.abs(got_mean - x) <= tx).all(), np.abs(got_mean - x).max()
    assert (np.abs(cov - P) <= tP).all(), np.abs(cov - P).max()


def test_shared_plan_equals_the_formulas():
    sys = system()
    _, z = simulate(sys, 12, 3, 0, 4)
    e = estimate(sys, z, "EI")
    assert e.cov.ndim == 3  # one plan for all runs
    check(e.mean, e.cov, sys, z)


def test_per_run_plan_equals_the_formulas():
    sys = system()
    z = dropped(sys, 5, 10, 4)
    plan = build_plan(sys, "EI", 10, ~np.isnan(z))
    assert plan.per_run
    e = run_plan(plan, z)
    check(e.mean, e.cov, sys, z)


def test_one_run_without_plans_equals_the_formulas():
    sys = system()
    z = dropped(sys, 1, 30, 5)
    fast = replay_estimates(sys, ["EI"], z)
    assert fast is not None  # the one-run path takes it
    check(fast["EI"].mean, fast["EI"].cov, sys, z)


@pytest.mark.parametrize("filt", ["EKF", "UKF"])
def test_ekf_and_ukf_locals_run_and_on_a_linear_model_are_the_formulas(filt):
    sys = system(filt)
    z = dropped(sys, 3, 8, 6)
    tr = lanes_estimate(sys, "EI", z, np.arange(9.0))
    check(tr.mean, tr.cov, sys, z)


def test_equal_estimates_fuse_to_themselves():
    """Two equal estimates are all mutual (every d_i = 1, eta = zeta): EI gives them back, the
    mutual mean their average, up to the rounding of d (a few ulps) over zeta."""
    from fusionlog.core.architectures.ei import ei

    rng = np.random.default_rng(2)
    B = rng.standard_normal((3, 3))
    P = B @ B.T + np.eye(3)
    C, Pf = ei(np.stack([P, P]), None, "trace")
    assert np.allclose(Pf, P, rtol=1e-12, atol=0)
    assert np.abs(C - np.hstack([np.eye(3), np.eye(3)]) / 2).max() <= 1e3 * EPS / ZETA


def test_expected_mse_agrees_with_monte_carlo():
    sys = system()
    K, M = 15, 4000
    x, z = simulate(sys, K, 11, 0, M)
    plan = build_plan(sys, "EI", K)
    e = run_plan(plan, z).mean - x
    ex = analyse(plan, sys)
    # per run, the squared error of each state averaged over the instants: M independent values
    per_run = (e**2).mean(axis=1)
    mc, se = per_run.mean(axis=0), per_run.std(axis=0, ddof=1) / np.sqrt(M)
    want = np.diagonal(ex.mse, axis1=-2, axis2=-1).mean(axis=0)
    assert (np.abs(mc - want) <= 4 * se).all(), (mc, want, se)
    assert np.abs(ex.bias).max() < 1e-9 * np.abs(x).max()  # unbiased: the weights sum to I


def test_the_cli_runs_it_and_its_summary_has_the_exact_values(tmp_path):
    res = cli("run", "pipeline/heterogeneous.toml", "--runs", "300", "--steps", "20",
              "--arch", "EI", "--arch", "CI", "--out-dir", tmp_path)  # fmt: skip
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "summary.json").read_text())["architectures"]["EI"]
    assert abs(s["mse"] - s["expected"]["mse"]) <= 4 * s["stderr"]["mse"]
    assert set(s["bound"]) == {"holds", "worst", "worst_step"}


def test_one_sensor_is_refused_in_one_line(tmp_path):
    path = tmp_path / "one.toml"
    path.write_text(ONE_SENSOR)
    res = cli("run", path, "--arch", "EI", "--out-dir", tmp_path / "out")
    one_line_error(res, "--arch", "EI fuses at least 2 local filters", "1 sensor")
    sc = fl.load(path)
    with pytest.raises(fl.FusionlogError, match="EI fuses at least 2 local filters"):
        fl.estimate(sc, fl.simulate(sc), ["EI"])
    path.write_text(ONE_SENSOR + '\n[estimate]\narchitectures = ["EI"]\n')
    one_line_error(cli("run", path, "--out-dir", tmp_path / "o2"), "one.toml", "EI fuses")
