"""Truth-free consistency (core.nis) against closed forms on simulated data.

A consistent filter's NIS is chi-square with dim(nu) degrees of freedom (mean = dof), and its
normalised innovations are white; an over-confident architecture (MSC: Millman's formula
ignoring the correlation of the local errors) predicts with a covariance that is too small,
so the innovations of its fused prediction are too large for it.
"""

from __future__ import annotations

import numpy as np

from fusionlog.core.architectures import estimate
from fusionlog.core.model import ajgl2009
from fusionlog.core.nis import innovations, whiteness
from fusionlog.core.simulate import simulate


def _mean_se(a: np.ndarray) -> tuple[float, float]:
    a = a[np.isfinite(a)]
    return float(a.mean()), float(a.std(ddof=1) / np.sqrt(a.size))


def test_ckf_nis_has_mean_dof_and_white_innovations() -> None:
    system = ajgl2009()
    _, z = simulate(system, 20, 5, 0, 4000)
    est = estimate(system, z, "CKF")
    inn = innovations(system, est.mean, est.cov, z, np.arange(system.m))
    assert (inn.dof == 3).all()
    mean, se = _mean_se(inn.nis)
    assert abs(mean - 3.0) < 4 * se, (mean, se)
    # per step too: the average over runs of chi-square(3)
    per_step = np.nanmean(inn.nis, axis=0)
    assert (np.abs(per_step - 3.0) < 4 * np.sqrt(6.0 / 4000)).all()
    w = whiteness(inn.normalised[:200], lags=5)
    assert w["fraction_inside"] > 0.85, w


def test_missing_components_reduce_the_degrees_of_freedom() -> None:
    system = ajgl2009()
    _, z = simulate(system, 20, 6, 0, 3000)
    z[np.random.default_rng(1).random(z.shape) < 0.3] = np.nan
    est = estimate(system, z, "CKF")
    inn = innovations(system, est.mean, est.cov, z, np.arange(system.m))
    np.testing.assert_array_equal(inn.dof, (~np.isnan(z)).sum(axis=-1))
    some = inn.dof > 0
    assert np.isnan(inn.nis[~some]).all()
    ratio = inn.nis[some] / inn.dof[some]
    mean, se = _mean_se(ratio)
    assert abs(mean - 1.0) < 4 * se, (mean, se)


def test_msc_fused_prediction_is_over_confident() -> None:
    """Each sensor's innovation against the fused prediction: about dof = 1 for MSC-GMF
    (consistent), far above it for MSC (its claimed covariance is too small)."""
    system = ajgl2009()
    _, z = simulate(system, 20, 7, 0, 3000)
    means = {}
    for arch in ("MSC-GMF", "MSC"):
        est = estimate(system, z, arch)
        inn = innovations(system, est.mean, est.cov, z, np.array([0]))
        means[arch] = _mean_se(inn.nis[:, 5:])  # after the first steps
    gmf, msc = means["MSC-GMF"], means["MSC"]
    assert abs(gmf[0] - 1.0) < 4 * gmf[1], gmf
    assert msc[0] > 1.0 + 20 * msc[1], msc
