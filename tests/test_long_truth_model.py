"""Issue 34: the exact values of a long one-run log in blocks of time when the truth is not the
filters' model (`estimate --model`, a scenario's `[truth]`, a truth with other noise or
dynamics), on logs without steady plans (irregular instants, a covariance per message, missing
readings): `core.exact_mismatch`, taken by the evaluate stage where the one-log route in blocks
(`exact_replay.replay_expected_blocks`) took only where the truth is the model.

* Core: every architecture's MSE matrix, bias, reported covariance, NEES, DM and the bound
  check in blocks against the whole log's route, `exact.analyse` of the plans (a truth with
  other noise, another initial distribution, other F and H); against the exact moments by
  superposition of the references written from the paper's equations (`references`), and the
  CKF against the covariance of [x; x_hat] propagated here from the formulas.
* The CLI: a simulated run with dropouts on irregular instants estimated with `--model`, a
  scenario whose `[truth]` is not its prior, replay_robot (ROS 2 MCAP and CSV) estimated with
  `--model`: summary.json in blocks of time = whole.
* Memory: four times the instants, the same peak.

Tolerances: the blocks and the plans compute the same recursions in another order (batched
products, the kernels' sums), and the filters are contractive, so a rounding does not grow
along the log: 1e-9 of the largest entry bounds what a few hundred instants can move (1e-13
each). The superposition reference sums ~10^3 basis runs' outer products: 1e-9 too.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from conftest import random_system
from long_helpers import count_calls, summaries_close, time_block

from fusionlog.core.model import Prior, System

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = ROOT / "pipeline"
RTOL = 1e-9
ARCHS = ["CKF", "HKF", "MSC-GMF", "MSC", "CI", "FBS", "AVG", "ICI", "EI", "SKF:s1", "SKF:s2",
         "SKF:s3"]  # fmt: skip


def _model(K1: int, varying_r: bool = True) -> tuple[System, np.ndarray, np.ndarray]:
    """A random stable model (sensors of sizes 1, 2, 1, the first two correlated) on irregular
    instants (a continuous model discretised per interval: F, Q per instant), R scaled per
    instant (a covariance per message) where `varying_r`; its instants (K1,) and a mask with a
    quarter of the components missing (K1, m)."""
    rng = np.random.default_rng(K1)
    s = random_system(np.random.default_rng(3), 3, [1, 2, 1], correlated=True)
    A = 0.3 * rng.standard_normal((3, 3)) - 0.3 * np.eye(3)
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.2, 1.2, K1 - 1))])
    s = dataclasses.replace(s, continuous=(A, s.Q), initial=None).on_times(times)
    if varying_r:
        s = dataclasses.replace(s, Rs=s.R * (1 + rng.random(K1))[:, None, None])
    return s, times, rng.random((K1, s.m)) > 0.25


def _truth(model: System, times: np.ndarray, kind: str) -> System:
    """The data's model: other noise (Q 1.8 times, R 0.6 times), another initial distribution,
    or other dynamics and measurement matrices (x then stays in the joint moments)."""
    A, Qc = model.continuous
    if kind == "initial":
        p = model.prior
        return dataclasses.replace(model, initial=Prior(p.mean + [0.8, -0.5, 0.3], 2.5 * p.cov))
    if kind == "noise":
        t = dataclasses.replace(model, continuous=(A, 1.8 * Qc)).on_times(times)
        sensors = tuple(dataclasses.replace(s, R=0.6 * s.R) for s in model.sensors)
        cross = {k: 0.6 * v for k, v in model.cross_R.items()}
        Rs = None if model.Rs is None else 0.6 * model.Rs
        return dataclasses.replace(t, sensors=sensors, cross_R=cross, Rs=Rs)
    rng = np.random.default_rng(11)
    sensors = tuple(
        dataclasses.replace(s, H=s.H + 0.1 * rng.standard_normal(s.H.shape)) for s in model.sensors
    )
    t = dataclasses.replace(model, continuous=(A - 0.15 * np.eye(3), Qc)).on_times(times)
    return dataclasses.replace(t, sensors=sensors)


def _blocked(model: System, truth: System, archs, mask: np.ndarray, block: int):
    """{arch: {field: (K+1, ...)}} of the exact values in blocks of `block` instants, and
    the bound check's summary ("summary"); asserts the route takes them."""
    from fusionlog.core.exact_mismatch import MismatchBlocks
    from fusionlog.core.exact_replay import replay_expected_blocks
    from fusionlog.driver.long_log import edges
    from fusionlog.stages.evaluator.long_mismatch import LongMismatchExact

    K1 = len(mask)
    blocks = replay_expected_blocks(model, truth, archs, K1 - 1, block)
    assert isinstance(blocks, MismatchBlocks)
    long = LongMismatchExact(blocks, mask, model.m, block)
    got: dict[str, dict[str, list]] = {a: {} for a in archs}
    for k0, k1 in edges(K1, block):
        for a, (ex, ratio) in long.window(k0, k1).items():
            for f in ("mse", "bias", "P", "nees", "dm"):
                got[a].setdefault(f, []).append(getattr(ex, f))
            got[a].setdefault("bound", []).append(ratio)
    out: dict[str, dict] = {a: {f: np.concatenate(v) for f, v in d.items()} for a, d in got.items()}
    for a in archs:
        out[a]["summary"] = long.bound_summary(a)
    return out


