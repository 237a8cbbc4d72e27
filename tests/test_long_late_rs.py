"""Issue 34: a long one-run log with late sensors whose messages carry their own covariance
(DESIGN.md "Late measurements" and "MCAP files": a `covariance` field per message,
`System.Rs`) is estimated and evaluated in blocks of time, each message's R read per block.

The stacked model of the late path (`core.latency`: X_k = [x_k; ...; x_{k-W}], the reading of
instant k - l arriving at k a row on block l) takes each reading with the R of the instant it
was taken: R~_k[c, c'] = R_{k-l}[o, o'] for two slots of one lag l, 0 across lags.

References:
- the whole run of the same log (the plans of the run's arrival pattern, their exact analysis
  by `core.exact.analyse`, with the whole (K+1, m, m) array): blocked = whole to the rounding
  of the two routes (tests/test_long_late_random.py's `RTOL`, `EXACT_ATOL`);
- the centralised KF written here from its formulas (eqs. 14-18) with each message's own
  variance, and the late policy reprocess written from its definition (DESIGN.md): the
  estimate at t_k is the Kalman estimate of x_k from exactly the readings that arrived by
  t_k, each with the R of its message (the filter settled W instants back, where every
  reading has arrived, refiltered forward);
- a Kalman filter under its own model reports its error covariance: the exact analysis of the
  CKF under reprocess (the truth is the filters' model, the readings drawn with each
  message's variance) has its bound ratio 1 at every instant -- with the nominal R in either
  the filter or the analysis it would not.

A simulated scenario cannot give a sensor a covariance per message (its `[[sensors]] R` is one
matrix): `_per_message` rewrites a simulated sensors file with the project's writer, s1 and s3
redrawn with a variance of their own per message (0.2..5), the truth, the arrival fields and
the scenario kept. The time-block size is the hidden setting FUSIONLOG_TIME_BLOCK (as
tests/test_long_*.py).
"""

from __future__ import annotations

import dataclasses
import json
import math
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from test_long_late_random import EXACT_ATOL, RTOL

from fusionlog.io.mcap import McapFile

STEPS = 299
BLOCK = 40

SCENARIO = """
[scenario]
name = "long_late_rs"
steps = {steps}
runs = 1
seed = 343
dt = 1.0
state_names = ["position", "velocity"]
[model]
kind = "constant-velocity"
n0 = 0.16
[prior]
mean = [100.0, -1.0]
cov = [[1.0, 0.0], [0.0, 1.0]]
[[sensors]]
name = "s1"
H = [[1.0, 0.0]]
R = 1.0
[[sensors]]
name = "s2"
H = [[1.0, 0.0]]
R = 2.0
latency = 1.0
period = 2.0
[[sensors]]
name = "s3"
H = [[1.0, 0.0]]
R = 0.5
latency = {s3}
{correlated}
[estimate]
architectures = {archs}
late = "{late}"
"""

#: The architectures of the blocked late paths: the filters fusing every sensor and one
#: sensor's, and per-sensor rules (MSC-GMF reads the locals' joint J).
ARCHS = ["CKF", "HKF", "SKF:s3", "MSC", "MSC-GMF", "CI"]
DRAWN, FIXED = "{min = 1.0, max = 3.0}", "3.0"
#: the sensors whose messages carry their own variance
NOISY = ("s1", "s3")
#: s1 and s3 correlated: 0.1 keeps the joint R of every instant positive definite with the
#: messages' variances 0.2..5
CORRELATED = '[[correlations]]\nsensors = ["s1", "s3"]\ncov = [[0.1]]\n'


def _scenario(tmp: Path, s3: str, late: str, archs=ARCHS, correlated=False, steps=STEPS) -> Path:
    corr = CORRELATED if correlated else ""
    text = SCENARIO.format(steps=steps, s3=s3, late=late, archs=json.dumps(archs), correlated=corr)
    path = tmp / "late_rs.toml"
    path.write_text(text)
    return path


