"""The exact analysis of a recorded log (issue 22d).

`core.exact_replay` (one run, the truth the filters' model): every architecture's MSE matrix,
NEES, DM and reported P equal to `exact.analyse` of its plan to what rounding-level changes of
the model move the plans' numbers by (`conditioning.sensitivity`), on replay_robot's first
instants (per-message R, irregular instants) and on correlated sensors with gaps; a truth other
than the model goes to the plans; `fusionlog run` takes it. And DM of a shared plan's many
distinct statistics (a replay's instants), integrated on the per-run analysis' fitted grid:
against the fixed 1601-node grid within its truncation and, for the CKF, the chi mean.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from cli_helpers import ok
from conditioning import assert_agree, sensitivity
from replay_helpers import REPLAY, gappy, head, robot_log, state_archs
from scipy import special

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
        np.testing.assert_array_equal(ex.bias, 0.0)


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
    init = Prior(system.prior.mean + 1.0, system.prior.cov)
    assert (
        replay_expected(system, dataclasses.replace(system, initial=init), ["CKF"], present, K)
        == {}
    )
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
    assert len(seen) == 1 and sorted(seen[0]) == ["CKF", "HKF", "MSC"]
    monkeypatch.setattr(exact_replay, "truth_is_model", lambda *a: False)
    slow = run(tmp_path / "slow")
    for a in ("CKF", "MSC", "HKF"):
        for f, v in slow["architectures"][a]["expected"].items():
            assert fast["architectures"][a]["expected"][f] == pytest.approx(v, rel=1e-9), (a, f)
