"""The identity kind's core (fusionlog.core.identity): model, simulation, fusion, metrics.

Pure numpy, no files: the aircraft system of pipeline/aircraft_identity.toml built directly,
simulated through the chunked random streams shared with the state kind, fused with BAYES and
DS, and scored, each checked against an independent computation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusionlog.core.identity.fusion import (
    bayes_posteriors,
    columns,
    decision_weights,
    dims,
    ds_columns,
    ds_combine,
    estimate,
    report_indices,
)
from fusionlog.core.identity.metrics import IdentityMetrics, MetricSums, PerClassSums
from fusionlog.core.identity.model import (
    ARCHITECTURES,
    UNKNOWN,
    IdentitySensor,
    IdentitySystem,
)
from fusionlog.core.identity.simulate import simulate
from fusionlog.core.simulate import chunk_runs, chunked

CLASSES = ("Learjet", "Falcon", "Caravan")
FAST, FRAME = 0b011, 0b111


def aircraft() -> IdentitySystem:
    """The system of pipeline/aircraft_identity.toml (bit j of a subset = CLASSES[j])."""
    sensors = (
        IdentitySensor(
            "radar",
            ("fast", "Caravan", UNKNOWN),
            (FAST, 0b100, FRAME),
            np.array([[0.75, 0.05, 0.20], [0.75, 0.05, 0.20], [0.10, 0.70, 0.20]]),
            0.8,
        ),
        IdentitySensor(
            "esm",
            ("Learjet", "Falcon", "Caravan", UNKNOWN),
            (0b001, 0b010, 0b100, FRAME),
            np.array(
                [[0.50, 0.20, 0.05, 0.25], [0.20, 0.50, 0.05, 0.25], [0.05, 0.05, 0.65, 0.25]]
            ),
            0.6,
        ),
        IdentitySensor(
            "imager",
            ("Learjet", "Falcon", "Caravan", "fast"),
            (0b001, 0b010, 0b100, FAST),
            np.array(
                [[0.45, 0.15, 0.05, 0.35], [0.15, 0.45, 0.05, 0.35], [0.05, 0.10, 0.80, 0.05]]
            ),
            0.7,
        ),
    )
    return IdentitySystem(
        CLASSES, np.array([0.5, 0.4, 0.1]), {"fast": ("Learjet", "Falcon")}, sensors
    )


# ------------------------------------------------------------------------------------------
# model
# ------------------------------------------------------------------------------------------


def test_system_to_dict_and_tables() -> None:
    system = aircraft()
    assert system.n == 3 and ARCHITECTURES == ("BAYES", "DS")
    d = system.to_dict()
    assert list(d) == ["classes", "prior", "sets", "sensors"]
    assert d["sets"] == {"fast": ["Learjet", "Falcon"]}
    assert d["sensors"][0]["subsets"] == [["Learjet", "Falcon"], ["Caravan"], list(CLASSES)]
    radar = system.sensors[0]
    table = radar.mass_table(3)  # rows: fast, Caravan, unknown, no report
    np.testing.assert_allclose(table.sum(-1), 1.0)
    assert (table[0, FAST], table[0, FRAME]) == pytest.approx((0.8, 0.2))
    assert table[2, FRAME] == table[3, FRAME] == 1.0  # "unknown" and no report: vacuous
    np.testing.assert_array_equal(radar.likelihood()[:3], radar.confusion.T)
    np.testing.assert_array_equal(radar.likelihood()[3], 1.0)


def test_system_rejects_inconsistent_shapes() -> None:
    s = aircraft()
    with pytest.raises(ValueError, match="prior"):
        IdentitySystem(CLASSES, np.ones(2) / 2, {}, s.sensors)
    bad = IdentitySensor("x", ("Learjet",), (1,), np.ones((3, 2)) / 2, 0.5)
    with pytest.raises(ValueError, match="sensor 'x'"):
        IdentitySystem(CLASSES, s.prior, {}, (bad,))


# ------------------------------------------------------------------------------------------
# simulation: the chunked random streams
# ------------------------------------------------------------------------------------------


def test_simulate_draws_classes_then_reports_from_one_stream_per_chunk() -> None:
    """An independent re-implementation pins the random numbers: chunk c's stream is child c
    of the seed's SeedSequence; it draws one uniform per run (the class), then one per (run,
    step, sensor) (the reports), each turned into an index by the inverse CDF."""
    system, steps, seed = aircraft(), 3000, 7
    size = chunk_runs(steps)  # 87 runs per chunk at this horizon
    truth, reports = simulate(system, steps, seed, size - 5, 10)  # straddles chunks 0 and 1
    want_t, want_r = [], []
    for c in (0, 1):
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(c,)))
        u0 = rng.random(size)
        u = rng.random((size, steps + 1, 3))
        t = np.searchsorted(np.cumsum(system.prior), u0, side="right")
        r = np.empty((size, steps + 1, 3), dtype=np.int64)
        for s, sensor in enumerate(system.sensors):
            cdf = np.cumsum(sensor.confusion[t], axis=-1)  # (size, reports)
            for b in range(size):
                r[b, :, s] = np.searchsorted(cdf[b], u[b, :, s], side="right")
        want_t.append(t)
        want_r.append(r)
    np.testing.assert_array_equal(truth, np.concatenate(want_t)[size - 5 : size + 5])
    np.testing.assert_array_equal(reports, np.concatenate(want_r)[size - 5 : size + 5])


def test_simulate_does_not_depend_on_the_blocks() -> None:
    system, steps = aircraft(), 5
    truth, reports = simulate(system, steps, 3, 0, 2500)  # chunks of 1024 runs
    for off, runs in ((0, 1), (1000, 100), (2047, 2), (1500, 1000)):
        t, r = simulate(system, steps, 3, off, runs)
        np.testing.assert_array_equal(t, truth[off : off + runs])
        np.testing.assert_array_equal(r, reports[off : off + runs])
    # the classes follow the prior; the reports follow the confusion rows
    np.testing.assert_allclose(np.bincount(truth, minlength=3) / 2500, system.prior, atol=0.03)
    radar = reports[truth == 2][..., 0].ravel()
    np.testing.assert_allclose(np.bincount(radar) / radar.size, [0.1, 0.7, 0.2], atol=0.03)


def test_chunked_slices_the_chunk_streams() -> None:
    """chunked is what both kinds share: runs [a, b) whatever the split, one stream a chunk."""
    steps = (1 << 18) // 8 - 1  # 8 runs per chunk

    def draw(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
        return rng.random(size), rng.standard_normal((size, 2))

    whole = chunked(draw, steps, 5, 0, 40)
    assert [a.shape for a in whole] == [(40,), (40, 2)]
    parts = [chunked(draw, steps, 5, off, 7) for off in range(3, 38, 7)]
    for i in range(2):
        np.testing.assert_array_equal(np.concatenate([p[i] for p in parts]), whole[i][3:38])
    third = draw(np.random.default_rng(np.random.SeedSequence(5, spawn_key=(2,))), 8)
    np.testing.assert_array_equal(whole[0][16:24], third[0])
    with pytest.raises(ValueError, match="range of runs"):
        chunked(draw, steps, 5, 0, 0)


# ------------------------------------------------------------------------------------------
# fusion
# ------------------------------------------------------------------------------------------


def test_estimate_layout_and_bayes_against_a_direct_product() -> None:
    system = aircraft()
    _, reports = simulate(system, 6, 1, 0, 50)
    assert dims(3) == {"BAYES": 3, "DS": 8}
    assert columns(CLASSES, ["DS", "BAYES"]) == {
        "DS": ds_columns(CLASSES),
        "BAYES": ["P(Learjet)", "P(Falcon)", "P(Caravan)"],
    }
    est = {a: estimate(system, reports, a) for a in ARCHITECTURES}
    for a, v in est.items():
        assert v.shape == (50, 7, dims(3)[a])
    np.testing.assert_array_equal(
        est["BAYES"], bayes_posteriors(reports, system.sensors, system.prior)
    )
    bel, pl, k, acc = ds_combine(reports, system.sensors, 3)
    np.testing.assert_array_equal(
        est["DS"], np.concatenate([bel, pl, k[..., None], acc[..., None]], -1)
    )
    for b in range(5):
        p = system.prior.copy()
        for t in range(7):
            for s, sensor in enumerate(system.sensors):
                p = p * sensor.confusion[:, reports[b, t, s]]
            np.testing.assert_allclose(est["BAYES"][b, t], p / p.sum(), rtol=1e-12)
    with pytest.raises(ValueError, match="unknown identity architecture 'CKF'"):
        estimate(system, reports, "CKF")


def test_bayes_names_the_run_the_model_rules_out() -> None:
    system = aircraft()
    reports = np.zeros((3, 2, 3), dtype=np.int64)
    reports[2, 1] = [1, 2, 0]  # Caravan to the radar and the ESM, Learjet to the imager
    sure = [
        IdentitySensor(s.name, s.reports, s.subsets, (s.confusion > 0.4).astype(float), 1.0)
        for s in system.sensors
    ]
    with pytest.raises(ValueError, match="run 12, step 1: .* zero likelihood"):
        bayes_posteriors(reports, sure, system.prior, run_offset=10)


def test_report_indices() -> None:
    v = np.array([[0.0, 2.0], [np.nan, 1.0]])
    np.testing.assert_array_equal(report_indices(v, 3, "x", allow_nan=True), [[0, 2], [3, 1]])
    with pytest.raises(ValueError, match="x: NaN where a class index"):
        report_indices(v, 3, "x", allow_nan=False)
    with pytest.raises(ValueError, match=r"x: value 1.5 is not an index 0..2"):
        report_indices(np.array([1.5]), 3, "x", allow_nan=True)
    with pytest.raises(ValueError, match=r"value 3.0 is not an index"):
        report_indices(np.array([3.0]), 3, "x", allow_nan=True)


def test_decision_weights_split_ties() -> None:
    score = np.array([[0.5, 0.5, 0.0], [0.2, 0.3, 0.5], [0.0, 0.0, 0.0], [np.nan] * 3])
    tb = np.array([[1.0, 0.4, 0.2], [0.0, 0.0, 0.0], [1.0, 1.0, 0.5], [0.0] * 3])
    np.testing.assert_array_equal(
        decision_weights(score), [[0.5, 0.5, 0], [0, 0, 1], [1 / 3] * 3, [0, 0, 0]]
    )
    np.testing.assert_array_equal(
        decision_weights(score, tiebreak=tb), [[1, 0, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0, 0]]
    )


def test_ds_combine_treats_a_missing_report_as_no_evidence() -> None:
    onehot = ("Learjet", "Falcon", "Caravan")
    c = np.array([[0.94, 0.03, 0.03], [0.03, 0.94, 0.03], [0.03, 0.03, 0.94]])
    sensors = [IdentitySensor(n, onehot, (1, 2, 4), c, 0.8) for n in ("a", "b")]
    reports = np.array([[[0, 3], [3, 3], [3, 0]]])  # index 3 = no report for these sensors
    bel, pl, conflict, acc = ds_combine(reports, sensors, 3)
    np.testing.assert_allclose(bel[0, 0], bel[0, 1])  # step 1: nothing new
    assert conflict[0, 1] == 0 and acc[0, 1] == acc[0, 0] == 0
    np.testing.assert_allclose(bel[0, 2, 0], 1 - 0.2 * 0.2)  # two reports of Learjet, r = 0.8
    np.testing.assert_allclose(pl[0, 2], [1.0, 0.04, 0.04])


# ------------------------------------------------------------------------------------------
# metrics
# ------------------------------------------------------------------------------------------


def _direct_summary(truth: np.ndarray, est: dict[str, np.ndarray]) -> dict[str, dict]:
    """The summary's numbers computed run by run, step by step, with plain loops."""
    out: dict[str, dict] = {}
    B, K1 = truth.size, est["BAYES"].shape[1]
    for a, v in est.items():
        acc = np.zeros(K1)
        pt = np.zeros(K1)
        for b in range(B):
            for k in range(K1):
                if a == "BAYES":
                    score, p = v[b, k], v[b, k]
                    top = np.flatnonzero(score >= score.max() - 1e-12)
                else:
                    bel, pl = v[b, k, :3], v[b, k, 3:6]
                    p = pl / pl.sum()
                    top = np.flatnonzero(bel >= bel.max() - 1e-12)
                    top = top[pl[top] >= pl[top].max() - 1e-12]
                acc[k] += (truth[b] in top) / top.size / B
                pt[k] += p[truth[b]] / B
        out[a] = {"accuracy": acc, "p_true": pt}
    return out