def _per_message(sim: Path, out: Path, seed: int = 34) -> np.ndarray:
    """`sim` (a simulated one-run sensors file) rewritten to `out` with the `NOISY` sensors'
    readings redrawn about the truth with a variance per message (0.2..5, log-uniform) in
    its covariance field; the truth, the other readings, the arrivals, the instants each topic
    has messages at and the scenario kept. Returns the variances (K+1, len(NOISY)), NaN
    where a sensor has no message."""
    from fusionlog.io.mcap import VALUES, McapWriter
    from fusionlog.io.mcap.arrival import read_arrivals
    from fusionlog.io.mcap.run_steps import RunColumn
    from fusionlog.stages.common import PROVENANCE_META, SCENARIO_META

    mf = McapFile(sim)
    times = np.asarray(mf.times())
    K1 = len(times)
    sensors = [f"/sensors/{s}" for s in ("s1", "s2", "s3")]
    data = mf.read_all(["/truth", *sensors])
    arrivals = read_arrivals(sim, sensors, 1, K1)
    rng = np.random.default_rng(seed)
    x = data["/truth"][0]
    columns, present, variances = [RunColumn("/truth", VALUES, x)], [np.ones(K1, bool)], []
    for t in sensors:
        have = mf.topic_steps(t)
        z, cov = data[t][0], None
        if t.rsplit("/", 1)[1] in NOISY:
            r = np.exp(rng.uniform(np.log(0.2), np.log(5.0), K1))
            z = x[:, :1] + np.sqrt(r)[:, None] * rng.normal(size=(K1, 1))
            cov = r[:, None, None]
            variances.append(np.where(have, r, np.nan))
        a = arrivals[t]
        columns.append(RunColumn(t, VALUES, z, cov, None if a is None else a[0]))
        present.append(have)
    with open(out, "wb") as f, McapWriter(f) as w:
        w.add_metadata(SCENARIO_META, mf.metadata[SCENARIO_META])
        w.add_metadata(PROVENANCE_META, mf.metadata[PROVENANCE_META])
        if any(a is not None for a in arrivals.values()):
            w.declare_arrival()
        w.write_run_steps(0, times, columns, np.stack(present, axis=1))
    return np.stack(variances, axis=1)


def _estimate_and_evaluate(sens: Path, out: Path, block: int | None, mp) -> Path:
    if block is None:
        mp.delenv("FUSIONLOG_TIME_BLOCK", raising=False)
    else:
        mp.setenv("FUSIONLOG_TIME_BLOCK", str(block))
    out.mkdir()
    ok("estimate", sens, "-o", out / "estimates.mcap")
    ok("evaluate", sens, out / "estimates.mcap", "-o", out / "eval.rrd",
       "--summary", out / "summary.json")  # fmt: skip
    return out


class _Spy:
    """Counts the blocks of time the late paths estimated and the exact blocks evaluated."""

    def __init__(self, mp: pytest.MonkeyPatch) -> None:
        import fusionlog.stages.late_blocks as late_blocks
        from fusionlog.stages.evaluator.long_late import LongLateExact

        self.estimated, self.exact = 0, 0
        inner, window = late_blocks.late_estimates, LongLateExact.window

        def late_estimates(*a, **kw):
            for got in inner(*a, **kw):
                self.estimated += 1
                yield got

        def exact(ev, *a, **kw):
            self.exact += 1
            return window(ev, *a, **kw)

        mp.setattr(late_blocks, "late_estimates", late_estimates)
        mp.setattr(LongLateExact, "window", exact)


def _log(tmp: Path, s3: str, late: str, **kw) -> tuple[Path, np.ndarray]:
    sc = _scenario(tmp, s3, late, **kw)
    ok("simulate", sc, "-o", tmp / "sim.mcap")
    r = _per_message(tmp / "sim.mcap", tmp / "sensors.mcap")
    return tmp / "sensors.mcap", r


