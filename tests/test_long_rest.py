"""Issue 34, the rest of item 1: a long one-run log in blocks of time where it was taken whole.

* A simulation with dropouts (`timing.dropout`) or irregular instants (a time-varying F, Q)
  is drawn in blocks (`core.simulate.one_run_blocks`): the sensors file is byte for byte the
  whole draw's, and its estimate and evaluation (readings missing at the dropouts) go through
  the replay path carried block to block (estimates; the exact values by the one-log route,
  the truth being the filters' model).
* EKF/UKF filters on a log whose messages carry their own covariance (`System.Rs`) use R of
  each instant: against an EKF/UKF written here from the formulas with that R, and in blocks
  of time (`core.nonlinear.long_log`) bit for bit the whole run's.

The time-block size is the hidden setting FUSIONLOG_TIME_BLOCK (test_long_logs.py), so that a
log of a few hundred instants spans several blocks. Which path ran is seen by wrapping the
public functions of each path (`one_run_blocks`, `replay_long_estimates`,
`replay_expected_blocks`, `estimate_blocks`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from long_helpers import count_calls, summaries, summaries_close, time_block
from test_latency_nonlinear import Filter, readings
from test_nis_nonlinear import MODEL, REPLAY, write_log

from fusionlog.core.model import System
from fusionlog.io.mcap import McapFile

PIPELINE = Path(__file__).resolve().parents[1] / "pipeline"
EPS = np.finfo(float).eps

# Blocked and whole runs differ only in the grouping of sums over instants and, for the exact
# values, in the route (the plans of the pattern against the filters' own covariances, the
# same algebra in another order); the filters are contractive, so a rounding does not grow
# along the log: 1e-9 relative is far above what a few hundred instants can move (1e-13 each).
RTOL = 1e-9


def _fusionlog(folder: Path, block: int | None, mp, *args) -> None:
    """`fusionlog ARGS` run in `folder` (relative outputs: the provenance's command is the
    same text for the whole and blocked runs), blocks of time of `block` instants (None: the
    default, longer than these logs)."""
    folder.mkdir(exist_ok=True)
    with mp.context() as m:
        m.chdir(folder)
        time_block(m, block)
        ok(*args)


def _dropout_scenario(folder: Path, name: str) -> Path:
    """ajgl2009_dropout (10 % of each sensor's readings lost, regular instants), multirate
    (radar 1 Hz, GNSS 5 Hz offset 50 ms: irregular instants, F and Q per interval) with
    20 % of the GNSS readings lost, or radar_tracking (range-bearing radars, a nonlinear h)
    with 20 % of radar2's lost."""
    text = (PIPELINE / f"{name}.toml").read_text()
    old = {
        "multirate": "period = 0.2\noffset = 0.05\n",
        "radar_tracking": "position = [5000.0, 0.0]\nR = [[100.0, 0.0], [0.0, 3.0e-4]]\n",
    }.get(name)
    if old is not None:
        assert old in text
        text = text.replace(old, old + "dropout = 0.2\n")
    path = folder / f"{name}.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("name", "steps", "block"),
    [
        ("ajgl2009_dropout", 400, 70),
        ("multirate", 400, 70),
        ("radar_tracking", 400, 70),
        ("ajgl2009_dropout", 140_000, 50_000),
    ],
    ids=["dropout", "irregular instants", "range-bearing", "dropout, one run a stream"],
)
def test_a_simulation_with_dropouts_in_blocks_is_the_whole_draw(
    tmp_path, monkeypatch, name, steps, block
) -> None:
    """`fusionlog simulate --runs 1`: the sensors file in blocks of time, byte for byte the
    whole draw's. 400 instants: the stream's chunk has several runs (run 0's numbers first,
    their products made as the chunk's); 140 001: a chunk of one run. The readings lost are
    about the dropout's share (within 5 standard errors), NaN in their messages."""
    from fusionlog.core import simulate

    scenario = _dropout_scenario(tmp_path, name)
    args = ("simulate", scenario, "--runs", "1", "--steps", steps, "-o", "s.mcap")
    _fusionlog(tmp_path / "whole", None, monkeypatch, *args)
    with monkeypatch.context() as m:
        calls = count_calls(m, simulate, "one_run_blocks")
        _fusionlog(tmp_path / "blocked", block, m, *args)
        assert calls.count == 1
    whole, blocked = ((tmp_path / d / "s.mcap").read_bytes() for d in ("whole", "blocked"))
    assert blocked == whole
    sensor, p = {
        "multirate": ("/sensors/gnss", 0.2),
        "radar_tracking": ("/sensors/radar2", 0.2),
    }.get(name, ("/sensors/s1", 0.1))
    mf = McapFile(tmp_path / "whole" / "s.mcap")
    z = mf.read_all([sensor])[sensor]
    lost = np.isnan((z[0] if isinstance(z, tuple) else z)[0][mf.topic_steps(sensor)]).any(-1)
    assert abs(lost.mean() - p) < 5 * math.sqrt(p * (1 - p) / len(lost)), lost.mean()
    if name == "multirate":
        assert np.ptp(np.diff(mf.times())) > 0.01  # 0.05 s and 0.1 s apart


