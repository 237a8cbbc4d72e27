"""The exact analysis of a recorded log (issue 22d): every instant of a replay is a distinct
statistic, which the analysis integrates for DM (eq. 46) on the fitted grid of the per-run
analysis rather than the shared plans' fixed 1601-node grid. Both against the fixed grid
(within its truncation, `test_exact_per_run.test_many_agrees_with_the_fixed_grid`) and, for a
filter consistent under the model, against the chi mean.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from scipy import special

from fusionlog.core.architectures import STATE_ARCHITECTURES, build_plan
from fusionlog.core.exact import FIXED_GRID_ITEMS, analyse, expected_sqrt_quadratic
from fusionlog.io.mcap import McapFile
from fusionlog.stages.common import scenario_from_file
from fusionlog.stages.noise import with_message_covariances

ROOT = Path(__file__).resolve().parents[1]
REPLAY = ROOT / "pipeline" / "replay_robot.toml"
#: Enough instants for the fitted grid (more distinct statistics than FIXED_GRID_ITEMS).
INSTANTS = 400


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """replay_robot's filter model on its first instants with its messages' R, and the mask
    of its readings."""
    path = tmp_path_factory.mktemp("exact") / "s.mcap"
    ok("import", REPLAY, "-o", path)
    mf = McapFile(path)
    system = with_message_covariances(scenario_from_file(mf).system.on_times(mf.times()), mf)
    topics = [f"/sensors/{s.name}" for s in system.sensors]
    z = np.concatenate([mf.read_all([t])[t] for t in topics], axis=-1)[0, :INSTANTS]
    system = _head(system, INSTANTS)
    return system, ~np.isnan(z)


def _head(system, K1: int):
    """The model cut to its first K1 instants."""
    cut = dataclasses.replace(system, Fs=system.Fs[: K1 - 1], Qs=system.Qs[: K1 - 1])
    return dataclasses.replace(cut, Rs=system.Rs[:K1])


def _archs(system) -> list[str]:
    return [a for a in STATE_ARCHITECTURES if a != "SKF"] + [
        f"SKF:{s.name}" for s in system.sensors
    ]


def test_every_architecture_s_dm_on_a_recorded_log_is_the_fixed_grid_s(robot) -> None:
    """DM of each instant against the fixed grid on the same statistics: they agree within
    the fixed grid's truncation at t = e^-60, 2 E[q] e^-30 / (2 sqrt(pi)) (1e-12 relative and
    6e-14 of the expected NEES, as for the per-run routines)."""
    system, present = robot
    for a in _archs(system):
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
