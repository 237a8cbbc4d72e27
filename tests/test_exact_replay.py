"""The exact analysis of a recorded log (issue 22d).

`core.exact_replay` (one run, the truth the filters' model): every architecture's MSE matrix,
NEES, DM and reported P equal to `exact.analyse` of its plan to what rounding-level changes of
the model move the plans' numbers by (`conditioning.sensitivity`), on replay_robot's first
instants (per-message R, irregular instants) and on correlated sensors with gaps; a truth other
than the model goes to the plans; `fusionlog run` takes it. And DM of a shared plan's many
distinct statistics (a replay's instants), integrated on the per-run analysis' fitted grid:
against the fixed 1601-node grid within its truncation and, for the CKF, the chi mean.
Independently of the plans: every architecture against superposition of the references
written from the equations (`references`), and a filter prior other than the truth's initial
distribution through the Python API against the true error covariance propagated here.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from cli_helpers import ok
from conditioning import assert_agree, sensitivity
from references import exact_by_superposition
from replay_helpers import REPLAY, gappy, head, robot_log, state_archs
from scipy import special

import fusionlog as fl
from fusionlog.core.architectures import build_plan
from fusionlog.core.exact import FIXED_GRID_ITEMS, analyse, expected_sqrt_quadratic
from fusionlog.core.exact_replay import replay_expected
from fusionlog.core.model import Prior
from fusionlog.core.reference import reference_paths

#: Enough instants for the fitted grid (more distinct statistics than FIXED_GRID_ITEMS).
INSTANTS = 400
RTOL = 1e-12


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """replay_robot's filter model on its first instants with its messages' R, and the mask
    of its readings."""
    _, system, z = robot_log(tmp_path_factory.mktemp("exact"))
    system, z = head(system, z, INSTANTS)
    return system, ~np.isnan(z[0])


def test_every_architecture_s_dm_on_a_recorded_log_is_the_fixed_grid_s(robot) -> None:
    """DM of each instant against the fixed grid on the same statistics: they agree within
    the fixed grid's truncation at t = e^-60, 2 E[q] e^-30 / (2 sqrt(pi)) (1e-12 relative and
    6e-14 of the expected NEES, as for the per-run routines)."""
    system, present = robot
    for a in state_archs(system):
        ex = analyse(build_plan(system, a, INSTANTS - 1, present), system)
        ok_ = ex.defined
        assert ok_.sum() > FIXED_GRID_ITEMS, a
        cov = ex.mse - ex.bias[..., :, None] * ex.bias[..., None, :]
        want = expected_sqrt_quadratic(ex.P[ok_], ex.bias[ok_], cov[ok_])
        tol = 1e-12 * want + 6e-14 * (ex.nees[ok_] + 1.0)
        assert (np.abs(ex.dm[ok_] - want) <= tol).all(), a


def test_a_consistent_filter_s_dm_is_the_chi_mean(robot) -> None:
    """The CKF is the model's optimal filter: its error covariance is its P, so its DM is the
    chi mean sqrt(2) G((n+1)/2) / G(n/2) at every instant, to the rounding of E[e e^T] = P
    (the NEES, n, tells it) and the fitted grid's 1e-15 (ten times over). The fixed grid is
    1.4e-13 below it here (its truncation at t = e^-60)."""
    system, present = robot
    ex = analyse(build_plan(system, "CKF", INSTANTS - 1, present), system)
    n = system.n
    chi_mean = np.sqrt(2) * special.gamma((n + 1) / 2) / special.gamma(n / 2)
    off = np.abs(ex.nees - n).max() / n  # how far rounding moved E[e e^T] from P
    np.testing.assert_allclose(ex.dm, chi_mean, rtol=off + 1e-14)


def _gappy():
    """`replay_helpers.gappy` as the mask of its readings."""
    system, z = gappy()
    return system, ~np.isnan(z[0])


def _check_against_plans(system, present) -> None:
    """Every architecture (`replay_expected` covers them all here) against `analyse` of its
    plan, to what rounding-level changes of the model move the plans' numbers by."""
    K = len(present) - 1
    archs = state_archs(system)
    fast = replay_expected(system, system, archs, present, K)
    assert sorted(fast) == sorted(archs)
    for a, ex in fast.items():

        def plans(s, a=a):
            e = analyse(build_plan(s, a, K, present), s)
            return SimpleNamespace(mse=e.mse, bias=e.bias, nees=e.nees, dm=e.dm, P=e.P)

        sens = sensitivity(plans, system, ("mse", "nees", "dm", "P"))
        base = plans(system)
        for f in ("mse", "nees", "dm", "P"):
            tol = sens.tolerance(f, RTOL)
            assert_agree(getattr(ex, f), getattr(base, f), tol, sens.unsettled, f"{a} {f}")
        # the plans' error means are zero to rounding of the prior's mean (the truth's)
        scale = np.abs(system.prior.mean).max() + np.sqrt(np.abs(base.mse).max())
        assert np.abs(base.bias).max() <= 1e-12 * scale