def _close(a, b) -> None:
    """Summaries equal to RTOL; the bound's worst ratio to 1e-7: the plans' analysis of
    MSC-GMF on multirate's correlated radar and odometer leaves 4e-8 (its worst instant then
    another one within BOUND_TOL of 1), the filters' covariances 4e-16."""
    summaries_close(a, b, rtol=RTOL, atol=1e-12, nan=True, bound_rtol=1e-7)


@pytest.fixture(scope="module", params=["ajgl2009_dropout", "multirate"])
def dropout_runs(tmp_path_factory, request):
    """`fusionlog run --runs 1 --steps 400` whole and in blocks of 70 instants, and how many
    times the blocked run entered the blocked replay's estimate and exact analysis."""
    from fusionlog.core import exact_replay
    from fusionlog.driver import long_log

    tmp = tmp_path_factory.mktemp("dropout")
    scenario = _dropout_scenario(tmp, request.param)
    args = ("run", scenario, "--runs", "1", "--steps", "400", "--out-dir", "out")
    mp = pytest.MonkeyPatch()
    try:
        _fusionlog(tmp / "whole", None, mp, *args)
        est = count_calls(mp, long_log, "replay_long_estimates")
        exact = count_calls(mp, exact_replay, "replay_expected_blocks")
        _fusionlog(tmp / "blocked", 70, mp, *args)
    finally:
        mp.undo()
    return tmp / "whole" / "out", tmp / "blocked" / "out", (est.count, exact.count)


def test_the_dropout_log_is_estimated_and_evaluated_in_blocks(dropout_runs) -> None:
    """The blocked run went through the replay path (estimates) and the one-log route in
    blocks (exact values); the log has readings missing."""
    whole, _, (estimates, exact) = dropout_runs
    assert estimates == 1 and exact == 1
    prov = McapFile(whole / "estimates.mcap").metadata["fusionlog.provenance"]
    assert prov["measurement_pattern"] not in ("complete", "per-run")


def test_blocked_estimates_of_a_dropout_log_equal_the_whole_run(dropout_runs) -> None:
    """Every architecture's means and covariances (the whole run's plans of the pattern, the
    blocked run's filters carried from block to block: the same recursions), the pattern."""
    whole, blocked, _ = dropout_runs
    a, b = (McapFile(d / "estimates.mcap") for d in (whole, blocked))
    topics = [t for t in a.topics if t.startswith("/estimates/")]
    assert "/estimates/FBS" in topics and len(topics) == 7
    x, y = a.read_all(topics), b.read_all(topics)
    for t in topics:
        scale = np.abs(x[t][0]).max()
        np.testing.assert_allclose(y[t][0], x[t][0], rtol=0, atol=RTOL * scale, err_msg=t)
        np.testing.assert_allclose(y[t][1], x[t][1], rtol=RTOL, atol=1e-15, err_msg=t)
    pa, pb = (f.metadata["fusionlog.provenance"] for f in (a, b))
    assert pb["measurement_pattern"] == pa["measurement_pattern"]


def test_blocked_summary_of_a_dropout_log_equals_the_whole_run(dropout_runs) -> None:
    """The Monte Carlo metrics, the exact values (given the drawn pattern) and the bound."""
    whole, blocked, _ = dropout_runs
    a, b = summaries(whole, blocked)
    _close(b, a)
    for arch, entry in b["architectures"].items():
        assert entry["expected"]["mse"] > 0, arch
    for arch in ("CKF", "MSC-GMF", "FBS"):  # reported = true error covariance: 1 + 1e-15
        assert b["architectures"][arch]["bound"]["holds"], arch


