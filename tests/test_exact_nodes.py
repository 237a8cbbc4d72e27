"""The exact analysis of per-run plans on their history nodes (`core.exact_nodes`): each run's
statistics computed once per node equal the per-run analysis of the same plan with every run's
maps gathered (`Plan.per_run_maps`), for every architecture, with and without a prior,
correlated sensors, and a truth that differs from the filters' model; and, independently of
the moments code both share, under a mismatched truth with and without a prior, each run's
statistics equal the superposition of the references written from the equations
(`references`); failures name a run."""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
import pytest
from conditioning import assert_agree, sensitivity
from conftest import random_system
from references import exact_by_superposition, no_prior_reference

from fusionlog.core.architectures import build_plan
from fusionlog.core.exact import analyse
from fusionlog.core.model import Prior
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


@dataclasses.dataclass
class _Stats:
    bias: np.ndarray  # steps first: (K+1, runs, ...)
    mse: np.ndarray
    nees: np.ndarray


SUPERPOSITION_CASES = [(a, False) for a in ("CKF", "HKF", "MSC")] + [
    (a, True) for a in ("CKF", "HKF", "MSC", "MSC-GMF", "AVG", "CI", "SKF:s2")
]


@pytest.mark.parametrize(("arch", "prior"), SUPERPOSITION_CASES)
def test_nodes_under_a_mismatched_truth_equal_superposition(arch, prior):
    """Independently of the moments code that the comparison above shares: under a truth
    with other dynamics (the true state stays in the moments) and, with a prior, another
    initial distribution, each run's exact bias, MSE matrix and NEES on history nodes equal
    those of the reference written from the equations (`references`; without a prior its
    information filters, whose map of the true state D_k changes at every step) on the
    run's own pattern, by superposition (`exact_by_superposition`), where the information is
    well conditioned (< 1e8) and rounding decides nothing (`conditioning`); ours reports no
    estimate only where it is not. An analysis holding D_0 at every step (never advancing
    D_prev) fails it without a prior."""
    rng = np.random.default_rng(zlib.crc32(f"{arch} {prior} superposition".encode()))
    dims = [2, 1] if arch == "CI" else [1, 2, 1]  # the CI reference fuses two inputs
    system = random_system(rng, 3, dims, prior=prior, correlated=True)
    K = 10
    masks = shared_histories(rng, K, system.m)
    init = system.truth_initial  # random_system's: without a prior, drawn apart from it
    if prior:
        init = Prior(init.mean + 1.0, 2.0 * init.cov)
    truth = dataclasses.replace(system, F=0.97 * system.F, initial=init)
    ref = None if prior else no_prior_reference

    def ours(s):
        plan = build_plan(s, arch, K, masks, history_nodes=True)
        assert plan.nodes is not None
        ex = analyse(plan, truth)
        return _Stats(*(np.swapaxes(getattr(ex, f), 0, 1) for f in ("bias", "mse", "nees")))

    got = ours(system)
    sens = sensitivity(ours, system, ("bias", "mse", "nees"), trials=2)
    refs = [exact_by_superposition(system, truth, arch, mk, ref) for mk in masks]
    bias, mse, P = (np.stack([r[i] for r in refs], axis=1) for i in range(3))  # (K+1, runs)
    Y = np.linalg.inv(np.where(np.isnan(P), np.eye(3), P))
    nees = np.where(np.isnan(P).any(axis=(-1, -2)), np.nan, np.einsum("krij,krji->kr", Y, mse))
    cond = np.ones((K + 1, len(masks)))
    if not prior:
        zeros = np.zeros((1, K + 1, system.m))
        cond = np.stack([no_prior_reference(system, arch, zeros, mk)[2] for mk in masks], axis=1)
    undefined = np.isnan(got.nees)
    assert (cond[undefined] > 1e8).all(), arch
    use = (cond < 1e8) & ~undefined & ~sens.unsettled[:, None]
    assert use.sum() >= 0.6 * use.size, use.sum()
    for f, want in (("bias", bias), ("mse", mse), ("nees", nees)):
        assert_agree(getattr(got, f)[use], want[use], sens.tolerance(f), None, f"{arch} {f}")


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
