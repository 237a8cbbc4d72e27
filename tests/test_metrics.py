"""Section VI metrics (eqs. 44-47): accumulator against direct formulas, block-split invariance,
chi-square band and Monte Carlo sanity, NaN exclusion."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from fusionlog.core.metrics import (
    MetricsAccumulator,
    MetricsResult,
    MetricsWorkspace,
    expected_mahalanobis_consistent,
)
from fusionlog.jsonout import dumps


def random_spd(rng: np.random.Generator, shape: tuple[int, ...], n: int) -> np.ndarray:
    a = rng.normal(size=(*shape, n, n))
    return a @ np.swapaxes(a, -1, -2) + 0.5 * np.eye(n)


def direct(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> dict[str, np.ndarray]:
    """Loop-by-loop textbook formulas on fully defined data."""
    m, s, n = x.shape
    per_run = cov.ndim == 4
    nees = np.empty((m, s))
    tr = np.empty((m, s))
    for r in range(m):
        for k in range(s):
            p = cov[r, k] if per_run else cov[k]
            e = x[r, k] - mean[r, k]
            nees[r, k] = e @ np.linalg.inv(p) @ e
            tr[r, k] = np.trace(p)
    mse_step = ((x - mean) ** 2).mean(axis=0)  # eq. 44
    dm = np.sqrt(nees)
    return {
        "mse_step": mse_step,
        "mse": mse_step.sum() / (n * s),  # eq. 45
        "nees_step": nees.mean(axis=0),
        "anees": nees.mean(),
        "dm_step": dm.mean(axis=0),
        "dm": dm.sum() / (s * m),  # eq. 47
        "trace_step": tr.mean(axis=0),
        "run_mse": ((x - mean) ** 2).mean(axis=(1, 2)),
        "run_nees": nees.mean(axis=1),
        "run_dm": dm.mean(axis=1),
    }


@pytest.mark.parametrize("per_run", [False, True])
def test_accumulator_matches_direct_formulas(per_run: bool) -> None:
    rng = np.random.default_rng(3)
    m, s, n = 17, 6, 3
    x = rng.normal(size=(m, s, n))
    mean = x + rng.normal(size=(m, s, n))
    cov = random_spd(rng, (m, s) if per_run else (s,), n)
    acc = MetricsAccumulator(s, n)
    acc.add(x, mean, cov)
    r = acc.finalize(0.95)
    d = direct(x, mean, cov)
    np.testing.assert_allclose(r.mse_step, d["mse_step"], rtol=1e-12)
    np.testing.assert_allclose(r.mse, d["mse"], rtol=1e-12)
    np.testing.assert_allclose(r.mse_per_state, d["mse_step"].mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(r.nees_step, d["nees_step"], rtol=1e-10)
    np.testing.assert_allclose(r.anees, d["anees"], rtol=1e-10)
    np.testing.assert_allclose(r.dm_step, d["dm_step"], rtol=1e-10)
    np.testing.assert_allclose(r.dm, d["dm"], rtol=1e-10)
    np.testing.assert_allclose(r.trace_step, d["trace_step"], rtol=1e-12)
    np.testing.assert_allclose(r.mean_trace, d["trace_step"].mean(), rtol=1e-12)
    # standard errors: sample std of the per-run averages / sqrt(M)
    for key, se in (
        ("run_mse", r.stderr_mse),
        ("run_nees", r.stderr_anees),
        ("run_dm", r.stderr_dm),
    ):
        np.testing.assert_allclose(se, d[key].std(ddof=1) / math.sqrt(m), rtol=1e-8)
    # per-step standard errors
    sq = (x - mean) ** 2
    np.testing.assert_allclose(r.mse_step_stderr, sq.std(axis=0, ddof=1) / math.sqrt(m), rtol=1e-8)
    assert r.count.tolist() == [m] * s
    assert r.excluded.sum() == 0


def test_chi_square_band_is_scipy_quantile() -> None:
    rng = np.random.default_rng(0)
    m, s, n = 40, 4, 2
    x = rng.normal(size=(m, s, n))
    acc = MetricsAccumulator(s, n)
    acc.add(x, x + rng.normal(size=x.shape), np.broadcast_to(np.eye(n), (s, n, n)))
    r = acc.finalize(0.99)
    np.testing.assert_allclose(r.nees_lower, stats.chi2.ppf(0.005, m * n) / m, rtol=1e-14)
    np.testing.assert_allclose(r.nees_upper, stats.chi2.ppf(0.995, m * n) / m, rtol=1e-14)
    inside = (r.nees_step >= r.nees_lower) & (r.nees_step <= r.nees_upper)
    assert r.nees_inside.tolist() == inside.tolist()
    assert r.nees_fraction_inside == pytest.approx(inside.mean())
    with pytest.raises(ValueError):
        acc.finalize(1.0)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_consistent_gaussian_errors(n: int) -> None:
    """Errors drawn with the filter's own covariance: ANEES ~ n, DM ~ E[sqrt(chi2_n)],
    the run-averaged NEES inside the 95 % band at about 95 % of the steps."""
    rng = np.random.default_rng(100 + n)
    m, s = 2000, 200
    cov = random_spd(rng, (s,), n)
    e = np.einsum("sij,msj->msi", np.linalg.cholesky(cov), rng.normal(size=(m, s, n)))
    x = rng.normal(size=(m, s, n))
    acc = MetricsAccumulator(s, n)
    for lo in range(0, m, 500):
        acc.add(x[lo : lo + 500], x[lo : lo + 500] - e[lo : lo + 500], cov)
    r = acc.finalize(0.95)
    assert abs(r.anees - n) < 4 * r.stderr_anees
    assert r.stderr_anees == pytest.approx(math.sqrt(2 * n / (s * m)), rel=0.1)
    dm_exp = expected_mahalanobis_consistent(n)
    assert abs(r.dm - dm_exp) < 4 * r.stderr_dm
    assert abs(r.nees_fraction_inside - 0.95) < 0.06
    assert abs(r.mean_trace - np.trace(cov, axis1=1, axis2=2).mean()) < 1e-9


def test_expected_mahalanobis_constants() -> None:
    assert expected_mahalanobis_consistent(2) == pytest.approx(math.sqrt(math.pi / 2), rel=1e-14)
    assert expected_mahalanobis_consistent(1) == pytest.approx(math.sqrt(2 / math.pi), rel=1e-14)
    assert expected_mahalanobis_consistent(3) == pytest.approx(2 * math.sqrt(2 / math.pi))


def test_stderr_accounts_for_correlation_across_steps() -> None:
    """Identical error at every step of a run: the standard error of the overall MSE is that of
    one step (sqrt(2/(n M)) for unit covariance), not sqrt(K+1) times smaller."""
    rng = np.random.default_rng(7)
    m, s, n = 4000, 30, 2
    e = np.repeat(rng.normal(size=(m, 1, n)), s, axis=1)
    x = np.zeros((m, s, n))
    acc = MetricsAccumulator(s, n)
    acc.add(x, x - e, np.broadcast_to(np.eye(n), (s, n, n)))
    r = acc.finalize()
    assert r.stderr_mse == pytest.approx(math.sqrt(2 / (n * m)), rel=0.1)
    naive = math.sqrt(2 / (n * m * s))
    assert r.stderr_mse > 3 * naive


def test_nan_steps_are_excluded_and_counted() -> None:
    rng = np.random.default_rng(11)
    m, s, n = 9, 5, 2
    x = rng.normal(size=(m, s, n))
    mean = x + rng.normal(size=(m, s, n))
    cov = random_spd(rng, (s,), n)
    mean[:, 0] = np.nan  # no prior: undefined at step 0 for all runs
    cov[1] = np.nan  # covariance undefined at step 1
    mean[3, 2, 1] = np.nan  # one run undefined at step 2
    acc = MetricsAccumulator(s, n)
    acc.add(x, mean, cov)
    r = acc.finalize(0.95)
    assert r.count.tolist() == [0, 0, m - 1, m, m]
    assert r.excluded.tolist() == [m, m, 1, 0, 0]
    assert np.isnan(r.mse_step[:2]).all() and np.isnan(r.nees_lower[:2]).all()
    assert not r.nees_inside[:2].any()
    keep = np.ones(m, bool)
    keep[3] = False
    d2 = direct(x[keep, 2:3], mean[keep, 2:3], cov[2:3])
    np.testing.assert_allclose(r.mse_step[2], d2["mse_step"][0], rtol=1e-12)
    np.testing.assert_allclose(r.nees_step[2], d2["nees_step"][0], rtol=1e-10)
    d34 = direct(x[:, 3:], mean[:, 3:], cov[3:])
    np.testing.assert_allclose(r.mse_step[3:], d34["mse_step"], rtol=1e-12)
    # overall values average over the defined steps only
    np.testing.assert_allclose(r.mse, np.nanmean(r.mse_step), rtol=1e-12)
    np.testing.assert_allclose(r.anees, np.nanmean(r.nees_step), rtol=1e-12)
    np.testing.assert_allclose(r.dm, np.nanmean(r.dm_step), rtol=1e-12)
    defined = r.count > 0
    assert r.nees_fraction_inside == pytest.approx(r.nees_inside[defined].mean())
    summ = r.summary()
    assert summ["excluded"] == 2 * m + 1
    assert all(math.isfinite(v) for v in (summ["mse"], summ["anees"], summ["dm"]))
    assert np.isfinite(r.nees_lower[defined]).all() and np.isfinite(r.nees_upper[defined]).all()
    # the band of step 2 uses its own number of defined runs
    assert r.nees_upper[2] == pytest.approx(stats.chi2.ppf(0.975, (m - 1) * n) / (m - 1))


def test_all_undefined_gives_nulls() -> None:
    """Undefined metrics are NaN in memory, null plus a `non_finite` note in strict JSON."""
    acc = MetricsAccumulator(3, 2)
    x = np.zeros((4, 3, 2))
    acc.add(x, np.full_like(x, np.nan), np.full((3, 2, 2), np.nan))
    summ = acc.finalize().summary()
    assert all(math.isnan(summ[k]) for k in ("mse", "anees", "dm"))
    assert summ["excluded"] == 12
    assert summ["expected"] == {"mse": None, "anees": None, "dm": None}  # no analysis: null
    doc = json.loads(dumps({"architectures": {"X": summ}}), parse_constant=_no_constant)
    assert doc["architectures"]["X"]["mse"] is None
    assert doc["non_finite"]["architectures.X.mse"] == "NaN"
    assert doc["non_finite"]["architectures.X.mse_per_state[1]"] == "NaN"
    assert "architectures.X.expected.mse" not in doc["non_finite"]


def _no_constant(name: str) -> None:
    raise AssertionError(f"{name} in strict JSON")


def test_singular_covariance_falls_back_to_pseudo_inverse() -> None:
    m, s, n = 3, 2, 2
    x = np.zeros((m, s, n))
    mean = x.copy()
    mean[:, :, 0] = -2.0  # error only in the first state
    cov = np.broadcast_to(np.diag([4.0, 0.0]), (s, n, n)).copy()
    acc = MetricsAccumulator(s, n)
    acc.add(x, mean, cov)
    r = acc.finalize()
    np.testing.assert_allclose(r.nees_step, 1.0)
    np.testing.assert_allclose(r.dm_step, 1.0)


def test_shape_errors() -> None:
    acc = MetricsAccumulator(3, 2)
    with pytest.raises(ValueError, match="truth"):
        acc.add(np.zeros((4, 2, 2)), np.zeros((4, 2, 2)), np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="mean"):
        acc.add(np.zeros((4, 3, 2)), np.zeros((5, 3, 2)), np.zeros((3, 2, 2)))
    with pytest.raises(ValueError, match="cov"):
        acc.add(np.zeros((4, 3, 2)), np.zeros((4, 3, 2)), np.zeros((4, 2, 2)))
    with pytest.raises(ValueError, match="merge"):
        acc.merge(MetricsAccumulator(4, 2))


def test_summary_layout_and_expected_values() -> None:
    rng = np.random.default_rng(5)
    m, s, n = 20, 4, 2
    x = rng.normal(size=(m, s, n))
    mean = x + rng.normal(size=x.shape)
    mean[:, 0] = np.nan
    acc = MetricsAccumulator(s, n)
    acc.add(x, mean, np.broadcast_to(np.eye(n), (s, n, n)))
    r = acc.finalize()
    exp_mse = np.arange(s * n, dtype=float).reshape(s, n)
    exp_nees = np.array([np.nan, 2.0, 2.0, 5.0])
    exp_dm = np.array([9.0, 1.0, 2.0, 3.0])
    summ = r.summary(exp_mse, exp_nees, exp_dm)
    # DESIGN.md contract keys (extra keys allowed, none renamed)
    for key in ("mse", "mse_per_state", "mean_trace", "anees", "nees_fraction_inside", "dm"):
        assert key in summ
    assert {"mse", "anees"} <= set(summ["expected"])
    # expected overall = mean over the steps where the estimate is defined (here steps 1..3)
    assert summ["expected"]["mse"] == pytest.approx(exp_mse[1:].mean())
    assert summ["expected"]["anees"] == pytest.approx(3.0)
    assert summ["expected"]["dm"] == pytest.approx(2.0)
    assert set(summ["stderr"]) == {"mse", "anees", "dm"}
    assert len(summ["mse_per_state"]) == n
    json.dumps(summ, allow_nan=False)
    assert r.summary()["expected"] == {"mse": None, "anees": None, "dm": None}
    ser = r.series(exp_mse, exp_nees, exp_dm)
    assert set(ser) == {
        "mse",
        "trace",
        "nees",
        "dm",
        "expected_mse",
        "expected_nees",
        "expected_dm",
    }
    with pytest.raises(ValueError):
        r.summary(expected_mse=np.zeros(s))


def _results_close(a: MetricsResult, b: MetricsResult) -> None:
    for name in MetricsResult.__dataclass_fields__:
        va, vb = getattr(a, name), getattr(b, name)
        if isinstance(va, np.ndarray) and va.dtype.kind in "biu":
            np.testing.assert_array_equal(va, vb, err_msg=name)
        else:
            np.testing.assert_allclose(va, vb, rtol=1e-10, atol=1e-13, err_msg=name)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    m=st.integers(1, 14),
    s=st.integers(1, 5),
    n=st.integers(1, 3),
    per_run=st.booleans(),
    cuts=st.lists(st.integers(0, 14), max_size=5),
    nan_rate=st.sampled_from([0.0, 0.2]),
)
def test_block_split_invariance(seed, m, s, n, per_run, cuts, nan_rate) -> None:
    """Any split of the runs into blocks, merged in any grouping, gives the same result."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(m, s, n))
    mean = x + rng.normal(size=(m, s, n))
    mean[rng.random((m, s)) < nan_rate] = np.nan
    cov = random_spd(rng, (m, s) if per_run else (s,), n)
    whole = MetricsAccumulator(s, n)
    whole.add(x, mean, cov)
    bounds = sorted({0, m, *[c for c in cuts if c <= m]})
    parts = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        acc = MetricsAccumulator(s, n)
        acc.add(x[lo:hi], mean[lo:hi], cov[lo:hi] if per_run else cov)
        parts.append(acc)
    # sequential adds into one accumulator
    seq = MetricsAccumulator(s, n)
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        seq.add(x[lo:hi], mean[lo:hi], cov[lo:hi] if per_run else cov)
    # merged in reverse order
    merged = MetricsAccumulator(s, n)
    for p in reversed(parts):
        merged.merge(p)
    ref = whole.finalize(0.9)
    _results_close(seq.finalize(0.9), ref)
    _results_close(merged.finalize(0.9), ref)


