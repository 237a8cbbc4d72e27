"""ICI, inverse covariance intersection (DESIGN.md "Unknown correlation and the bound check";
Noack, Sijs, Reinhardt, Hanebeck 2017), in every backend: against local Kalman filters and the
pairwise ICI written here from the formulas, with omega from scipy's bounded scalar minimiser
of tr P; its exact expected MSE against Monte Carlo; with EKF and UKF locals; a model with one
sensor refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import cli, one_line_error
from conditioning import EPS
from local_filters import local_kfs
from scipy.optimize import minimize_scalar

import fusionlog as fl
from fusionlog.core.architectures import build_plan, estimate, run_plan
from fusionlog.core.architectures.replay import replay_estimates
from fusionlog.core.exact import analyse
from fusionlog.core.model import Prior, Sensor, System, constant_velocity
from fusionlog.core.nonlinear import estimate as lanes_estimate
from fusionlog.core.simulate import simulate

#: scipy's bounded Brent stops within sqrt(eps) |w| + xatol / 3 of the minimiser it brackets
XATOL = 1e-12


def system(filt: str | None = None) -> System:
    """A constant-velocity target in 2-D seen by three sensors of different quality (so that
    the locals' covariances differ and every omega is decided)."""
    F1, Q1 = constant_velocity(1.0, 0.3)
    F, Q = np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1)
    sensors = (
        Sensor("a", np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]]), np.diag([4.0, 1.0])),
        Sensor("b", np.array([[1.0, 0, 0.5, 0]]), np.array([[0.5]])),
        Sensor("c", np.array([[0, 0, 1.0, 0], [0, 1.0, 0, 0]]), np.diag([2.0, 0.3])),
    )
    prior = Prior(np.array([5.0, 1.0, -3.0, 0.5]), np.diag([20.0, 4.0, 20.0, 4.0]))
    return System(F, Q, sensors, prior, filter=filt)


def ici_pair(xa, Pa, xb, Pb, w):
    """The two-estimate ICI of the paper for a given omega."""
    Ga = np.linalg.inv(w * Pa + (1 - w) * Pb)
    Ia, Ib = np.linalg.inv(Pa), np.linalg.inv(Pb)
    P = np.linalg.inv(Ia + Ib - Ga)
    x = P @ (Ia - w * Ga) @ xa + P @ (Ib - (1 - w) * Ga) @ xb
    return x, (P + P.T) / 2


def ici_reference(xs: np.ndarray, Ps: np.ndarray):
    """((1 + 2) + 3) ..., each omega minimising tr P by minimize_scalar (bounded); returns the
    fused x, P and a tolerance for each: what the pairs' omegas, each known to within what the
    minimiser resolves (its xatol and sqrt(eps) |w|, and the flatness of tr P at its minimum,
    sqrt(2 eps tr P / (d^2 tr P / dw^2))), move them by (finite differences in each omega)."""
    omegas, spreads = [], []
    x, P = xs[0], Ps[0]
    for j in range(1, len(xs)):

        def cost(w, x=x, P=P, j=j):
            return np.trace(ici_pair(x, P, xs[j], Ps[j], w)[1])

        w = minimize_scalar(cost, bounds=(0.0, 1.0), method="bounded",
                            options={"xatol": XATOL}).x  # fmt: skip
        h = 1e-4
        lo, hi = max(w - h, 0.0), min(w + h, 1.0)
        mid = (lo + hi) / 2
        curv = abs(cost(hi) - 2 * cost(mid) + cost(lo)) / ((hi - lo) / 2) ** 2
        flat = np.sqrt(2 * EPS * cost(w) / max(curv, EPS))
        omegas.append(w)
        spreads.append(3 * (np.sqrt(EPS) * abs(w) + XATOL + flat))
        x, P = ici_pair(x, P, xs[j], Ps[j], w)

    def fused(ws):
        x, P = xs[0], Ps[0]
        for j, w in enumerate(ws, start=1):
            x, P = ici_pair(x, P, xs[j], Ps[j], min(max(w, 0.0), 1.0))
        return x, P

    tol_x, tol_P = np.zeros_like(x), np.zeros_like(P)
    for i, d in enumerate(spreads):
        up = list(omegas)
        up[i] += 1e-6
        x1, P1 = fused(up)
        tol_x += np.abs(x1 - x) / 1e-6 * d
        tol_P += np.abs(P1 - P) / 1e-6 * d
    scale = 1e-9 * (1 + np.abs(x).max()), 1e-9 * np.abs(P).max()
    return x, P, tol_x + scale[0], tol_P + scale[1]