#: (name, s3's latency, policy, architectures: every kind the blocked path takes under each
#: policy, the rules' whole runs (their plans) being the costly part)
CASES = [
    ("drawn delays, reprocess", DRAWN, "reprocess", ARCHS),
    ("drawn delays, neglect", DRAWN, "neglect", ["CKF", "HKF", "SKF:s3", "CI"]),
    ("drawn delays, retrodict", DRAWN, "retrodict", ["CKF", "HKF", "SKF:s3", "MSC-GMF"]),
    ("fixed latencies, reprocess", FIXED, "reprocess", ["CKF", "SKF:s3", "MSC"]),
]


@pytest.fixture(scope="module", params=CASES, ids=[c[0] for c in CASES])
def runs(request, tmp_path_factory):
    """The log estimated and evaluated whole and in blocks of `BLOCK` instants."""
    _, s3, late, archs = request.param
    tmp = tmp_path_factory.mktemp("late_rs")
    mp = pytest.MonkeyPatch()
    try:
        sens, r = _log(tmp, s3, late, archs=archs)
        whole = _estimate_and_evaluate(sens, tmp / "whole", None, mp)
        spy = _Spy(mp)
        blocked = _estimate_and_evaluate(sens, tmp / "blocked", BLOCK, mp)
    finally:
        mp.undo()
    return {"whole": whole, "blocked": blocked, "spy": spy, "sensors": sens, "r": r,
            "late": late, "s3": s3, "archs": archs}  # fmt: skip


def _estimates(path: Path) -> dict:
    mf = McapFile(path)
    return {t: mf.read_all([t])[t] for t in mf.topics if t.startswith("/estimates/")}


