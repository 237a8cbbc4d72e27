"""Issue 34: the exact analysis of a long one-run log with late sensors whose truth is not the
filters' model (`estimate --model`, a scenario's `[truth]`), in blocks of time: the joint
moments of the truth and each architecture's stacked filters carried from block to block
(`LateBlocks.mismatch`, `core.latency_mismatch`; retrodicted, `RetroBlocks.mismatch`), where
`_late_exact` returned None (the whole run) before.

* Core: MSE matrix, bias and reported covariance in blocks against the whole run's route, the
  plans of the run's arrivals (`PlanCache.block_plans`) analysed by `exact.analyse` with the
  truth apart, for reprocess, neglect and retrodict, drawn delays and missing readings, a
  truth with other noise and initial distribution or other F and H; and, independently, the
  CKF's and an SKF's values under reprocess against the batch conditioning written here (the
  reprocess estimate is E[x_k | the readings arrived by k] under the model, an affine map of
  the readings whose error moments follow from the truth's joint Gaussian of states and
  readings). Memory: four times the instants, the same peak.
* The CLI: a simulated run with drawn delays estimated with `--model` (other noise; other
  dynamics), a scenario with fixed latencies whose `[truth]` is not its prior, retrodicted with
  `--model`: summary.json in blocks of time = whole, and the blocked route taken.

Tolerances: blocks and plans compute the same recursions in another order (the stacked
filter's gains against the wrapped plan's maps), the filters contractive: 1e-9 of the largest
entry (the errors seen are ~1e-13). The batch reference solves systems of ~100 readings
whose covariances are well conditioned (R >= 0.1, prior of order 1): 1e-9 too.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from conftest import random_system
from long_helpers import (
    NS,
    T0,
    Spy,
    late_toml,
    position_sensor,
    random_walk,
    recorded_toml,
    stamped_mcap,
    summaries,
    summaries_close,
    time_block,
)

from fusionlog.core.latency_blocks import LateBlocks
from fusionlog.core.model import Prior, System
from fusionlog.core.retrodict_blocks import RetroBlocks
from fusionlog.core.timing import SensorTiming

RTOL = 1e-9
ARCHS = ["CKF", "HKF", "SKF:s3", "MSC", "MSC-GMF", "CI", "AVG"]


def _model(late: str, s3=(1.0, 3.0)) -> System:
    """A random stable model of two states and three scalar sensors: s1 on time, s2 a fixed
    instant late, s3 late by `s3` (a range: drawn per reading)."""
    s = random_system(np.random.default_rng(3), 2, [1, 1, 1])
    lat = [(0.0, 0.0), (1.0, 1.0), tuple(s3)]
    sensors = tuple(
        dataclasses.replace(x, timing=SensorTiming(latency=lt))
        for x, lt in zip(s.sensors, lat, strict=True)
    )
    return dataclasses.replace(s, sensors=sensors, late=late)


def _truth(model: System, kind: str) -> System:
    """The data's model: other noise (Q 1.8 times, R 0.6 times) and initial distribution, or
    other F and H (x then stays in the joint moments)."""
    if kind == "noise":
        sensors = tuple(dataclasses.replace(s, R=0.6 * s.R) for s in model.sensors)
        p = model.prior
        return dataclasses.replace(
            model, Q=1.8 * model.Q, sensors=sensors, initial=Prior(p.mean + 0.5, 2 * p.cov)
        )
    rng = np.random.default_rng(11)
    sensors = tuple(
        dataclasses.replace(s, H=s.H + 0.2 * rng.standard_normal(s.H.shape)) for s in model.sensors
    )
    return dataclasses.replace(model, F=0.9 * model.F, sensors=sensors)


def _log(K1: int, seed: int = 5, s3=(1.0, 3.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Instants (K1,) s, which readings were taken (K1, 3) (a fifth missing) and when each
    arrived (K1, 3) s (NaN: not taken), s3's delay drawn in `s3`."""
    rng = np.random.default_rng(seed)
    times = np.arange(K1, dtype=float)
    present = rng.random((K1, 3)) > 0.2
    arrival = np.stack([times, times + 1.0, times + rng.uniform(*s3, K1)], axis=1)
    return times, present, np.where(present, arrival, np.nan)