def test_identity_metrics_against_a_direct_computation() -> None:
    system = aircraft()
    truth, reports = simulate(system, 8, 4, 0, 120)
    est = {a: estimate(system, reports, a) for a in ARCHITECTURES}
    m = IdentityMetrics(9, CLASSES, ARCHITECTURES, sample_runs=2)
    m.add(truth[:70], {a: v[:70] for a, v in est.items()}, 0)
    m.add(truth[70:], {a: v[70:] for a, v in est.items()}, 70)
    res = m.finish()
    want = _direct_summary(truth, est)
    for a in ARCHITECTURES:
        e = res.architectures[a]
        np.testing.assert_allclose(res.series[a]["accuracy"], want[a]["accuracy"], rtol=1e-12)
        np.testing.assert_allclose(res.series[a]["p_true"], want[a]["p_true"], rtol=1e-12)
        assert e["accuracy"] == pytest.approx(want[a]["accuracy"].mean(), rel=1e-12)
        assert e["final"]["mean_p_true"] == pytest.approx(want[a]["p_true"][-1], rel=1e-12)
        # per-run averages over the steps: the standard error of their mean
        p = est[a] if a == "BAYES" else est[a][..., 3:6] / est[a][..., 3:6].sum(-1, keepdims=True)
        per_run = -np.log(np.take_along_axis(p, truth[:, None, None], -1))
        per_run = per_run[..., 0].mean(axis=1)
        assert e["stderr"]["log_loss"] == pytest.approx(per_run.std(ddof=1) / math.sqrt(120))
    ds = res.architectures["DS"]
    assert ds["total_conflict"] == 0.0
    assert ds["mean_conflict"] == pytest.approx(np.nanmean(est["DS"][..., 6]))
    w_b = decision_weights(est["BAYES"])
    w_d = decision_weights(est["DS"][..., :3], tiebreak=est["DS"][..., 3:6])
    np.testing.assert_allclose(res.disagreement, 1 - (w_b * w_d).sum(-1).mean(0), rtol=1e-12)
    assert res.disagreement_overall == pytest.approx(res.disagreement.mean())
    assert res.disagreement_final == res.disagreement[-1]
    # per-class means: runs of class c, score of class c
    for c in range(3):
        own = est["BAYES"][truth == c][..., c].mean(0)
        np.testing.assert_allclose(res.series["BAYES"]["probability"][:, c], own, rtol=1e-12)
    # the sample runs: the first two, whole
    assert list(res.samples) == [0, 1]
    t0, arrays = res.samples[1]
    assert t0 == truth[1]
    np.testing.assert_array_equal(arrays["BAYES"]["probability"], est["BAYES"][1])
    np.testing.assert_array_equal(arrays["DS"]["plausibility"], est["DS"][1, :, 3:6])