def test_every_architecture_equals_the_plans_analysis_on_a_recorded_log(robot) -> None:
    system, present = robot
    _check_against_plans(system, present)


def test_every_architecture_equals_the_plans_analysis_with_gaps() -> None:
    system, present = _gappy()
    _check_against_plans(system, present)


def test_a_truth_other_than_the_model_goes_to_the_plans(robot) -> None:
    """A mismatched truth (another R, or another initial distribution) needs the plans'
    joint moments: nothing here."""
    system, present = robot
    K = len(present) - 1
    louder = dataclasses.replace(system, Rs=system.Rs * 2.0)
    assert replay_expected(system, louder, ["CKF"], present, K) == {}
    for init in (
        Prior(system.prior.mean + 1.0, system.prior.cov),
        Prior(system.prior.mean, 2.0 * system.prior.cov),
    ):
        truth = dataclasses.replace(system, initial=init)
        assert replay_expected(system, truth, ["CKF"], present, K) == {}
    assert "CKF" in replay_expected(system, system, ["CKF"], present, K)


@pytest.mark.skipif(reference_paths(), reason="FUSIONLOG_REFERENCE_PATHS forces the plans")
def test_the_evaluate_stage_takes_it_for_one_run(tmp_path, monkeypatch) -> None:
    """`fusionlog run` of a recorded log: the same summary with the plans' analysis alone
    (within rounding: the goldens' relative 1e-9 is far above it), and none of the covered
    architectures' plans built."""
    import json

    from fusionlog.core import exact_replay

    def run(out):
        ok("run", REPLAY, "--out-dir", out, "--arch", "CKF", "--arch", "MSC", "--arch", "HKF")
        return json.loads((out / "summary.json").read_text())

    seen = []

    def recorded(*args, replay_expected=exact_replay.replay_expected):
        seen.append(replay_expected(*args))
        return seen[-1]

    monkeypatch.setattr(exact_replay, "replay_expected", recorded)
    fast = run(tmp_path / "fast")
    # what the route returned, should it refuse on some machine (a Prescott run was reported
    # to fail here once and could not be reproduced: the quantities are conditioned ~1e-16)
    assert len(seen) == 1 and sorted(seen[0]) == ["CKF", "HKF", "MSC"], [sorted(e) for e in seen]
    monkeypatch.setattr(exact_replay, "truth_is_model", lambda *a: False)
    slow = run(tmp_path / "slow")
    for a in ("CKF", "MSC", "HKF"):
        for f, v in slow["architectures"][a]["expected"].items():
            assert fast["architectures"][a]["expected"][f] == pytest.approx(v, rel=1e-9), (a, f)


def test_every_architecture_equals_superposition_of_its_equations() -> None:
    """Independently of the plans: each architecture's exact bias, MSE matrix and NEES from
    `replay_expected` on the correlated sensors with gaps equal those of the reference written
    from the paper's equations (`references`), by superposition (the error is affine in the
    noises: one run at the means, one per unit noise direction). The bias is zero because the
    truth is the model: the reference's is zero to the rounding of the states it subtracts
    (1e-12 of the prior's mean plus the error's standard deviation). CI is left out: its
    reference fuses two inputs, these are three."""
    system, present = _gappy()
    K = len(present) - 1
    archs = [a for a in state_archs(system) if a != "CI"]
    fast = replay_expected(system, system, archs, present, K)
    assert sorted(fast) == sorted(archs)
    for a in archs:
        bias, mse, P = exact_by_superposition(system, system, a, present)
        nees = np.einsum("kij,kji->k", np.linalg.inv(P), mse)

        def ours(s, a=a):
            e = replay_expected(s, s, [a], present, K)[a]
            return SimpleNamespace(mse=e.mse, nees=e.nees, P=e.P)

        sens = sensitivity(ours, system, ("mse", "nees", "P"), trials=2)
        ex = fast[a]
        for f, want in (("mse", mse), ("nees", nees), ("P", P)):
            tol = sens.tolerance(f, RTOL)
            assert_agree(getattr(ex, f), want, tol, sens.unsettled, f"{a} {f}")
        scale = np.abs(system.prior.mean).max() + np.sqrt(np.abs(mse).max())
        assert np.abs(ex.bias - bias).max() <= 1e-12 * scale, a