def _agree(got: np.ndarray, want: np.ndarray, what: str, scale: float | None = None) -> None:
    """Within RTOL of `scale` (default the largest entry of `want`; a bias: the errors' RMS,
    as it may be zero but for rounding)."""
    scale = max(float(np.abs(want).max()), 1e-300) if scale is None else scale
    np.testing.assert_allclose(got, want, rtol=0, atol=RTOL * scale, err_msg=what)


@pytest.mark.parametrize("kind", ["noise", "initial", "dynamics"])
def test_blocks_equal_the_whole_log_s_analysis(kind) -> None:
    """400 instants in blocks of 70, every architecture (SKF on each sensor, ICI and EI too):
    as the plans' analysis of the whole log (`exact.analyse`), the bound check's worst instant
    the same."""
    from fusionlog.core.bound import bound_summary
    from fusionlog.core.exact import analyse
    from fusionlog.driver import PlanCache

    model, times, mask = _model(400)
    truth = _truth(model, times, kind)
    got = _blocked(model, truth, ARCHS, mask, 70)
    cache = PlanCache(model, 399)
    for a in ARCHS:
        whole = analyse(cache.plan(a, mask), truth)
        rms = math.sqrt(np.abs(whole.mse).max())
        for f in ("mse", "bias", "P", "nees", "dm"):
            _agree(got[a][f], getattr(whole, f), f"{kind} {a} {f}", rms if f == "bias" else None)
        _agree(got[a]["bound"], whole.bound, f"{kind} {a} bound")
        want, have = bound_summary(whole.bound), got[a]["summary"]
        assert have["worst_step"] == want["worst_step"] and have["holds"] == want["holds"], a
        assert math.isclose(have["worst"], want["worst"], rel_tol=RTOL), a
    # the truth is not the model: the errors are biased or their covariance is not P
    assert np.abs(got["CKF"]["bias"]).max() > 1e-3 or np.abs(got["CKF"]["bound"] - 1).max() > 0.01