def _blocked(model, truth, archs, times, present, arrival, block) -> dict[str, tuple]:
    """{arch: (MSE (K1, n, n), bias (K1, n), P (K1, n, n))} in blocks of `block` instants."""
    from fusionlog.driver.long_log import edges

    K1 = len(times)
    kind = RetroBlocks if model.late == "retrodict" else LateBlocks
    blocks = kind.of(model, archs, K1 - 1, times, block)
    assert blocks is not None and blocks.takes(truth)
    got: dict[str, list] = {a: [] for a in archs}
    for k0, k1 in edges(K1, block):
        for a, v in blocks.mismatch(k0, k1, present[k0:k1], arrival[k0:k1], truth).items():
            got[a].append(v)
    return {a: tuple(np.concatenate([g[i] for g in v]) for i in range(3)) for a, v in got.items()}


def _agree(got: np.ndarray, want: np.ndarray, what: str, scale: float | None = None) -> None:
    scale = max(float(np.abs(want).max()), 1e-300) if scale is None else scale
    np.testing.assert_allclose(got, want, rtol=0, atol=RTOL * scale, err_msg=what)


def _against_the_plans(got, model, truth, times, present, arrival, what: str) -> None:
    """`got` (`_blocked`'s) as the whole run's plans of the arrivals analysed with `truth`."""
    from fusionlog.core.exact import analyse
    from fusionlog.driver import PlanCache

    cache = PlanCache(model, len(times) - 1, clock=times)
    cache.arrivals = arrival[None]
    plans, _ = cache.block_plans(list(got), np.where(present, 0.0, np.nan)[None], 0)
    for a in got:
        whole = analyse(plans[a], truth)
        rms = math.sqrt(np.abs(whole.mse).max())
        for i, f in enumerate(("mse", "bias", "P")):  # a per-run plan's: (1, K1, ...)
            want = getattr(whole, f).reshape(got[a][i].shape)
            _agree(got[a][i], want, f"{what} {a} {f}", rms if f == "bias" else None)


@pytest.mark.parametrize("kind", ["noise", "dynamics"])
@pytest.mark.parametrize("late", ["reprocess", "neglect", "retrodict"])
def test_blocks_equal_the_plans_of_the_whole_run(late, kind) -> None:
    """90 instants in blocks of 25 (s3's readings cross the edges), drawn delays, a fifth of
    the readings missing: each architecture's MSE, bias and P as the whole run's route (its
    plans, conditional on the drawn delays, analysed with the truth apart)."""
    model = _model(late)
    truth = _truth(model, kind)
    times, present, arrival = _log(90)
    got = _blocked(model, truth, ARCHS, times, present, arrival, 25)
    _against_the_plans(got, model, truth, times, present, arrival, f"{late} {kind}")
    # the truth is not the model: the errors are biased or their covariance is not P
    mse, bias, P = got["CKF"]
    assert np.abs(bias).max() > 0.1 or np.abs(mse - P).max() > 0.1 * np.abs(P).max()


def test_irregular_instants_with_other_dynamics() -> None:
    """Irregular instants (a continuous model discretised per interval: F, Q per instant, the
    truth's stacked per block of time) and a truth of another A and Qc, 60 instants in blocks
    of 20 under reprocess: as the whole run's plans."""
    rng = np.random.default_rng(4)
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.5, 1.5, 59))])
    base = _model("reprocess")
    A = 0.3 * rng.standard_normal((2, 2)) - 0.3 * np.eye(2)
    base = dataclasses.replace(base, continuous=(A, base.Q), initial=None)
    model = base.on_times(times)
    truth = dataclasses.replace(base, continuous=(A - 0.2 * np.eye(2), 1.5 * base.Q))
    truth = truth.on_times(times)
    _, present, arrival = _log(60, seed=6)
    arrival = arrival - np.arange(60.0)[:, None] + times[:, None]  # the same delays
    got = _blocked(model, truth, ["CKF", "HKF", "MSC-GMF"], times, present, arrival, 20)
    _against_the_plans(got, model, truth, times, present, arrival, "irregular")


