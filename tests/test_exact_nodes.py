"""The exact analysis of per-run plans on their history nodes (`core.exact_nodes`): each run's
statistics computed once per node equal the per-run analysis of the same plan with every run's
maps gathered (`Plan.per_run_maps`), for every architecture, with and without a prior,
correlated sensors, and a truth that differs from the filters' model; failures name a run."""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
import pytest
from conftest import random_system

from fusionlog.core.architectures import build_plan
from fusionlog.core.exact import analyse
from fusionlog.core.names import STATE_ARCHITECTURES
from fusionlog.errors import NumericalError

FIELDS = ("mse", "bias", "P", "nees", "dm")
#: The node analysis does each run's arithmetic once per node, item for item as the per-run
#: analysis does it: the same numbers up to how a matrix product of a batch may round an item
#: (the batches differ in size).
RTOL = 1e-13


def shared_histories(rng: np.random.Generator, K: int, m: int) -> np.ndarray:
    """Twelve runs' masks (12, K+1, m) from four histories, two of them shared only up to a
    step, so that the runs group into nodes at every step."""
    base = rng.random((4, K + 1, m)) > 0.3
    masks = base[[0, 1, 2, 3, 0, 1, 2, 3, 0, 0, 1, 2]].copy()
    masks[8, K // 2 :] = ~masks[8, K // 2 :]  # run 8 leaves run 0's history half way
    masks[11, 2:] = True  # run 11 leaves run 2's after two steps
    return masks


def assert_equal_analyses(got, want) -> None:
    for f in FIELDS:
        a, b = getattr(got, f), getattr(want, f)
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=f)
        scale = max(float(np.nanmax(np.abs(b), initial=0.0)), 1e-300)
        np.testing.assert_allclose(
            np.nan_to_num(a), np.nan_to_num(b), rtol=0, atol=RTOL * scale, err_msg=f
        )


@pytest.mark.parametrize("case", ["prior", "no-prior", "correlated", "mismatch"])
@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_nodes_give_each_run_its_per_run_statistics(arch, case):
    rng = np.random.default_rng(zlib.crc32(f"{arch} {case}".encode()))
    system = random_system(
        rng, 3, [1, 2, 1], prior=case != "no-prior", correlated=case == "correlated"
    )
    K = 10
    masks = shared_histories(rng, K, system.m)
    plan = build_plan(system, arch, K, masks, history_nodes=True)
    assert plan.nodes is not None, "the runs must group into nodes for this test"
    assert len(np.unique(plan.nodes[-1])) < len(masks)
    truth = system
    if case == "mismatch":  # other dynamics: the true state stays in the moments (coupled)
        truth = dataclasses.replace(system, F=0.97 * system.F)
    assert_equal_analyses(analyse(plan, truth), analyse(plan.per_run_maps(), truth))


def test_a_failing_node_names_its_first_run():
    """A reported covariance that is not positive definite at one node: the error names the
    step and the first run of that node, as the per-run analysis names that run."""
    rng = np.random.default_rng(4)
    system = random_system(rng, 2, [1, 1, 1])
    masks = shared_histories(rng, 8, system.m)
    plan = build_plan(system, "CKF", 8, masks, history_nodes=True)
    k = 5
    node = int(plan.nodes[k][9])  # run 9's node (run 0's history up to step 8//2 = 4: shared)
    first = int(np.flatnonzero(plan.nodes[k] == node)[0])
    step = plan.steps[k]
    P = np.array(step.P, copy=True)
    P[node] = [[1.0, 2.0], [2.0, 1.0]]
    plan.steps[k] = dataclasses.replace(step, P=P)
    with pytest.raises(NumericalError, match=rf"exact analysis, step {k} of run {first}:"):
        analyse(plan, system)
    with pytest.raises(NumericalError, match=rf"exact analysis, step {k} of run {first}:"):
        analyse(plan.per_run_maps(), system)