@pytest.mark.parametrize("kind", ["noise", "initial", "dynamics"])
def test_blocks_equal_superposition_of_the_references(kind) -> None:
    """120 instants in blocks of 25 (F, Q per interval; a constant R, which the references
    take): bias, MSE matrix and reported covariance of CKF, FBS, HKF, MSC-GMF, AVG and SKF
    against the references' estimators run on the basis runs of the truth (`references.
    exact_by_superposition`: the error is affine in the noises)."""
    from references import exact_by_superposition

    model, times, mask = _model(120, varying_r=False)
    truth = _truth(model, times, kind)
    archs = ["CKF", "FBS", "HKF", "MSC-GMF", "AVG", "SKF:s2"]
    got = _blocked(model, truth, archs, mask, 25)
    for a in archs:
        bias, mse, cov = exact_by_superposition(model, truth, a, mask)
        _agree(got[a]["bias"], bias, f"{kind} {a} bias", math.sqrt(np.abs(mse).max()))
        _agree(got[a]["mse"], mse, f"{kind} {a} mse")
        _agree(got[a]["P"], cov, f"{kind} {a} P")


def test_ckf_against_the_joint_of_truth_and_estimate_written_here() -> None:
    """The CKF under other dynamics, H, noise and initial distribution: the covariance of
    Z = [x; x_hat] propagated here from the formulas, Z_k = A_k Z_{k-1} + [I; K H_t] w + [0;
    K] v with A_k = [[F_t, 0], [K H_t F_t, (I - K H) F]] (K the model's gain over the present
    rows), e = [I, -I] Z."""
    model, times, mask = _model(150)
    truth = _truth(model, times, "dynamics")
    truth = dataclasses.replace(truth, initial=Prior(np.array([1.0, 0.0, -1.0]), 3 * np.eye(3)))
    got = _blocked(model, truth, ["CKF"], mask, 40)["CKF"]
    n, H, Ht = model.n, model.linear_measurement(), truth.linear_measurement()
    P = model.prior.cov
    init = truth.truth_initial
    mu = np.concatenate([init.mean, model.prior.mean])
    C = np.zeros((2 * n, 2 * n))
    C[:n, :n] = init.cov
    E = np.hstack([np.eye(n), -np.eye(n)])
    for k in range(len(mask)):
        F, Ft = (model.F_at(k), truth.F_at(k)) if k else (np.eye(n), np.eye(n))
        Q, Qt = (model.GQG_at(k), truth.GQG_at(k)) if k else (np.zeros((n, n)),) * 2
        Pp = F @ P @ F.T + Q
        r = np.flatnonzero(mask[k])
        R = model.R_at(k)[np.ix_(r, r)]
        Kg = np.zeros((n, model.m))
        Kg[:, r] = Pp @ H[r].T @ np.linalg.inv(H[r] @ Pp @ H[r].T + R)
        IKH = np.eye(n) - Kg @ H
        P = IKH @ Pp @ IKH.T + Kg[:, r] @ R @ Kg[:, r].T
        A = np.block([[Ft, np.zeros((n, n))], [Kg @ Ht @ Ft, IKH @ F]])
        Bw, Bv = np.vstack([np.eye(n), Kg @ Ht]), np.vstack([np.zeros((n, model.m)), Kg])
        Rt = np.zeros_like(truth.R_at(k))
        Rt[np.ix_(r, r)] = truth.R_at(k)[np.ix_(r, r)]
        mu, C = A @ mu, A @ C @ A.T + Bw @ Qt @ Bw.T + Bv @ Rt @ Bv.T
        bias = E @ mu
        mse = E @ C @ E.T + np.outer(bias, bias)
        scale = np.abs(mse).max()
        np.testing.assert_allclose(got["bias"][k], bias, rtol=0, atol=RTOL * math.sqrt(scale))
        np.testing.assert_allclose(got["mse"][k], mse, rtol=0, atol=RTOL * scale, err_msg=str(k))
        np.testing.assert_allclose(got["P"][k], P, rtol=0, atol=RTOL * np.abs(P).max())