def _batch(model: System, truth: System, arrived, K1: int):
    """The reprocess filter's values from the batch: (MSE, bias, P) (K1, ...) of x_hat_k =
    E_model[x_k | the readings arrived by k] (`arrived(k)`: a boolean (K1, S) of the readings
    fused at k), under the truth. X = [x_0; ...; x_K] = A [x_0; w_1; ...; w_K] (A of the
    powers of F), readings z_(i,j) = H_j x_i + v_(i,j): Gaussian under either model."""
    n, S = model.n, len(model.sensors)

    def joint(sys: System):
        init = sys.truth_initial if sys is truth else sys.prior
        A = np.zeros((K1 * n, K1 * n))
        for i in range(K1):
            for j in range(i + 1):
                A[i * n : (i + 1) * n, j * n : (j + 1) * n] = np.linalg.matrix_power(sys.F, i - j)
        cov_in = np.zeros((K1 * n, K1 * n))
        cov_in[:n, :n] = init.cov
        for i in range(1, K1):
            cov_in[i * n : (i + 1) * n, i * n : (i + 1) * n] = sys.Q
        mean_in = np.concatenate([init.mean, np.zeros((K1 - 1) * n)])
        H = np.zeros((K1 * S, K1 * n))  # reading (i, j) in row i S + j
        R = np.zeros((K1 * S, K1 * S))
        for i in range(K1):
            for j, s in enumerate(sys.sensors):
                H[i * S + j, i * n : (i + 1) * n] = s.H[0]
                R[i * S + j, i * S + j] = s.R[0, 0]
        # [X; Z] = [A; H A] [x_0; w] + [0; v]
        M = np.vstack([A, H @ A])
        mean = M @ mean_in
        cov = M @ cov_in @ M.T
        cov[K1 * n :, K1 * n :] += R
        return mean, cov

    mm, cm = joint(model)
    mt, ct = joint(truth)
    out = [np.empty((K1, n, n)), np.empty((K1, n)), np.empty((K1, n, n))]
    for k in range(K1):
        r = K1 * n + np.flatnonzero(arrived(k).ravel())  # the readings fused at k
        x = np.arange(k * n, (k + 1) * n)
        G = np.linalg.solve(cm[np.ix_(r, r)], cm[np.ix_(r, x)]).T  # x_hat = mm_x + G (z - mm_r)
        P = cm[np.ix_(x, x)] - G @ cm[np.ix_(r, x)]
        L = np.zeros((n, len(mt)))  # e = x_k - x_hat = L [X; Z] - (mm_x - G mm_r)
        L[:, x] = np.eye(n)
        L[:, r] = -G
        bias = L @ mt - (mm[x] - G @ mm[r])
        out[0][k] = L @ ct @ L.T + np.outer(bias, bias)
        out[1][k], out[2][k] = bias, P
    return out


@pytest.mark.parametrize("kind", ["noise", "dynamics"])
def test_reprocess_against_the_batch_estimate_written_here(kind) -> None:
    """40 instants in blocks of 15, s2 a fixed instant late, s3 drawn 1 to 3 late, readings
    missing: the CKF (every reading arrived by k) and SKF:s3 (s3's) as the batch conditioning
    `_batch`, which knows nothing of stacked states, plans or blocks."""
    model = _model("reprocess")
    truth = _truth(model, kind)
    times, present, arrival = _log(40, seed=8)
    K1 = len(times)
    got = _blocked(model, truth, ["CKF", "SKF:s3"], times, present, arrival, 15)
    step = np.ceil(arrival - 1e-9)  # the instant (times k) each reading arrives at

    def by(k: int, sensors: list[int]) -> np.ndarray:
        out = present & (step <= k)
        out[:, [j for j in range(3) if j not in sensors]] = False
        return out

    for a, sensors in (("CKF", [0, 1, 2]), ("SKF:s3", [2])):
        want = _batch(model, truth, lambda k, s=sensors: by(k, s), K1)
        rms = math.sqrt(np.abs(want[0]).max())
        for i, f in enumerate(("mse", "bias", "P")):
            _agree(got[a][i], want[i], f"{kind} {a} {f}", rms if f == "bias" else None)


def _peak(K1: int, block: int) -> int:
    """The peak of the Python allocations (tracemalloc) while the exact values of a log of K1
    instants (made before) are computed in blocks of time, each block's values dropped."""
    import tracemalloc

    from fusionlog.driver.long_log import edges

    model = _model("reprocess")
    truth = _truth(model, "dynamics")
    times, present, arrival = _log(K1)
    tracemalloc.start()
    try:
        blocks = LateBlocks.of(model, ["CKF", "MSC"], K1 - 1, times, block)
        for k0, k1 in edges(K1, block):
            blocks.mismatch(k0, k1, present[k0:k1], arrival[k0:k1], truth)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_peak_memory_does_not_grow_with_the_instants() -> None:
    """Blocks of 75 instants: four times the instants, the same peak within 10 % (the whole
    run's plans hold every instant's maps and moments)."""
    _peak(150, 75)  # what is imported on first use
    p1, p2 = _peak(300, 75), _peak(1_200, 75)
    assert p2 <= 1.1 * p1, (p1, p2)


# -- the CLI ----------------------------------------------------------------------------------

CV = 'kind = "constant-velocity"\nn0 = 0.16'
#: another F (the velocity decays) and Q
DECAY = "F = [[1.0, 1.0], [0.0, 0.9]]\nQ = [[0.05, 0.08], [0.08, 0.16]]"