def _close(a, b, path=""):
    """summary.json's values within `RTOL` relative (exact ones and the bound's also
    `EXACT_ATOL` absolute, the Monte Carlo metrics 1e-9), the rest equal."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            if k not in ("worst_step", "provenance", "timing"):
                _close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        exact = ".expected." in path or ".bound." in path
        tol = EXACT_ATOL if exact else 1e-9
        assert math.isclose(a, b, rel_tol=RTOL, abs_tol=tol), (path, a, b)
    else:
        assert a == b, (path, a, b)


def test_the_log_spans_several_blocks_with_late_readings_of_their_own_R(runs) -> None:
    mf = McapFile(runs["sensors"])
    assert mf.steps() == STEPS + 1 > 6 * BLOCK
    got = mf.message_covariances("/sensors/s3")
    have = np.isfinite(got[:, 0, 0])
    np.testing.assert_array_equal(got[have, 0, 0], runs["r"][have, 1])
    assert len(np.unique(got[have, 0, 0])) == have.sum()  # a variance of its own each


def test_blocked_estimates_and_summary_equal_the_whole_run(runs) -> None:
    spy = runs["spy"]
    assert spy.estimated == math.ceil((STEPS + 1) / BLOCK)  # estimated in blocks
    assert spy.exact == math.ceil((STEPS + 1) / BLOCK)  # and its exact analysis
    whole = _estimates(runs["whole"] / "estimates.mcap")
    blocked = _estimates(runs["blocked"] / "estimates.mcap")
    assert whole.keys() == blocked.keys() and len(whole) == len(runs["archs"])
    for topic, (mean, cov) in whole.items():
        scale = np.abs(mean).max()
        np.testing.assert_allclose(blocked[topic][0], mean, rtol=RTOL, atol=RTOL * scale,
                                   err_msg=topic)  # fmt: skip
        np.testing.assert_allclose(blocked[topic][1], cov, rtol=RTOL, atol=1e-12, err_msg=topic)
    a, b = (json.loads((runs[k] / "summary.json").read_text()) for k in ("whole", "blocked"))
    _close(a, b)
    assert a["late"] == runs["late"]
    for arch in runs["archs"]:
        assert a["architectures"][arch]["expected"]["mse"] is not None, arch


def _reference_ckf(sens: Path, r: np.ndarray, s3: str) -> tuple[np.ndarray, np.ndarray]:
    """The CKF under reprocess written here (module docstring): constant velocity (dt 1 s,
    n0 0.16), the prior, s1 and s3 with each message's variance `r`, s2 with R 2; a reading
    of instant i arrives at its arrival field (drawn delays), else at t_i + its sensor's fixed
    latency (s2 1 s, s3 3 s), and is used at t_k when it has arrived by then."""
    from fusionlog.io.mcap.arrival import read_arrivals

    mf = McapFile(sens)
    t = np.asarray(mf.times())
    K1 = len(t)
    topics = [f"/sensors/{s}" for s in ("s1", "s2", "s3")]
    data = mf.read_all(topics)
    z = np.stack([data[q][0, :, 0] for q in topics], axis=1)  # (K1, 3), NaN: no reading
    got = read_arrivals(sens, topics, 1, K1)
    fixed = (0.0, 1.0, 3.0 if s3 == FIXED else None)
    arrival = np.stack(
        [t + lat if got[q] is None else got[q][0] for q, lat in zip(topics, fixed, strict=True)],
        axis=1,
    )
    R = np.stack([r[:, 0], np.full(K1, 2.0), r[:, 1]], axis=1)
    W = int(np.nanmax(np.ceil(arrival - t[:, None])))  # the largest lag (instants)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.16 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    H = np.array([[1.0, 0.0]])
    settled = None  # (x, P) after instant k - W - 1, every reading of it and before fused
    means, covs = np.empty((K1, 2)), np.empty((K1, 2, 2))
    for k in range(K1):
        first = max(0, k - W)
        x, P = (np.array([100.0, -1.0]), np.eye(2)) if settled is None else settled
        for i in range(first, k + 1):
            if i > 0:
                x, P = F @ x, F @ P @ F.T + Q
            for j in range(3):
                if np.isfinite(z[i, j]) and arrival[i, j] <= t[k]:
                    S = H @ P @ H.T + R[i, j]
                    K = P @ H.T / S
                    x = x + (K * (z[i, j] - H @ x)).ravel()
                    IKH = np.eye(2) - K @ H
                    P = IKH @ P @ IKH.T + R[i, j] * K @ K.T
            if i == first and k >= W:  # every reading of instant k - W has arrived by t_k
                settled = (x.copy(), P.copy())
        means[k], covs[k] = x, P
    return means, covs


def test_ckf_is_the_kalman_filter_of_the_arrived_readings_with_each_messages_R(runs) -> None:
    """The blocked CKF against `_reference_ckf` (reprocess); the KF is contractive, so the
    rounding does not grow along the log (1e-9 of the values)."""
    if runs["late"] != "reprocess":
        pytest.skip("the reference is written for reprocess")
    means, covs = _reference_ckf(runs["sensors"], runs["r"], runs["s3"])
    for k in ("blocked", "whole"):
        mean, cov = _estimates(runs[k] / "estimates.mcap")["/estimates/CKF"]
        np.testing.assert_allclose(mean[0], means, rtol=1e-9, atol=1e-9 * 100, err_msg=k)
        np.testing.assert_allclose(cov, covs, rtol=1e-9, atol=1e-12, err_msg=k)


def test_the_exact_analysis_takes_each_messages_R(runs) -> None:
    """A Kalman filter on the truth's own model reports its error covariance: the CKF's and
    SKF:s3's bound ratio is 1 at every instant (reprocess and neglect: Kalman filters of the
    readings they take), blocked and whole -- with the nominal R in the filter or in the
    analysis it is not (the variances span 0.2..5 about R 1 and 0.5)."""
    if runs["late"] == "retrodict":
        pytest.skip("Al1 over several updates is not the Kalman filter (core.retrodict)")
    for k in ("blocked", "whole"):
        s = json.loads((runs[k] / "summary.json").read_text())
        for arch in ("CKF", "SKF:s3"):
            bound = s["architectures"][arch]["bound"]
            assert bound["holds"], (k, arch, bound)
            assert abs(bound["worst"] - 1.0) < 1e-6, (k, arch, bound)


# -- memory ---------------------------------------------------------------------------------


def _sensors_file(path: Path, K1: int, seed: int = 7) -> None:
    """A one-run sensors file of K1 instants (dt 1 s): the truth, s1 and s3 with a variance
    of their own in each message's covariance field, s2 with its R (the scenario's fixed
    latencies say when they arrive), in chunks of 64 KiB (the reading's peak is a chunk's
    decoding: both logs span several)."""
    from fusionlog.io.mcap import VALUES, McapWriter
    from fusionlog.io.mcap.run_steps import RunColumn

    rng = np.random.default_rng(seed)
    x = np.stack([100.0 + np.cumsum(rng.normal(size=K1)) * 0.1, rng.normal(size=K1)], axis=1)
    cols = [RunColumn("/truth", VALUES, x)]
    for s in ("s1", "s2", "s3"):
        r = np.exp(rng.uniform(-1, 1, K1)) if s in NOISY else np.full(K1, 2.0)
        z = x[:, :1] + np.sqrt(r)[:, None] * rng.normal(size=(K1, 1))
        cols.append(RunColumn(f"/sensors/{s}", VALUES, z, r[:, None, None] if s in NOISY else None))
    with open(path, "wb") as f, McapWriter(f, chunk_size=1 << 16) as w:  # chunks of a small log
        w.write_run_steps(0, np.arange(K1) * 1.0, cols)


def _peak(path: Path, block: int) -> int:
    """tracemalloc's peak while the log's per-instant R is read (`with_message_covariances`
    of a log taken in blocks of time) and the late filters (s2 1 s, s3 3 s late) estimate it
    block by block and give their exact analysis, each block's results dropped as a writer
    does."""
    from fusionlog.core.latency_blocks import LateBlocks
    from fusionlog.driver.long_log import edges
    from fusionlog.scenario import scenario_from_text
    from fusionlog.stages.noise import with_message_covariances

    mf = McapFile(path)
    times, K1 = np.asarray(mf.times()), mf.steps()
    text = SCENARIO.format(steps=K1 - 1, s3=FIXED, late="reprocess", archs='["CKF"]',
                           correlated="")  # fmt: skip
    system = scenario_from_text(text).system
    topics = [f"/sensors/{s}" for s in ("s1", "s2", "s3")]
    archs = ["CKF", "HKF", "MSC-GMF"]
    tracemalloc.start()
    try:
        sy = with_message_covariances(system.on_times(times), mf, blocked=True)
        assert sy.Rs is not None and len(sy.Rs) == K1
        est = LateBlocks.of(sy, archs, K1 - 1, times, block)
        ex = LateBlocks.of(sy, archs, K1 - 1, times, block)
        assert est is not None and ex is not None
        for (k0, k1), (r0, r1, data) in zip(edges(K1, block), mf.iter_time_blocks(topics, block),
                                            strict=True):  # fmt: skip
            assert (k0, k1) == (r0, r1)
            z = np.concatenate([data[t][0] for t in topics], axis=-1)
            assert set(est.estimates(k0, k1, z)) == set(archs)
            assert set(ex.error_covariances(k0, k1, ~np.isnan(z))) == set(archs)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_the_peak_does_not_grow_with_the_log(tmp_path, monkeypatch) -> None:
    """Four times the instants (blocks of 250), the peak grows by less than 8 bytes per added
    instant; the raw R held whole is 8 m^2 = 72 bytes an instant here, the stacked R~ of
    the late slots as much again, and the whole log's gains and covariances far more."""
    monkeypatch.setenv("FUSIONLOG_TIME_BLOCK", "250")
    tiny, small, large = (tmp_path / f"{n}.mcap" for n in ("tiny", "small", "large"))
    K = 1_500
    _sensors_file(tiny, 300)
    _sensors_file(small, K)
    _sensors_file(large, 4 * K)
    _peak(tiny, 250)  # what is imported on first use
    p1, p2 = _peak(small, 250), _peak(large, 250)
    assert p2 - p1 < 8 * 3 * K, (p1, p2)