@pytest.mark.parametrize("per_run", [False, True])
def test_workspace_chunks_and_sharing_do_not_change_results(per_run: bool) -> None:
    """`add` works through a block in chunks of runs, in scratch arrays of a MetricsWorkspace:
    chunks of any size (here 1 to 5 runs, down to one run of more elements than a chunk holds),
    and a workspace shared by several accumulators, give the one-chunk result."""
    rng = np.random.default_rng(11)
    m, s, n = 23, 6, 2
    x = rng.normal(size=(m, s, n))
    mean = x + rng.normal(size=(m, s, n))
    mean[rng.random((m, s)) < 0.1] = np.nan
    cov = random_spd(rng, (m, s) if per_run else (s,), n)
    whole = MetricsAccumulator(s, n)
    whole.add(x, mean, cov)
    ref = whole.finalize()
    shared = MetricsWorkspace()
    for elements in (1, 12, 30, 60):
        ws = MetricsWorkspace()
        ws.CHUNK_ELEMENTS = elements
        assert ws.runs_per_chunk(s * n) == max(1, elements // (s * n))
        acc = MetricsAccumulator(s, n, workspace=ws)
        acc.add(x, mean, cov)
        _results_close(acc.finalize(), ref)
        other = MetricsAccumulator(s, n, workspace=shared)
        other.add(x[::-1], mean[::-1], cov[::-1] if per_run else cov)
        _results_close(other.finalize(), ref)