def _scenario(path: Path, model=CV, r2="2.0", s3="{min = 1.0, max = 3.0}", late="reprocess",
              extra="") -> Path:  # fmt: skip
    """s1 (dropping out) on time, s2 one instant late, s3 late by `s3`; `extra` after it."""
    path.parent.mkdir(exist_ok=True, parents=True)
    s1 = position_sensor("s1", 1.0, extra="dropout = 0.2\n")
    sensors = s1 + position_sensor("s2", r2, "1.0") + position_sensor("s3", 0.5, s3)
    archs = ["CKF", "HKF", "SKF:s3", "MSC", "CI"]
    path.write_text(late_toml("long_late_truth", 343, 199, sensors, archs, late, model) + extra)
    return path


def _summaries(tmp: Path, block: int, *commands) -> tuple[dict, dict, int]:
    """The commands run in `tmp`/whole and, in blocks of `block` instants, in `tmp`/blocked
    (the last writes summary.json): the two summaries and the blocked route's block count."""
    out, count = [], 0
    for name, b in (("whole", None), ("blocked", block)):
        folder = tmp / name
        folder.mkdir()
        with pytest.MonkeyPatch.context() as m:
            m.chdir(folder)
            time_block(m, b)
            # the blocks of the late mismatch route
            calls = Spy(
                m, calls={"late": (LateBlocks, "mismatch"), "retro": (RetroBlocks, "mismatch")}
            )
            for c in commands:
                ok(*c)
            n = calls.late + calls.retro
            count = n if b is not None else count
            assert b is not None or n == 0
        out += summaries(folder)
    return out[0], out[1], count


def _close(a, b) -> None:
    """Summaries equal to RTOL (the Monte Carlo metrics' means move by the blocks' roundings,
    the exact values by the two routes')."""
    summaries_close(a, b, rtol=RTOL, atol=1e-12, nan=True)


def test_correlated_readings_apart_stay_whole() -> None:
    """s1 and s3 correlated (under the model, or under the truth only) with s3's readings
    arriving apart from s1's: the stacked noise is correlated across instants, which the
    stacked filters' joint moments do not hold, so the blocked route refuses the truth (the
    evaluator then takes the whole run); correlated readings arriving together (s3 on time)
    are taken, as the plans' analysis."""
    model = _model("reprocess")
    cross = {(0, 2): np.array([[0.3 * math.sqrt(model.R[0, 0] * model.R[2, 2])]])}
    times = np.arange(50.0)
    for m, t in ((dataclasses.replace(model, cross_R=cross), model),
                 (model, dataclasses.replace(model, cross_R=cross))):  # fmt: skip
        blocks = LateBlocks.of(m, ["CKF", "MSC"], 49, times, 20)
        assert blocks is not None and not blocks.takes(_truth(t, "noise"))
    # on time together: the stacked noise of one instant correlated, white across instants
    together = _model("reprocess", s3=(0.0, 0.0))
    truth = dataclasses.replace(_truth(together, "dynamics"), cross_R=cross)
    times, present, arrival = _log(40, s3=(0.0, 0.0))
    got = _blocked(together, truth, ["CKF", "MSC-GMF"], times, present, arrival, 15)
    _against_the_plans(got, together, truth, times, present, arrival, "together")


def _expected_everywhere(summary: dict) -> None:
    for a, entry in summary["architectures"].items():
        assert entry["expected"]["mse"] > 0 and "bound" in entry, a


@pytest.mark.parametrize(
    ("late", "model"),
    [("reprocess", {"n0 = 0.16": "n0 = 0.3", "r2": "4.0"}), ("neglect", {"model": DECAY}),
     ("retrodict", {"n0 = 0.16": "n0 = 0.3"})],
    ids=["reprocess, other noise", "neglect, other dynamics", "retrodict, other noise"],
)  # fmt: skip
def test_a_simulated_run_estimated_with_another_model(tmp_path, late, model) -> None:
    """200 instants with s3's delays drawn 1 to 3 instants and s1's readings dropping out,
    estimated with `--model` (other noise, or another F and Q), evaluated whole and in blocks
    of 40: the same summary (the exact values conditional on the drawn delays), the blocked
    route taken once a block."""
    scenario = _scenario(tmp_path / "sc.toml", late=late)
    kw = {"model": model.get("model", CV).replace("n0 = 0.16", model.get("n0 = 0.16", "n0 = 0.16"))}
    other = _scenario(tmp_path / "model.toml", late=late, r2=model.get("r2", "2.0"), **kw)
    sim = ("simulate", scenario, "--runs", "1", "-o", "s.mcap")
    est = ("estimate", "s.mcap", "--model", other, "-o", "e.mcap")
    ev = ("evaluate", "s.mcap", "e.mcap", "-o", "ev.rrd", "--summary", "summary.json")
    whole, blocked, count = _summaries(tmp_path, 40, sim, est, ev)
    assert count == 5
    _close(blocked, whole)
    _expected_everywhere(whole)
    assert all(e["expected"]["conditional"] for e in whole["architectures"].values())


