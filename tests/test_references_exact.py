"""The exact analysis (`core.exact.analyse`) under model mismatch (F, Q, R, cross-covariances,
initial state), correlated noise and lost measurements, against the exact error statistics of
the references (`references`), obtained by superposition: every reference is affine in
(x0, w, v) with gains that do not depend on the data, so its error is c + A xi with
xi ~ N(0, I) and E[e e^T] = c c^T + A A^T, read off by running the reference once on the means
and once per unit noise direction; also each run of a per-run plan.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conditioning import assert_agree, sensitivity
from references import K, exact_by_superposition, mask_of, on_irregular_instants, system_of

from fusionlog.core.architectures import build_plan
from fusionlog.core.exact import analyse
from fusionlog.core.model import Prior, System

# --------------------------------------------------------------------------------------------
# The exact analysis against the references' exact error statistics (superposition)


def _mismatched(filt: System, seed: int) -> System:
    """A truth other than the filters' model: other F, Q, R (cross-covariances too), and an
    initial state distribution other than their prior."""
    rng = np.random.default_rng(seed)
    n = filt.n
    if filt.Fs is not None:  # irregular instants: other transitions and process noises
        filt = dataclasses.replace(
            filt, Fs=filt.Fs + 0.05 * rng.standard_normal(filt.Fs.shape), Qs=3.0 * filt.Qs
        )
    sensors = tuple(dataclasses.replace(s, R=1.7 * s.R) for s in filt.sensors)
    cross = {key: 1.7 * 0.8 * v for key, v in filt.cross_R.items()}
    initial = Prior(filt.prior.mean + rng.standard_normal(n), 2.0 * filt.prior.cov)
    return dataclasses.replace(
        filt,
        F=filt.F + 0.05 * rng.standard_normal((n, n)),
        Q=3.0 * filt.Q,
        sensors=sensors,
        cross_R=cross,
        initial=initial,
    )


@dataclasses.dataclass
class Stats:
    bias: np.ndarray
    mse: np.ndarray
    nees: np.ndarray


EXACT_CASES = [
    ("CKF", [1, 2, 1], True),
    ("FBS", [1, 2, 1], True),
    ("MSC", [1, 2, 1], True),
    ("MSC-GMF", [1, 2, 1], True),
    ("MSC-GMF", [2, 2], False),
    ("AVG", [1, 2, 1], True),
    ("CI", [2, 1], True),
    ("HKF", [1, 2, 1], True),
    ("HKF", [2, 1], False),
]


@pytest.mark.parametrize(("arch", "dims", "lost"), EXACT_CASES)
@pytest.mark.parametrize("irregular", [False, True])
def test_exact_analysis_equals_superposition_under_mismatch(arch, dims, lost, irregular) -> None:
    """`analyse` of the plan with the true model = the reference's exact bias, E[e e^T] and
    NEES tr(P^-1 E[e e^T]), with a truth other than the filters' model and correlated noise,
    on regular and irregular instants."""
    filt = system_of(41 + len(dims), dims)
    if irregular:
        filt = on_irregular_instants(filt, 4)
    truth = _mismatched(filt, 3)
    mask = mask_of(filt, 9) if lost else np.ones((K + 1, filt.m), bool)
    bias, mse, P = exact_by_superposition(filt, truth, arch, mask)
    nees = np.einsum("kij,kji->k", np.linalg.inv(P), mse)

    def compute(system: System) -> Stats:
        ex = analyse(build_plan(system, arch, K, present=mask), truth)
        return Stats(ex.bias, ex.mse, ex.nees)

    got = compute(filt)
    sens = sensitivity(compute, filt, ("bias", "mse", "nees"))
    assert_agree(got.bias, bias, sens.tolerance("bias"), sens.unsettled, f"{arch} bias")
    assert_agree(got.mse, mse, sens.tolerance("mse"), sens.unsettled, f"{arch} mse")
    assert_agree(got.nees, nees, sens.tolerance("nees"), sens.unsettled, f"{arch} nees")


@pytest.mark.parametrize("arch", ["CKF", "HKF", "MSC", "MSC-GMF", "CI", "AVG", "FBS"])
def test_per_run_exact_analysis_equals_superposition_of_each_run(arch: str) -> None:
    """With a pattern per run (dropouts), the per-run plan's analysis of run r equals the
    superposition of the reference on run r's own pattern (the conditional expected values
    summary.json averages)."""
    dims = [2, 1] if arch == "CI" else [1, 2, 1]
    filt = system_of(71, dims)
    truth = _mismatched(filt, 5)
    masks = np.stack([mask_of(filt, 20 + r) for r in range(3)])
    ex = analyse(build_plan(filt, arch, K, present=masks), truth)
    for r in range(3):
        bias, mse, _ = exact_by_superposition(filt, truth, arch, masks[r])

        def compute(system: System, r=r) -> Stats:
            e = analyse(build_plan(system, arch, K, present=masks[r]), truth)
            return Stats(e.bias, e.mse, e.nees)

        sens = sensitivity(compute, filt, ("bias", "mse"), trials=2)
        assert_agree(ex.bias[r], bias, sens.tolerance("bias"), sens.unsettled, f"{arch} {r}")
        assert_agree(ex.mse[r], mse, sens.tolerance("mse"), sens.unsettled, f"{arch} {r}")