def reference(sys: System, z: np.ndarray):
    """ICI of the local KFs of every run of z (M, K+1, m), and the tolerances."""
    out = [[ici_reference(*lk) for lk in zip(*local_kfs(sys, run), strict=True)] for run in z]
    return (np.array([[o[i] for o in run] for run in out]) for i in range(4))


def check(got_mean, got_cov, sys, z):
    x, P, tx, tP = reference(sys, z)
    cov = got_cov if got_cov.ndim == 4 else np.broadcast_to(got_cov, P.shape)
    assert (np.abs(got_mean - x) <= tx).all(), np.abs(got_mean - x).max()
    assert (np.abs(cov - P) <= tP).all(), np.abs(cov - P).max()


def dropped(sys: System, runs: int, steps: int, seed: int) -> np.ndarray:
    """Runs with each sensor's reading lost with probability 1/4."""
    _, z = simulate(sys, steps, seed, 0, runs)
    lost = np.random.default_rng(seed).random(z.shape[:2] + (len(sys.sensors),)) < 0.25
    for j, sl in enumerate(sys.sensor_slices):
        z[:, :, sl][lost[:, :, j]] = np.nan
    return z


def test_shared_plan_equals_the_formulas():
    sys = system()
    _, z = simulate(sys, 12, 3, 0, 4)
    e = estimate(sys, z, "ICI")
    assert e.cov.ndim == 3  # one plan for all runs
    check(e.mean, e.cov, sys, z)


def test_per_run_plan_equals_the_formulas():
    sys = system()
    z = dropped(sys, 5, 10, 4)
    plan = build_plan(sys, "ICI", 10, ~np.isnan(z))
    assert plan.per_run
    e = run_plan(plan, z)
    check(e.mean, e.cov, sys, z)


def test_one_run_without_plans_equals_the_formulas():
    sys = system()
    z = dropped(sys, 1, 30, 5)
    fast = replay_estimates(sys, ["ICI"], z)
    assert fast is not None  # the one-run path takes it
    check(fast["ICI"].mean, fast["ICI"].cov, sys, z)


@pytest.mark.parametrize("filt", ["EKF", "UKF"])
def test_ekf_and_ukf_locals_run_and_on_a_linear_model_are_the_formulas(filt):
    sys = system(filt)
    z = dropped(sys, 3, 8, 6)
    tr = lanes_estimate(sys, "ICI", z, np.arange(9.0))
    check(tr.mean, tr.cov, sys, z)


def test_with_ekf_and_ukf_locals_on_the_radar():
    sc = fl.load("pipeline/radar_tracking.toml")
    for filt in ("EKF", "UKF"):
        sim = fl.simulate(sc, runs=20, steps=15)
        est = fl.estimate(sc, sim, ["ICI", "MSC"], filter=filt)
        ici, msc = est["ICI"], est["MSC"]
        assert np.isfinite(ici.mean).all() and np.isfinite(ici.cov).all()
        # ICI never claims more than Millman's formula, which assumes independence
        tr = np.trace(ici.cov, axis1=-2, axis2=-1)
        assert (tr >= np.trace(msc.cov, axis1=-2, axis2=-1) * (1 - 1e-9)).all()


def test_expected_mse_agrees_with_monte_carlo():
    sys = system()
    K, M = 15, 4000
    x, z = simulate(sys, K, 11, 0, M)
    plan = build_plan(sys, "ICI", K)
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
              "--arch", "ICI", "--arch", "CI", "--out-dir", tmp_path)  # fmt: skip
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "summary.json").read_text())["architectures"]["ICI"]
    assert abs(s["mse"] - s["expected"]["mse"]) <= 4 * s["stderr"]["mse"]


ONE_SENSOR = """
[scenario]
name = "one"
steps = 5
runs = 4
seed = 1
dt = 1.0

[model]
kind = "constant-velocity"
n0 = 0.16

[prior]
mean = [0.0, 1.0]
cov = [[1.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "s1"
H = [[1.0, 0.0]]
R = 1.0
"""


def test_one_sensor_is_refused_in_one_line(tmp_path):
    path = tmp_path / "one.toml"
    path.write_text(ONE_SENSOR)
    res = cli("run", path, "--arch", "ICI", "--out-dir", tmp_path / "out")
    one_line_error(res, "--arch", "ICI fuses at least 2 local filters", "1 sensor")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    sc = fl.load(path)
    with pytest.raises(fl.FusionlogError, match="ICI fuses at least 2 local filters"):
        fl.estimate(sc, fl.simulate(sc), ["ICI"])
    path.write_text(ONE_SENSOR + '\n[estimate]\narchitectures = ["ICI"]\n')
    one_line_error(cli("run", path, "--out-dir", tmp_path / "o2"), "one.toml", "ICI fuses")
