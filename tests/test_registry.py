"""One registered definition per architecture (issue 29): a rule registered through the public
`register` is run by every backend -- the plans and their exact analysis, per-run plans, the
one-run path and its exact analysis, the EKF/UKF lanes, the CLI's --arch with its evaluation --
and once unregistered, refused by every one."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error
from local_filters import local_kfs

from fusionlog.core.architectures import (
    Architecture,
    build_plan,
    definition,
    estimate,
    register,
    run_plan,
    unregister,
)
from fusionlog.core.architectures.replay import replay_estimates
from fusionlog.core.exact import analyse
from fusionlog.core.exact_replay import replay_expected
from fusionlog.core.model import Prior, Sensor, System, constant_velocity
from fusionlog.core.nonlinear import estimate as lanes_estimate
from fusionlog.core.simulate import simulate
from fusionlog.io.rrd import arch_color

NAME = "FIRST-LOCAL"


def first_local(P, J, criterion):
    """A dummy rule: the first local filter's estimate, its covariance read from the joint
    one (its first diagonal block)."""
    S, n = P.shape[-3], P.shape[-1]
    C = np.zeros(P.shape[:-3] + (n, S * n))
    C[..., :, :n] = np.eye(n)
    return C, J[..., :n, :n].copy()


@pytest.fixture
def registered():
    arch = register(
        Architecture(
            NAME,
            "test: the first local",
            "per-sensor",
            rule=first_local,
            joint=True,
            color=(1, 2, 3),
        )  # fmt: skip
    )
    yield arch
    unregister(NAME)


def system(filt: str | None = None) -> System:
    F1, Q1 = constant_velocity(1.0, 0.2)
    sensors = (
        Sensor("a", np.array([[1.0, 0.0]]), np.array([[2.0]])),
        Sensor("b", np.array([[1.0, 0.0], [0.0, 1.0]]), np.diag([0.5, 1.0])),
    )
    return System(F1, Q1, sensors, Prior(np.array([3.0, -1.0]), np.diag([4.0, 1.0])), filter=filt)


def first_kf(sys: System, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sensor a's Kalman filter on every run of z: means (M, K+1, n), covariances."""
    out = [local_kfs(sys, run) for run in z]
    return np.array([o[0][:, 0] for o in out]), np.array([o[1][:, 0] for o in out])


def close(a, b):
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * max(1.0, np.abs(b).max()))


def data(runs: int, steps: int, drop: float, seed: int = 2) -> tuple[System, np.ndarray]:
    """Runs of `system()`, each sensor's reading lost with probability `drop`."""
    sys = system()
    _, z = simulate(sys, steps, seed, 0, runs)
    lost = np.random.default_rng(seed).random(z.shape[:2] + (len(sys.sensors),)) < drop
    for j, sl in enumerate(sys.sensor_slices):
        z[:, :, sl][lost[:, :, j]] = np.nan
    return sys, z


def test_plans_and_exact_analysis_take_it(registered):
    sys, z = data(3, 12, 0.0)
    e = estimate(sys, z, NAME)
    x, P = first_kf(sys, z)
    close(e.mean, x)
    close(np.broadcast_to(e.cov, P.shape), P)
    ex = analyse(build_plan(sys, NAME, 12), sys)  # a Kalman filter's error covariance is its P
    close(ex.mse, P[0])


def test_per_run_plans_take_it(registered):
    sys, z = data(6, 10, 0.3)
    plan = build_plan(sys, NAME, 10, ~np.isnan(z))
    x, P = first_kf(sys, z)
    e = run_plan(plan, z)
    close(e.mean, x)
    close(e.cov, P)
    close(analyse(plan, sys).mse, P)


def test_the_one_run_path_and_its_exact_analysis_take_it(registered):
    sys, z = data(1, 25, 0.3, seed=5)
    fast = replay_estimates(sys, [NAME], z)
    assert fast is not None
    x, P = first_kf(sys, z)
    close(fast[NAME].mean, x)
    close(fast[NAME].cov, P[0])
    ex = replay_expected(sys, sys, [NAME], ~np.isnan(z[0]), 25)
    close(ex[NAME].mse, P[0])


@pytest.mark.parametrize("filt", ["EKF", "UKF"])
def test_the_ekf_and_ukf_lanes_take_it(registered, filt):
    sys, z = data(4, 8, 0.2)
    tr = lanes_estimate(system(filt), NAME, z, np.arange(9.0))
    x, P = first_kf(sys, z)
    close(tr.mean, x)
    close(tr.cov, P)


def test_the_cli_takes_it_with_its_evaluation_and_colour(registered, tmp_path):
    ok("run", "pipeline/heterogeneous.toml", "--runs", "60", "--steps", "10", "--arch", NAME,
       "--arch", "CKF", "--out-dir", tmp_path)  # fmt: skip
    s = json.loads((tmp_path / "summary.json").read_text())["architectures"][NAME]
    assert abs(s["mse"] - s["expected"]["mse"]) <= 4 * s["stderr"]["mse"]
    assert arch_color(NAME) == (1, 2, 3)
    assert definition(NAME) is registered


def test_an_unregistered_name_is_refused_everywhere(tmp_path):
    sys, z = data(2, 6, 0.0)
    for run in (
        lambda: estimate(sys, z, NAME),
        lambda: build_plan(sys, NAME, 6),
        lambda: lanes_estimate(system("EKF"), NAME, z, np.arange(7.0)),
    ):
        with pytest.raises(ValueError, match=f"unknown architecture '{NAME}'"):
            run()
    assert replay_estimates(sys, [NAME], z[:1]) is None  # left to the plans, which refuse it
    res = cli("run", "pipeline/heterogeneous.toml", "--runs", "5", "--arch", NAME,
              "--out-dir", tmp_path)  # fmt: skip
    one_line_error(res, "--arch", f"unknown architecture '{NAME}'")


def test_a_name_is_registered_once(registered):
    with pytest.raises(ValueError, match="registered already"):
        register(registered)
    with pytest.raises(ValueError, match="a rule exactly for per-sensor locals"):
        Architecture("X", "no rule", "per-sensor")