# -- correlated readings arriving apart ----------------------------------------------------------

#: The architectures that take correlated readings arriving apart in blocks with each
#: message's R: HKF and the per-sensor locals keep the raw noises still to be read, each with
#: the R of its instant (`core.latency_apart`); MSC-GMF and AVG read their joint J.
APART = ["HKF", "SKF:s3", "MSC-GMF", "AVG"]


def test_correlated_readings_apart_with_each_messages_R_in_blocks(tmp_path, monkeypatch):
    """s1 and s3 correlated (0.1: the joint R of every instant positive definite with the
    variances 0.2..5), s3 late by 1..3 s drawn per reading: blocked = whole (estimates,
    summary), estimated and analysed in blocks; MSC-GMF and AVG report their true error
    covariance (their bound ratio 1), which a recursion with one R would not find."""
    mp = pytest.MonkeyPatch()
    try:
        sens, _ = _log(tmp_path, DRAWN, "reprocess", archs=APART, correlated=True)
        whole = _estimate_and_evaluate(sens, tmp_path / "whole", None, mp)
        spy = _Spy(mp)
        blocked = _estimate_and_evaluate(sens, tmp_path / "blocked", BLOCK, mp)
    finally:
        mp.undo()
    assert spy.estimated == spy.exact == math.ceil((STEPS + 1) / BLOCK)
    a, b = (_estimates(d / "estimates.mcap") for d in (whole, blocked))
    for topic, (mean, cov) in a.items():
        scale = np.abs(mean).max()
        np.testing.assert_allclose(b[topic][0], mean, rtol=RTOL, atol=RTOL * scale, err_msg=topic)
        np.testing.assert_allclose(b[topic][1], cov, rtol=RTOL, atol=1e-12, err_msg=topic)
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (whole, blocked))
    _close(sa, sb)
    for arch in ("MSC-GMF", "AVG"):
        bound = sb["architectures"][arch]["bound"]
        assert abs(bound["worst"] - 1.0) < 1e-6, (arch, bound)