def test_fixed_latencies_and_a_truth_not_the_prior(tmp_path) -> None:
    """Fixed latencies (s3 three instants late), s1 dropping out, a `[truth]` drawing x_0
    elsewhere than the prior says: `run` whole and in blocks of 40, the same summary."""
    truth = "[truth]\ninitial_mean = [104.0, 0.0]\ninitial_cov = [[9.0, 0.0], [0.0, 4.0]]\n"
    scenario = _scenario(tmp_path / "sc.toml", s3="3.0", extra=truth)
    run = ("run", scenario, "--out-dir", ".", "--force")
    whole, blocked, count = _summaries(tmp_path, 40, run)
    assert count == 5
    _close(blocked, whole)
    _expected_everywhere(whole)
    assert not whole["architectures"]["CKF"]["bound"]["holds"]  # the prior is too small


# -- a recorded replay: arrivals from the messages' log times, a truth --------------------------


def _recorded(tmp: Path) -> Path:
    """A JSON MCAP of two sensors of one random walk and its truth: a on time every 0.1 s, b
    stamped at 0.05 + 0.1 i and logged 0 to 0.3 s late (uniform), a fifth of b's readings
    left out, the walk at every instant (/truth). The scenario replays it with b's arrival
    its log time (Qc 0.4, R 0.49 and 0.16)."""
    rng = np.random.default_rng(9)
    N = 150
    x = np.cumsum(rng.normal(0, 0.2, 2 * N))
    events = []
    for i in range(N):
        ta, tb = T0 + i * NS // 10, T0 + (i * 100 + 50) * NS // 1000
        events += [(ta, "/a", ta, x[2 * i] + rng.normal(0, 0.7))]
        events += [(ta, "/truth", ta, x[2 * i]), (tb, "/truth", tb, x[2 * i + 1])]
        if rng.random() >= 0.2:
            logged = tb + round(rng.uniform(0, 0.3) * NS)
            events += [(logged, "/b", tb, x[2 * i + 1] + rng.normal(0, 0.4))]
    stamped_mcap(tmp / "log.mcap", ("/a", "/b", "/truth"), events)
    truth = ('[truth]\nsource = "log.mcap"\ntopic = "/truth"\nvalues = ["v"]\n'
             'time = "header.stamp"\nstates = ["x"]\n')  # fmt: skip
    text = recorded_toml("recorded_late_truth", ["CKF", "HKF", "SKF:b", "MSC"], "reprocess", truth)
    path = tmp / "recorded.toml"
    path.write_text(text)
    # the filters' model (Qc doubled, b's R 0.3), b late by up to the delays recorded
    model = (
        '[scenario]\nname = "recorded_model"\nstate_names = ["x"]\ndt = 0.05\nsteps = 1\nruns = 1\n'
        + random_walk(0.8)
        + '[[sensors]]\nname = "a"\nH = [[1.0]]\nR = 0.49\n'
        + '[[sensors]]\nname = "b"\nH = [[1.0]]\nR = 0.3\nlatency = {min = 0.0, max = 0.3}\n'
        + '[estimate]\nlate = "reprocess"\n'
    )
    (tmp / "model.toml").write_text(model)
    return path


def test_a_recorded_replay_estimated_with_another_model(tmp_path) -> None:
    """The replay (300 irregular instants, b's arrivals its log times) imported, estimated with
    `--model` (Qc doubled, b's R 0.3: a scenario file whose b is up to 0.3 s late) and
    evaluated whole and in blocks of 60: the same summary, the blocked route taken once a
    block."""
    replay = _recorded(tmp_path)
    imp = ("import", replay, "-o", "s.mcap")
    est = ("estimate", "s.mcap", "--model", tmp_path / "model.toml", "-o", "e.mcap")
    ev = ("evaluate", "s.mcap", "e.mcap", "-o", "ev.rrd", "--summary", "summary.json")
    whole, blocked, count = _summaries(tmp_path, 60, imp, est, ev)
    assert count == 5
    _close(blocked, whole)
    _expected_everywhere(whole)