def _peak(K1: int, block: int) -> int:
    """The peak of the Python allocations (tracemalloc) while the exact values of a log of
    K1 instants (its model, truth and mask made before) are computed in blocks of time, FBS's
    backward pass included, each block's values dropped as the evaluator does."""
    import tracemalloc

    from fusionlog.core.exact_replay import replay_expected_blocks
    from fusionlog.driver.long_log import edges
    from fusionlog.stages.evaluator.long_mismatch import LongMismatchExact

    model, times, mask = _model(K1)
    truth = _truth(model, times, "dynamics")
    archs = ["CKF", "HKF", "MSC-GMF", "SKF:s1", "FBS"]
    tracemalloc.start()
    try:
        long = LongMismatchExact(
            replay_expected_blocks(model, truth, archs, K1 - 1, block), mask, model.m, block
        )
        for k0, k1 in edges(K1, block):
            assert set(long.window(k0, k1)) == set(archs)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_peak_memory_does_not_grow_with_the_instants() -> None:
    """Blocks of 200 instants: four times the instants, the same peak within 10 % (the whole
    log's plans keep every instant's maps and moments: its peak grows fourfold)."""
    _peak(400, 200)  # what is imported on first use
    p1, p2 = _peak(800, 200), _peak(3_200, 200)
    assert p2 <= 1.1 * p1, (p1, p2)


# -- the CLI ----------------------------------------------------------------------------------


def _fusionlog(folder: Path, block: int | None, *args) -> int:
    """`fusionlog ARGS` in `folder` (relative outputs: the provenance's command is the same text
    whole and blocked) in blocks of time of `block` instants (None: the default, longer than
    these logs); how many times the blocked route was entered."""
    from fusionlog.core import exact_mismatch

    folder.mkdir(exist_ok=True)
    with pytest.MonkeyPatch.context() as m:
        m.chdir(folder)
        time_block(m, block)
        calls = count_calls(m, exact_mismatch, "mismatch_blocks")
        ok(*args)
        return calls.count


def _close(a, b) -> None:
    """Summaries equal to RTOL; the bound's worst ratio to 1e-7 (the plans' analysis of
    MSC-GMF on multirate's correlated radar and odometer leaves 4e-8 there, test_long_rest)."""
    summaries_close(a, b, rtol=RTOL, atol=1e-12, nan=True, bound_rtol=1e-7)


def _multirate(folder: Path, extra: str = "", **changes: str) -> Path:
    """multirate (radar 1 Hz, GNSS 5 Hz offset 50 ms, odometer 10 Hz: irregular instants, F
    and Q per interval) with 20 % of the GNSS readings lost, its seven architectures and AVG,
    `changes` (old text: new text) made and `extra` appended."""
    text = (PIPELINE / "multirate.toml").read_text()
    changes = {"period = 0.2\noffset = 0.05\n": "period = 0.2\noffset = 0.05\ndropout = 0.2\n",
               '"CI", "FBS"]': '"CI", "FBS", "AVG", "SKF:radar"]', **changes}  # fmt: skip
    for old, new in changes.items():
        assert old in text, old
        text = text.replace(old, new)
    path = folder / "scenario.toml"
    folder.mkdir(exist_ok=True)
    path.write_text(text + extra)
    return path


def _summaries(tmp: Path, block: int, *commands) -> tuple[dict, dict]:
    """The commands run whole and in blocks of `block` instants (the last writes summary.json);
    the two summaries, having checked that only the blocked run took the blocked route."""
    out = []
    for name, b in (("whole", None), ("blocked", block)):
        calls = sum(_fusionlog(tmp / name, b, *c) for c in commands)
        assert calls == (b is not None), (name, calls)
        out.append(json.loads((tmp / name / "summary.json").read_text()))
    for a, entry in out[0]["architectures"].items():
        assert entry["expected"]["mse"] > 0 and "bound" in entry, a
    return out[0], out[1]


