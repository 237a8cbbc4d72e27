"""Issue 34: retrodiction (``late = "retrodict"``) of a long one-run log in blocks of time where
no short steady plans stand for it -- delays drawn per reading, a recorded replay's arrivals,
missing readings, and the rules reading J where the error form is 0 (`core.retrodict_blocks`:
each block's plans from the gain recursions carried, the plans' state and the exact moments
carried).

The whole log taken at once is the reference: its plans over the whole run, whose filters are
checked against Al1 written from the formulas in tests/test_latency.py and
test_retrodict_t2t.py; and here, independently, a per-run Al1 written from Bar-Shalom, Chen and
Mallick (2004) on a log with drawn delays and missing readings, against the blocked estimates.
Blocks of 50 instants (the hidden setting FUSIONLOG_TIME_BLOCK) cut a log of 600, so readings
taken before an edge arrive after it (lags of 1 to 3 instants). Blocked and whole build the
same maps (the covariances to the bit); the means differ by where the recursion is cut, the
exact values by the route (nees_and_dm_many against the shared one: `test_long_late_random`'s
tolerances).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from long_helpers import (
    LATE_SENSORS,
    OfLargest,
    Spy,
    estimates_close,
    late_toml,
    summaries,
    time_block,
    whole_and_blocked,
)
from test_long_late_random import RECORDED_ARCHS, RTOL, STEPS, _close, _recorded, _scenario

from fusionlog.core.retrodict_blocks import RetroBlocks
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.arrival import read_arrivals

BLOCK = 50
ALL = ["CKF", "HKF", "SKF:s3", "MSC", "MSC-GMF", "CI", "AVG", "ICI", "EI"]

#: (name, s3's latency, missing readings, s1 and s3 correlated, architectures)
CASES = [
    ("random delays, missing readings", "{min = 1.0, max = 3.0}", True, False, ALL),
    ("random delays", "{min = 1.0, max = 3.0}", False, False, ["CKF", "SKF:s3", "AVG"]),
    ("fixed latencies, missing readings", "3.0", True, False, ["CKF", "HKF", "MSC-GMF"]),
]  # correlated readings arriving apart: retrodiction refuses them (Al1 takes them independent)


def _spy(mp: pytest.MonkeyPatch) -> Spy:
    """Counts the blocks of time the retrodiction path estimated and evaluated."""
    calls = {"estimated": (RetroBlocks, "estimates"), "exact": (RetroBlocks, "error_covariances")}
    return Spy(mp, calls=calls)


def _whole_and_blocked(path: Path, tmp: Path, horizons=None) -> tuple[Path, Path, Spy]:
    """The log run whole and in blocks of `BLOCK` (`horizons`: the steady plans' horizons of
    the blocked run, `long_log.HORIZONS`)."""
    return whole_and_blocked(path, tmp, BLOCK, horizons=horizons, spy=_spy)


def _same_estimates(whole: Path, blocked: Path, archs: list[str]) -> None:
    """Means to rounding of the largest (`test_long_late_random.RTOL`), covariances too (the
    same maps: in practice to the bit)."""
    estimates_close(whole, blocked, archs, mean=OfLargest(RTOL), cov=OfLargest(RTOL))


@pytest.fixture(scope="module", params=CASES, ids=lambda c: c[0])
def runs(tmp_path_factory, request):
    """One case's log of 600 instants retrodicted whole and in blocks of 50."""
    name, s3, missing, correlated, archs = request.param
    tmp = tmp_path_factory.mktemp("retro-blocks")
    path = _scenario(tmp, s3, missing, correlated, "retrodict", archs=archs)
    whole, blocked, spy = _whole_and_blocked(path, tmp)
    return name, archs, whole, blocked, spy


def test_retrodiction_went_in_blocks(runs) -> None:
    """The estimate stage and the exact analysis took the log's 12 blocks of time."""
    spy = runs[-1]
    assert (spy.estimated, spy.exact) == (12, 12)


def test_blocked_estimates_equal_the_whole_log(runs) -> None:
    """Every architecture's means and covariances across edges that late readings cross."""
    _, archs, whole, blocked, _ = runs
    _same_estimates(whole, blocked, archs)


def test_blocked_summary_equals_the_whole_log(runs) -> None:
    """The Monte Carlo metrics, the exact values (conditional on the drawn delays where they
    are drawn), NEES/DM and the bound check as from the whole log's plans."""
    name, archs, whole, blocked, _ = runs
    a, b = summaries(whole, blocked)
    _close(b, a)
    assert b["late"] == "retrodict"
    for arch in archs:
        ex = b["architectures"][arch]["expected"]
        assert ex["mse"] is not None and ex.get("conditional", False) == ("random" in name)


