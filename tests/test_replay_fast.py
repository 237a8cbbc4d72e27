"""One replayed run without plans (`core.architectures.replay`, issue 22's replay speed): every
architecture's estimates equal the plans' (`build_plan` + `run_plan`) to what rounding can move
them by (`conditioning.sensitivity`), on `pipeline/replay_robot.toml` (irregular instants, a
covariance per message) and on a random model with correlated sensors of different sizes and
missing components; the CKF equals a Kalman filter written here (1e-9); the estimate stage and
`estimate` take this path for one run, and the plans for what it does not cover.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from cli_helpers import ok
from conditioning import assert_agree, sensitivity
from replay_helpers import gappy, head, robot_log, state_archs

from fusionlog.core.architectures import (
    build_plan,
    estimate,
    replay,
    run_plan,
)
from fusionlog.core.architectures.replay import applies, replay_estimates
from fusionlog.core.reference import reference_paths
from fusionlog.driver import plans
from fusionlog.io.mcap import McapFile

#: The first instants of the log (every sensor measures in them, the localiser a few times):
#: the plans of the whole log, five times over for the sensitivity, would take a minute.
INSTANTS = 400
RTOL = 1e-12


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """replay_robot's sensors file, filter model on its instants with its messages' R, and its
    one run."""
    return robot_log(tmp_path_factory.mktemp("fast"))


def _check_against_plans(system, z) -> None:
    archs = state_archs(system)
    fast = replay_estimates(system, archs, z)
    assert fast is not None and list(fast) == archs
    K = z.shape[1] - 1
    pattern = ~np.isnan(z[0])
    for a in archs:

        def plans(s, a=a):
            e = run_plan(build_plan(s, a, K, None if pattern.all() else pattern), z)
            return SimpleNamespace(mean=e.mean[0], cov=e.cov)

        sens = sensitivity(plans, system, ("mean", "cov"))
        mine = SimpleNamespace(mean=fast[a].mean[0], cov=fast[a].cov)
        assert fast[a].cov.shape == (K + 1, system.n, system.n)
        for f in ("mean", "cov"):
            base = getattr(plans(system), f)
            tol = sens.tolerance(f, RTOL)
            assert_agree(getattr(mine, f), base, tol, sens.unsettled, f"{a} {f}")


def test_every_architecture_equals_its_plan_on_a_recorded_log(robot) -> None:
    _, system, z = robot
    system, z = head(system, z, INSTANTS)
    assert applies(system, z)
    _check_against_plans(system, z)


def test_every_architecture_equals_its_plan_with_gaps_and_correlated_sensors() -> None:
    system, z = gappy()
    assert applies(system, z)
    _check_against_plans(system, z)


def _independent_kf(system, z):
    """A Kalman filter written out: predict over each interval (F_k, Q_k), update with the
    components present at the instant (their rows of H and R), Joseph form."""
    x, P = system.prior.mean.copy(), system.prior.cov.copy()
    H = system.linear_measurement()
    means, covs = [], []
    for k in range(z.shape[1]):
        if k:
            F, Q = system.Fs[k - 1], system.Qs[k - 1]
            x, P = F @ x, F @ P @ F.T + Q
        rows = np.flatnonzero(~np.isnan(z[0, k]))
        if len(rows):
            Hk, Rk = H[rows], system.Rs[k][np.ix_(rows, rows)]
            Kg = P @ Hk.T @ np.linalg.inv(Hk @ P @ Hk.T + Rk)
            x = x + Kg @ (z[0, k, rows] - Hk @ x)
            A = np.eye(len(x)) - Kg @ Hk
            P = A @ P @ A.T + Kg @ Rk @ Kg.T
        means.append(x)
        covs.append(P)
    return np.array(means), np.array(covs)


def test_the_ckf_of_the_whole_log_equals_an_independent_kalman_filter(robot) -> None:
    _, system, z = robot
    mean, cov = _independent_kf(system, z)
    got = replay_estimates(system, ["CKF", "FBS"], z)["CKF"]
    scale = np.abs(mean).max()
    np.testing.assert_allclose(got.mean[0], mean, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(got.cov, cov, rtol=1e-9, atol=1e-9 * np.abs(cov).max())


@pytest.mark.skipif(reference_paths(), reason="FUSIONLOG_REFERENCE_PATHS forces the plans")
def test_the_estimate_command_takes_it_for_one_run(robot, tmp_path, monkeypatch) -> None:
    """`fusionlog estimate` on a one-run log builds no plan, and writes the estimates of
    `replay_estimates` (the command reads the same system and run back)."""
    path, system, z = robot

    def no_plans(*args, **kwargs):
        raise AssertionError("a plan was built for a one-run log")

    monkeypatch.setattr(plans, "build_plan", no_plans)  # the driver's plan cache
    archs = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF:mocap", "CI", "FBS", "AVG"]
    out = tmp_path / "e.mcap"
    ok("estimate", path, "-o", out, *[x for a in archs for x in ("--arch", a)])
    fast = replay_estimates(system, archs, z)
    ef = McapFile(out)
    for a in archs:
        mean, cov = ef.read_all([f"/estimates/{a}"])[f"/estimates/{a}"]
        np.testing.assert_array_equal(mean, fast[a].mean, err_msg=a)
        np.testing.assert_array_equal(np.broadcast_to(cov, fast[a].cov.shape), fast[a].cov)
    assert ef.metadata["fusionlog.provenance"]["measurement_pattern"] != "per-run"


def test_the_reference_switch_sends_one_run_to_the_plans(robot, tmp_path, monkeypatch) -> None:
    """FUSIONLOG_REFERENCE_PATHS=1: `fusionlog estimate` of a one-run log builds its plans, and
    its estimates are those of the plans (`build_plan` + `run_plan`, bit for bit: the same
    path) and within rounding of the path without plans."""
    path, system, z = robot
    built = []

    def counted(*args, build_plan=plans.build_plan, **kwargs):
        built.append(args[1])
        return build_plan(*args, **kwargs)

    monkeypatch.setattr(plans, "build_plan", counted)
    monkeypatch.setenv("FUSIONLOG_REFERENCE_PATHS", "1")
    out = tmp_path / "e.mcap"
    ok("estimate", path, "-o", out, "--arch", "CKF", "--arch", "MSC")
    assert {"CKF", "MSC"} <= set(built)
    fast = replay_estimates(system, ["CKF", "MSC"], z)
    K = z.shape[1] - 1
    pattern = ~np.isnan(z[0])
    ef = McapFile(out)
    for a in ("CKF", "MSC"):
        mean, _ = ef.read_all([f"/estimates/{a}"])[f"/estimates/{a}"]
        plan = run_plan(plans.build_plan(system, a, K, None if pattern.all() else pattern), z)
        np.testing.assert_array_equal(mean, plan.mean, err_msg=a)
        scale = np.abs(fast[a].mean).max()
        np.testing.assert_allclose(mean, fast[a].mean, rtol=1e-9, atol=1e-9 * scale, err_msg=a)


def test_what_it_does_not_cover_goes_to_the_plans(robot) -> None:
    _, system, z = robot
    system, z = head(system, z, 60)
    # two runs, no prior, a steady recursion (time-invariant, nothing missing): the plans
    assert not applies(system, np.concatenate([z, z]))
    assert replay_estimates(dataclasses.replace(system, prior=None), ["CKF"], z) is None
    steady, zs = gappy()
    zs = np.nan_to_num(zs)
    assert not applies(steady, zs) and replay_estimates(steady, ["CKF"], zs) is None
    # `estimate` of one run takes it, of two runs the plans: the same numbers either way
    one = estimate(system, z, "MSC")
    two = estimate(system, np.concatenate([z, z]), "MSC")
    np.testing.assert_allclose(one.mean[0], two.mean[1], rtol=RTOL, atol=RTOL)


def test_numbers_beyond_the_float_range_go_to_the_plans(robot) -> None:
    """An infinite measurement: no estimate here, the plans name the step."""
    _, system, z = robot
    system, z = head(system, z, 60)
    z = z.copy()
    z[0, 30, 0] = np.inf
    assert replay_estimates(system, ["CKF", "MSC"], z) is None


def test_an_architecture_alone_gets_the_numbers_it_gets_among_all(robot) -> None:
    """The filters are stepped as one batch of whichever the architectures need: each slot's
    numbers do not depend on the others (the same operations on its own matrices; bit for bit
    here, to rounding wherever BLAS picked another kernel for another batch)."""
    _, system, z = robot
    system, z = head(system, z, 120)
    archs = state_archs(system)
    together = replay_estimates(system, archs, z)
    for a in archs:
        alone = replay_estimates(system, [a], z)[a]
        for got, want in ((alone.mean, together[a].mean), (alone.cov, together[a].cov)):
            scale = np.abs(want).max()
            np.testing.assert_allclose(got, want, rtol=RTOL, atol=RTOL * scale, err_msg=a)


def test_many_sensors_on_a_long_log_go_to_the_plans(robot, monkeypatch) -> None:
    """Every slot's masked H and R for every instant are kept: beyond a bound, the plans."""
    _, system, z = robot
    system, z = head(system, z, 60)
    assert replay_estimates(system, ["CKF"], z) is not None
    one_slot = 60 * system.m * (system.m + system.n) * 8  # H and R of 60 instants, 8 bytes each
    monkeypatch.setattr(replay, "MASKED_BYTES_AT_MOST", one_slot)
    assert replay_estimates(system, ["CKF"], z) is not None
    assert replay_estimates(system, ["CKF", "MSC"], z) is None