def _drawn_peak(folder: Path, steps: int, block: int) -> int:
    """The peak of the Python allocations (tracemalloc) while one run of multirate with its
    GNSS dropping readings (irregular instants) is drawn in blocks of time, each block
    dropped as the writer would (the system on its instants, F and Q per interval, made
    before)."""
    import tracemalloc

    from fusionlog.core.simulate import one_run_blocks
    from fusionlog.scenario import load_scenario

    sc = load_scenario(_dropout_scenario(folder, "multirate"), runs=1, steps=steps)
    sched = sc.schedule
    system = sc.system.on_times(sched.times)
    measures = sched.measures
    tracemalloc.start()
    try:
        lost = 0
        for _k0, _k1, _x, z in one_run_blocks(system, steps, sc.seed, block, measures):
            lost += int(np.isnan(z).any(-1).sum())
        assert lost > 0
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_peak_memory_of_a_blocked_draw_does_not_grow_with_the_instants(tmp_path) -> None:
    """Blocks of 5 000 instants, one run a stream (more than 2^17 instants): twice the
    instants, the same peak within 10 % (the whole draw keeps x and z, 64 bytes an instant
    each: 18 MB more at 280 000)."""
    _drawn_peak(tmp_path, 1_000, 500)  # what is imported on first use
    p1, p2 = _drawn_peak(tmp_path, 140_000, 5_000), _drawn_peak(tmp_path, 280_000, 5_000)
    assert p2 <= 1.1 * p1, (p1, p2)


# -- EKF/UKF with a covariance per message ---------------------------------------------------


def _radars(filt: str) -> System:
    from test_latency_nonlinear import radar_system

    system = radar_system(True, filt, "reprocess")
    b = dataclasses.replace(system.sensors[1], timing=system.sensors[0].timing)  # on time
    return dataclasses.replace(system, sensors=(system.sensors[0], b), late=None)


@pytest.mark.parametrize("filt", ["EKF", "UKF"])
@pytest.mark.parametrize("arch", ["CKF", "SKF:b"])
def test_filters_use_the_r_of_each_instant(filt, arch) -> None:
    """A coordinated turn seen by two radars whose R varies per instant (range and bearing
    variances scaled by 0.3..3, some readings missing): the lanes' estimates equal an EKF/UKF
    written from the formulas (`test_latency_nonlinear.Filter`) with each instant's R, to the
    conditioning of the covariances times 1e3 eps; with the nominal R they differ."""
    from fusionlog.core.nonlinear import estimate
    from fusionlog.core.simulate import simulate

    K = 30
    system = _radars(filt)
    rng = np.random.default_rng(11)
    scale = rng.uniform(0.3, 3.0, (K + 1, system.m))
    Rs = np.repeat(system.R[None], K + 1, axis=0) * np.sqrt(scale[:, :, None] * scale[:, None])
    varying = dataclasses.replace(system, Rs=Rs)
    z = simulate(varying, K, 5, 0, 2)[1]
    z[:, rng.random(K + 1) < 0.2, :2] = np.nan
    got = estimate(varying, arch, z, np.arange(K + 1.0))
    nominal = estimate(system, arch, z, np.arange(K + 1.0))
    assert np.abs(nominal.mean - got.mean).max() > 1e-3
    which = [0, 1] if arch == "CKF" else [1]
    ukf = None if filt == "EKF" else system.ukf
    for r in range(z.shape[0]):
        f = Filter(system, ukf)
        x, P = system.prior.mean.copy(), system.prior.cov.copy()
        for k in range(K + 1):
            if k:
                x, P = f.predict(x, P)
            got_k = []
            for s, v in readings(system, z[r], k, which):
                sl = system.sensor_slices[system.sensors.index(s)]
                got_k.append((dataclasses.replace(s, R=Rs[k][sl, sl]), v))
            if got_k:
                x, P, _ = f.update(x, P, got_k)
            tol = 1e3 * np.linalg.cond(P) * EPS
            np.testing.assert_allclose(got.mean[r, k], x, rtol=0, atol=tol * np.abs(x).max())
            np.testing.assert_allclose(got.cov[r, k], P, rtol=0, atol=tol * np.abs(P).max())