def test_identity_metrics_merge_equals_one_pass() -> None:
    system = aircraft()
    truth, reports = simulate(system, 4, 9, 0, 90)
    est = {a: estimate(system, reports, a) for a in ARCHITECTURES}
    one = IdentityMetrics(5, CLASSES, ARCHITECTURES, sample_runs=3)
    one.add(truth, est, 0)
    parts = [IdentityMetrics(5, CLASSES, ARCHITECTURES, sample_runs=3) for _ in range(3)]
    for i, p in enumerate(parts):
        sl = slice(30 * i, 30 * (i + 1))
        p.add(truth[sl], {a: v[sl] for a, v in est.items()}, 30 * i)
    merged = parts[2].merge(parts[0]).merge(parts[1])
    a, b = one.finish(), merged.finish()
    assert a.architectures.keys() == b.architectures.keys()
    for arch in ARCHITECTURES:
        for key, val in a.architectures[arch].items():
            if isinstance(val, dict):
                for k2, v2 in val.items():
                    assert b.architectures[arch][key][k2] == pytest.approx(v2, rel=1e-12)
            else:
                assert b.architectures[arch][key] == pytest.approx(val, rel=1e-12)
        for key, s in a.series[arch].items():
            np.testing.assert_allclose(b.series[arch][key], s, rtol=1e-12)
    assert list(b.samples) == [0, 1, 2]
    with pytest.raises(ValueError, match="cannot merge"):
        one.merge(IdentityMetrics(5, CLASSES, ["BAYES"]))


def test_metric_sums_leave_undefined_values_out() -> None:
    s = MetricSums(3)
    s.add(np.array([[1.0, np.nan, 3.0], [np.nan, np.nan, 5.0]]))
    np.testing.assert_array_equal(s.series(), [1.0, np.nan, 4.0])
    assert s.overall() == 2.5 and s.final() == 4.0
    assert s.runs == 2 and s.stderr() == pytest.approx(1.5)  # per-run means 2 and 5
    pc = PerClassSums(1, 2)
    pc.add(np.array([0, 1, 1]), np.array([[[0.9, 0.1]], [[0.3, 0.7]], [[0.5, np.nan]]]))
    np.testing.assert_array_equal(pc.series(), [[0.9, 0.7]])
    with pytest.raises(ValueError, match="identity architectures"):
        IdentityMetrics(3, CLASSES, ["CKF"])