def test_the_centre_with_correlated_readings_apart_and_each_messages_R_runs_whole():
    """The CKF's decorrelated readings z_j - A z_E have A = R_jE R_EE^-1 of each instant's R:
    the blocked path (a stacked filter on fixed coefficients) declines them, the whole run's
    plans take them; HKF's blocks take the same log."""
    from fusionlog.core.latency_blocks import LateBlocks
    from fusionlog.scenario import scenario_from_text

    text = SCENARIO.format(
        steps=99, s3=DRAWN, late="reprocess", archs='["CKF"]', correlated=CORRELATED
    )
    system = scenario_from_text(text).system
    times = np.arange(100.0)
    rng = np.random.default_rng(3)
    Rs = np.repeat(system.R[None], 100, axis=0)
    Rs[:, 0, 0] = rng.uniform(0.2, 5.0, 100)
    per_message = dataclasses.replace(system.on_times(times), Rs=Rs)
    assert LateBlocks.of(system.on_times(times), ["CKF"], 99, times, 20) is not None
    assert LateBlocks.of(per_message, ["CKF"], 99, times, 20) is None
    assert LateBlocks.of(per_message, ["HKF"], 99, times, 20) is not None


# -- a recorded replay ------------------------------------------------------------------------

T0 = 1_700_000_000  # s: the recording's clock