def _covariance_log(folder: Path) -> None:
    """The radar log of test_nis_nonlinear with a covariance in each message (range and
    bearing variances 25 and 1e-3 scaled by 0.5..2, correlated 0.3), imported."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    write_log(folder / "plain.mcap")
    rng = np.random.default_rng(4)
    with open(folder / "plain.mcap", "rb") as f, open(folder / "log.mcap", "wb") as out:
        w = Writer(out)
        w.start()
        sid = w.register_schema("Reading", "jsonschema", b'{"type": "object"}')
        ch = {t: w.register_channel(t, "json", sid) for t in ("/a", "/b")}
        for _, channel, msg in make_reader(f).iter_messages(log_time_order=True):
            body = json.loads(msg.data)
            c = rng.uniform(0.5, 2.0, 2) * np.array([25.0, 1e-3])
            off = 0.3 * math.sqrt(c[0] * c[1])
            body["cov"] = [c[0], off, off, c[1]]
            w.add_message(ch[channel.topic], log_time=msg.log_time, data=json.dumps(body).encode(),
                          publish_time=msg.publish_time)  # fmt: skip
        w.finish()
    text = REPLAY.replace('time = "header.stamp"\n', 'time = "header.stamp"\ncovariance = "cov"\n')
    (folder / "replay.toml").write_text(text)
    (folder / "plain.toml").write_text(REPLAY.replace("log.mcap", "plain.mcap"))
    ok("import", folder / "replay.toml", "-o", folder / "s.mcap")
    ok("import", folder / "plain.toml", "-o", folder / "plain_s.mcap")


NL_ARCHS = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF:a", "SKF:b", "CI", "FBS", "AVG"]


@pytest.fixture(scope="module", params=["EKF", "UKF"])
def covariance_runs(tmp_path_factory, request):
    """The radar log with a covariance per message: `estimate --model` (range-bearing, the
    parameter's filter, every architecture) and `evaluate`, whole and in blocks of 8 instants
    (80 instants: ten blocks), and how often the blocked run entered the nonlinear blocks."""
    from fusionlog.core.nonlinear import long_log

    tmp = tmp_path_factory.mktemp("covariance")
    _covariance_log(tmp)
    (tmp / "model.toml").write_text(MODEL.replace('filter = "EKF"', f'filter = "{request.param}"'))
    archs = [a for arch in NL_ARCHS for a in ("--arch", arch)]
    mp = pytest.MonkeyPatch()
    outs, count = {}, 0
    try:
        for name, block, sensors in (("whole", None, "s"), ("blocked", 8, "s"),
                                     ("plain", None, "plain_s")):  # fmt: skip
            d = tmp / name
            calls = count_calls(mp, long_log, "estimate_blocks")
            est = ("estimate", tmp / f"{sensors}.mcap", "--model", tmp / "model.toml", *archs)
            _fusionlog(d, block, mp, *est, "-o", "e.mcap")
            _fusionlog(d, block, mp, "evaluate", tmp / f"{sensors}.mcap", "e.mcap", "-o",
                       "ev.rrd", "--summary", "summary.json")  # fmt: skip
            count += calls.count if name == "blocked" else 0
            outs[name] = d
    finally:
        mp.undo()
    return outs, count


def test_per_message_r_reaches_the_nonlinear_filters(covariance_runs) -> None:
    """The log's messages carry their covariance: the filters' estimates differ from those
    of the same readings with the nominal R."""
    outs, _ = covariance_runs
    a, b = (McapFile(outs[n] / "e.mcap") for n in ("whole", "plain"))
    x, y = a.read_all(["/estimates/CKF"]), b.read_all(["/estimates/CKF"])
    assert np.abs(x["/estimates/CKF"][1] - y["/estimates/CKF"][1]).max() > 1e-3


def test_nonlinear_blocks_with_per_message_r_equal_the_whole_run(covariance_runs) -> None:
    """Every architecture's means and per-run covariances bit for bit (the same operations on
    the same numbers, R of each instant from the same array), the NIS and the summary."""
    outs, count = covariance_runs
    assert count == 1
    a, b = (McapFile(outs[n] / "e.mcap") for n in ("whole", "blocked"))
    topics = [f"/estimates/{x}" for x in NL_ARCHS]
    x, y = a.read_all(topics), b.read_all(topics)
    for t in topics:
        np.testing.assert_array_equal(y[t][0], x[t][0], err_msg=t)
        np.testing.assert_array_equal(y[t][1], x[t][1], err_msg=t)
    sa, sb = summaries(outs["whole"], outs["blocked"])
    _close(sb, sa)
    assert all("nis" in sa["architectures"][arch] for arch in NL_ARCHS)