def _cv(dt: float, qc: float) -> tuple[np.ndarray, np.ndarray]:
    """The constant-velocity model on [x, vx, y, vy] over dt: F and Q in closed form."""
    F1 = np.array([[1.0, dt], [0.0, 1.0]])
    Q1 = qc * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1)


def test_a_filter_prior_other_than_the_truth_s_initial_covariance(tmp_path) -> None:
    """replay_robot estimated with a model (as `estimate --model`) whose prior covariance
    differs from the replay's [prior] (the truth's initial distribution): the expected MSE of
    the CKF and of SKF:pose at every instant equals the true error covariance propagated here
    with the filter's own gains (from its P), C+ = A C- A^T + K R K^T, C- = F C+ F^T + Q,
    started from the truth's covariance (the identity), on the recorded instants (F, Q in
    closed form, Qc = n0 dt = 0.02) with each pose message's own R. The filter's P taken for
    it (the truth seen as the model when only the initial covariance differs) is up to 8
    times off. Both propagations are contractions of well-conditioned matrices: 1e-9
    relative is far above their rounding."""
    text = REPLAY.read_text().replace('source = "data/', f'source = "{REPLAY.parent}/data/')
    p_filter = np.diag([4.0, 0.25, 9.0, 0.5])
    p_filter[0, 2] = p_filter[2, 0] = 1.5
    rows = ", ".join("[" + ", ".join(repr(float(v)) for v in row) + "]" for row in p_filter)
    start = text.index("cov = [[1.0,")
    end = text.index("\n", start)
    model_path = tmp_path / "model.toml"
    model_path.write_text(text[:start] + f"cov = [{rows}]" + text[end:])
    truth_sc, model_sc = fl.load(REPLAY), fl.load(model_path)
    np.testing.assert_array_equal(truth_sc.system.prior.cov, np.eye(4))
    sim = fl.simulate(truth_sc)
    archs = {"CKF": ["odom", "pose", "mocap"], "SKF:pose": ["pose"]}
    ev = fl.evaluate(model_sc, sim, fl.estimate(model_sc, sim, list(archs)))
    R_of = {s.name: s.R for s in truth_sc.system.sensors}
    for arch, names in archs.items():
        P, C = p_filter.copy(), np.eye(4)
        want = np.empty((len(sim.times), 4))
        for k in range(len(sim.times)):
            if k:
                F, Q = _cv(sim.times[k] - sim.times[k - 1], 0.02)
                P, C = F @ P @ F.T + Q, F @ C @ F.T + Q
            for name in names:
                z = sim.measurements[name][0, k]
                if np.isnan(z).all():
                    continue
                H = np.zeros((2, 4))
                H[0, 1 if name == "odom" else 0] = H[1, 3 if name == "odom" else 2] = 1.0
                R = sim.covariances[name][k] if name in sim.covariances else R_of[name]
                assert np.isfinite(R).all(), (name, k)
                G = np.linalg.solve(H @ P @ H.T + R, H @ P).T
                A = np.eye(4) - G @ H
                P, C = A @ P @ A.T + G @ R @ G.T, A @ C @ A.T + G @ R @ G.T
            want[k] = np.diag(C)
        got = ev.series[arch]["expected_mse"]
        np.testing.assert_allclose(got, want, rtol=1e-9, err_msg=arch)
        assert np.abs(np.diag(P) / want[-1] - 1).max() < 1e-3  # the prior forgotten by the end