def _recording(folder: Path, per_sensor: int, seed: int = 34) -> Path:
    """A replay of two position sensors at their own irregular instants: `a` in a JSON MCAP
    whose messages carry their own variance (0.05..5, the field `c`) and are logged 0..0.12 s
    after their stamp `t` (``arrival = "log_time"``: a lag of up to ~4 instants), `b` in a CSV
    with one R, on time; the truth (p, v) at every instant in a CSV."""
    from test_replay_sources import write_json_mcap

    rng = np.random.default_rng(seed)
    ta = np.round(np.cumsum(rng.uniform(0.02, 0.06, per_sensor)), 4)
    tb = np.round(np.cumsum(rng.uniform(0.02, 0.06, per_sensor)) + 0.00005, 5)
    t = np.union1d(ta, tb)
    v = 1.0 + 0.2 * np.cumsum(rng.normal(size=len(t))) * 0.05
    p = np.concatenate([[0.0], np.cumsum(v[:-1] * np.diff(t))])
    ra = np.exp(rng.uniform(np.log(0.05), np.log(5.0), per_sensor))
    za = p[np.searchsorted(t, ta)] + np.sqrt(ra) * rng.normal(size=per_sensor)
    zb = p[np.searchsorted(t, tb)] + np.sqrt(0.5) * rng.normal(size=per_sensor)
    logged = ta + rng.uniform(0.0, 0.12, per_sensor)
    msgs = sorted(
        (int(round((T0 + g) * 1e9)), {"t": T0 + float(x), "z": float(z), "c": [float(r)]})
        for x, g, z, r in zip(ta, logged, za, ra, strict=True)
    )
    write_json_mcap(folder / "a.mcap", {"/a": msgs})
    (folder / "b.csv").write_text(
        "time,b\n" + "".join(f"{T0 + x:.5f},{float(z)!r}\n" for x, z in zip(tb, zb, strict=True))
    )
    rows = zip(t, p, v, strict=True)
    (folder / "truth.csv").write_text(
        "time,p,v\n" + "".join(f"{T0 + x:.5f},{float(a)!r},{float(b)!r}\n" for x, a, b in rows)
    )
    replay = folder / "replay.toml"
    replay.write_text(
        '[scenario]\nname = "long_late_rs_replay"\nstate_names = ["p", "v"]\n'
        '[model]\nkind = "constant-velocity"\nn0 = 0.5\n'
        "[prior]\nmean = [0.0, 1.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n"
        '[[sensors]]\nname = "a"\nsource = "a.mcap"\ntopic = "/a"\nvalues = ["z"]\n'
        'time = "t"\ncovariance = "c"\narrival = "log_time"\nH = [[1.0, 0.0]]\nR = 1.0\n'
        '[[sensors]]\nname = "b"\nsource = "b.csv"\nvalues = ["b"]\nH = [[1.0, 0.0]]\n'
        "R = 0.5\n"
        '[truth]\nsource = "truth.csv"\nvalues = ["p", "v"]\nstates = ["p", "v"]\n'
        'match = "exact"\n'
        '[estimate]\narchitectures = ["CKF", "SKF:a", "MSC", "CI"]\n'
    )  # fmt: skip
    return replay


def test_a_recorded_replay_with_each_messages_R_in_blocks(tmp_path, monkeypatch):
    """The replay of 2 x 250 readings (~500 instants, blocks of 50), a's delays its messages'
    log times, reprocessed: `run` in blocks = the whole run (estimates, summary with NIS,
    exact values). (Retrodiction's blocks are the simulated logs' `runs`. HKF is left out:
    on this log's intervals of 5e-5 s its information-form fusion of the stacked locals
    diverges, |mean| ~ 1e9, whole and blocked alike, with one R as with each message's.)"""
    replay = _recording(tmp_path, 250)
    out = {}
    mp = pytest.MonkeyPatch()
    try:
        for name, block in (("whole", None), ("blocked", BLOCK)):
            if block is None:
                mp.delenv("FUSIONLOG_TIME_BLOCK", raising=False)
            else:
                mp.setenv("FUSIONLOG_TIME_BLOCK", str(block))
                spy = _Spy(mp)
            ok("run", replay, "--out-dir", tmp_path / name)
            out[name] = tmp_path / name
    finally:
        mp.undo()
    K1 = McapFile(out["whole"] / "sensors.mcap").steps()
    assert K1 > 6 * BLOCK and spy.estimated == spy.exact == math.ceil(K1 / BLOCK)
    assert McapFile(out["whole"] / "sensors.mcap").message_covariances("/sensors/a") is not None
    a, b = (_estimates(d / "estimates.mcap") for d in out.values())
    for topic, (mean, cov) in a.items():
        np.testing.assert_allclose(b[topic][0], mean, rtol=RTOL, atol=1e-12, err_msg=topic)
        np.testing.assert_allclose(b[topic][1], cov, rtol=RTOL, atol=1e-15, err_msg=topic)
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in out.values())
    _close(sa, sb)
    assert "nis" in sb["architectures"]["CKF"] and sb["late"] == "reprocess"