def test_a_recorded_replay_retrodicted_in_blocks_equals_the_whole_log(tmp_path) -> None:
    """A replay whose late sensor's arrivals are its messages' log times, a fifth of its
    readings missing (600 instants): estimates and summary as the whole log's."""
    path = _recorded(tmp_path, "retrodict", gaps=True)
    whole, blocked, spy = _whole_and_blocked(path, tmp_path)
    K1 = McapFile(whole / "sensors.mcap").steps()
    assert spy.estimated == -(-K1 // BLOCK) > 1
    # a random walk of std < 10: 1e-12 absolute
    estimates_close(whole, blocked, RECORDED_ARCHS, mean=(0, 1e-12), cov=(0, 1e-12))
    sa, sb = summaries(whole, blocked)
    _close(sb, sa)


# --- J where the error form is 0 ------------------------------------------------------------

#: velocity damped by 1e-3 a step
ILL_MODEL = "F = [[1.0, 1.0], [0.0, 0.001]]\nQ = [[0.05, 0.0], [0.0, 1.0]]"


def test_j_where_the_error_form_is_zero_goes_in_blocks(tmp_path) -> None:
    """A transition over the latency window ill-conditioned (velocity damped by 1e-3 a step:
    cond F^3 > 1e8, so D's blocks of lag 3 are 0 and J carries the position's growing
    variance: no steady middle), fixed latencies, every reading present, steady plans of 64
    instants tried (a log longer than the horizons): it goes in blocks, and the estimates and
    the summary (MSE, NEES, DM, exact values) are the whole log's plans'."""
    F = np.array([[1.0, 1.0], [0.0, 0.001]])
    assert np.linalg.cond(np.linalg.matrix_power(F, 3)) > 1e8  # the premise: D = 0 there
    path = tmp_path / "ill.toml"
    archs = ["CKF", "MSC-GMF", "AVG"]
    path.write_text(late_toml("retro_ill", 343, STEPS, LATE_SENSORS, archs, "retrodict", ILL_MODEL))
    whole, blocked, spy = _whole_and_blocked(path, tmp_path, horizons=(64,))
    assert (spy.estimated, spy.exact) == (12, 12)
    _same_estimates(whole, blocked, ["CKF", "MSC-GMF", "AVG"])
    a, b = summaries(whole, blocked)
    _close(b, a)
    assert b["architectures"]["MSC-GMF"]["expected"]["mse"] is not None


# --- an independent reference: Al1 per run, from the formulas --------------------------------


def _al1(z, arrive, F, Q, R, prior):
    """Bar-Shalom, Chen, Mallick (2004), Al1, event-driven on one run: at each instant k the
    readings arriving then, by their instant i in order, those of one instant as one vector
    measurement; i at or after the last update t: predict and update; i < t: the updates since
    the newest estimate stored at or before i as one equivalent measurement of x_t, the reading
    retrodicted to i. `z[j]` (K+1,) NaN where missing, `arrive[j]` (K+1,) instant indices."""
    K1 = len(z[0])

    def trans(a, b):
        Fab, Qab = np.eye(2), np.zeros((2, 2))
        for _ in range(b - a):
            Fab, Qab = F @ Fab, F @ Qab @ F.T + Q
        return Fab, Qab

    x, P, t = prior[0].copy(), prior[1].copy(), 0
    stored = {0: (x, P)}
    out = []
    h = np.array([[1.0, 0.0]])
    for k in range(K1):
        here = sorted({i for j in range(3) for i in range(K1) if arrive[j][i] == k})
        for i in here:
            js = [j for j in range(3) if arrive[j][i] == k and not np.isnan(z[j][i])]
            if not js:
                continue
            Hd = np.vstack([h] * len(js))
            Rd = np.diag([R[j] for j in js])
            zi = np.array([z[j][i] for j in js])
            if i >= t:
                Fi, Qi = trans(t, i)
                x, P, t = Fi @ x, Fi @ P @ Fi.T + Qi, i
                S = Hd @ P @ Hd.T + Rd
                G = P @ Hd.T @ np.linalg.inv(S)
                x = x + G @ (zi - Hd @ x)
                IGH = np.eye(2) - G @ Hd
                P = IGH @ P @ IGH.T + G @ Rd @ G.T
            else:
                a = max(s for s in stored if s <= i)
                xa, Pa = stored[a]
                Fa, Qa = trans(a, t)
                Pp = Fa @ Pa @ Fa.T + Qa
                Ppi = np.linalg.inv(Pp)
                Ainv = Ppi @ (Pp - P) @ Ppi
                g = Ppi @ (x - Fa @ xa)
                Fkd, Qkd = trans(i, t)
                Fdk = np.linalg.inv(Fkd)
                xd = Fdk @ (x - Qkd @ g)
                Pxv = Qkd - Pp @ Ainv @ Qkd
                Pvv = Qkd - Qkd @ Ainv @ Qkd
                Pd = Fdk @ (P + Pvv - Pxv - Pxv.T) @ Fdk.T
                Pxz = (P - Pxv) @ Fdk.T @ Hd.T
                Sd = Hd @ Pd @ Hd.T + Rd
                G = Pxz @ np.linalg.inv(Sd)
                x = x + G @ (zi - Hd @ xd)
                P = P - G @ Pxz.T
            stored[t] = (x, P)
        Fo, Qo = trans(t, k)
        out.append((Fo @ x, Fo @ P @ Fo.T + Qo))
    return out


def test_blocked_retrodiction_is_al1_from_the_formulas(tmp_path, monkeypatch) -> None:
    """CKF retrodicting s2 (1 s late, every second instant) and s3 (1 to 3 s, drawn; 30 %
    missing), s1 on time with 20 % missing, 120 instants in blocks of 25: each estimate and
    covariance is Al1's written here (1e-9: a contractive recursion's roundings)."""
    from fusionlog.scenario import load_scenario

    path = _scenario(tmp_path, "{min = 1.0, max = 3.0}", True, False, "retrodict", steps=119,
                     archs=["CKF"])  # fmt: skip
    time_block(monkeypatch, 25)
    spy = _spy(monkeypatch)
    ok("run", path, "--out-dir", tmp_path / "o", "--force")
    assert spy.estimated == 5
    system = load_scenario(path).system
    topics = ["/sensors/s1", "/sensors/s2", "/sensors/s3"]
    sensors = McapFile(tmp_path / "o" / "sensors.mcap")
    z = [sensors.read_all(topics)[t][0, :, 0] for t in topics]
    times = sensors.times()
    tk = np.round(times * 1e9)
    got = read_arrivals(tmp_path / "o" / "sensors.mcap", topics, 1, len(times))
    arrive = []
    for t in topics:
        a = tk if got[t] is None else np.round(got[t][0] * 1e9)
        arrive.append(np.searchsorted(tk, np.where(np.isnan(a), np.inf, a)))
    assert any(np.isnan(zj).any() for zj in z) and (arrive[2] - np.arange(len(tk)) >= 1).all()
    R = [1.0, 2.0, 0.5]
    prior = (np.array([100.0, -1.0]), np.eye(2))
    ref = _al1(z, arrive, system.F, system.GQG, R, prior)
    est = McapFile(tmp_path / "o" / "estimates.mcap").read_all(["/estimates/CKF"])
    mean, cov = est["/estimates/CKF"]
    for k, (x, P) in enumerate(ref):
        np.testing.assert_allclose(mean[0, k], x, rtol=1e-9, atol=1e-9, err_msg=str(k))
        np.testing.assert_allclose(cov[k], P, rtol=1e-9, atol=1e-12, err_msg=str(k))


# --- memory ---------------------------------------------------------------------------------


@pytest.mark.memory
@pytest.mark.parametrize("what", ["estimates", "error_covariances"])
def test_peak_is_independent_of_the_log_s_length(tmp_path, what) -> None:
    """`RetroBlocks` (CKF and MSC-GMF, drawn delays, a fifth of the readings missing) on 3000
    instants in blocks of 500 holds what a block needs: its traced peak is that of 1000
    instants within 10 % (the whole run holds the maps of every step, ~3 kB an instant)."""
    import tracemalloc

    from fusionlog.scenario import load_scenario

    archs = ["CKF", "MSC-GMF"]
    path = _scenario(tmp_path, "{min = 1.0, max = 3.0}", True, False, "retrodict", archs=archs)
    system = load_scenario(path).system
    rng = np.random.default_rng(5)
    peaks = []
    for K in (999, 2999):
        times = np.arange(K + 1, dtype=float)
        blocks = RetroBlocks.of(system, archs, K, times, 500)
        tracemalloc.start()
        try:
            for k0 in range(0, K + 1, 500):
                w = min(500, K + 1 - k0)
                arrival = np.repeat(times[k0 : k0 + w, None], 3, axis=1)
                arrival[:, 1] += 1.0
                arrival[:, 2] += rng.uniform(1.0, 3.0, w)
                z = np.where(rng.random((w, 3)) > 0.2, rng.normal(size=(w, 3)), np.nan)
                if what == "estimates":
                    blocks.estimates(k0, k0 + w, z, arrival)
                else:
                    blocks.error_covariances(k0, k0 + w, ~np.isnan(z), arrival)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    assert peaks[1] <= 1.1 * peaks[0], peaks