def test_a_simulated_run_estimated_with_another_model(tmp_path) -> None:
    """multirate with dropouts, 300 instants, estimated with `--model` (n0 3 instead of 2, the
    GNSS's R doubled), evaluated whole and in blocks of 70 instants: the same summary."""
    scenario = _multirate(tmp_path)
    model = _multirate(tmp_path / "m", **{"n0 = 2.0": "n0 = 3.0",
                                          "R = [[1.0, 0.0], [0.0, 1.0]]":
                                          "R = [[2.0, 0.0], [0.0, 2.0]]"})  # fmt: skip
    sim = ("simulate", scenario, "--runs", "1", "--steps", "300", "-o", "s.mcap")
    est = ("estimate", "s.mcap", "--model", model, "-o", "e.mcap")
    ev = ("evaluate", "s.mcap", "e.mcap", "-o", "ev.rrd", "--summary", "summary.json")
    whole, blocked = _summaries(tmp_path, 70, sim, est, ev)
    _close(blocked, whole)
    # the model is not the truth: the CKF's P is not its error covariance (E[ANEES] 1 if it were)
    assert abs(whole["architectures"]["CKF"]["expected"]["anees"] - 1) > 0.05


def test_a_scenario_whose_truth_is_not_its_prior(tmp_path) -> None:
    """multirate with dropouts and a `[truth]` (the true x_0 drawn elsewhere than the filters'
    prior says), `run --runs 1 --steps 300` whole and in blocks of 70 instants."""
    truth = ("\n[truth]\ninitial_mean = [8.0, 6.0, -5.0, 1.0]\n"
             "initial_cov = [[64.0, 0.0, 0.0, 0.0], [0.0, 9.0, 0.0, 0.0], "
             "[0.0, 0.0, 36.0, 0.0], [0.0, 0.0, 0.0, 1.0]]\n")  # fmt: skip
    scenario = _multirate(tmp_path, truth)
    run = ("run", scenario, "--runs", "1", "--steps", "300", "--out-dir", ".", "--force")
    whole, blocked = _summaries(tmp_path, 70, run)
    _close(blocked, whole)
    assert not whole["architectures"]["CKF"]["bound"]["holds"]  # the prior is too small


def test_a_replayed_log_estimated_with_another_model(tmp_path) -> None:
    """replay_robot (ROS 2 odometry and poses with a covariance per message, a motion-capture
    CSV; 2292 irregular instants, a truth of the positions) estimated with `--model` (n0, the
    prior and the motion capture's R other than the replay's), in blocks of 500 instants."""
    from test_long_replay import ARCHS as ROBOT_ARCHS
    from test_long_replay import _robot_partial

    replay = _robot_partial(tmp_path)
    model = tmp_path / "model.toml"
    model.write_text("""[scenario]
name = "robot_model"
state_names = ["px", "vx", "py", "vy"]
dt = 1.0
steps = 1
runs = 1

[model]
kind = "constant-velocity"
axes = 2
n0 = 0.05

[prior]
mean = [0.0, 0.0, 0.0, 0.0]
cov = [[0.25, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 0.25, 0.0], [0.0, 0.0, 0.0, 2.0]]

[[sensors]]
name = "odom"
H = [[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
R = [[0.0025, 0.0], [0.0, 0.0025]]

[[sensors]]
name = "pose"
H = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
R = [[0.01, 0.0], [0.0, 0.01]]

[[sensors]]
name = "mocap"
H = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
R = [[0.0004, 0.0], [0.0, 0.0004]]
""")
    arch = [x for a in ROBOT_ARCHS for x in ("--arch", a)]
    imp = ("import", replay, "-o", "s.mcap")
    est = ("estimate", "s.mcap", "--model", model, "-o", "e.mcap", *arch)
    ev = ("evaluate", "s.mcap", "e.mcap", "-o", "ev.rrd", "--summary", "summary.json")
    whole, blocked = _summaries(tmp_path, 500, imp, est, ev)
    _close(blocked, whole)
    assert set(whole["architectures"]) == set(ROBOT_ARCHS)
