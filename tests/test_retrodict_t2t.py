"""Retrodiction (Bar-Shalom, Chen, Mallick 2004, Al1) where a late sensor is fused by more than
one filter (issue 30): the hierarchical KF's centre, and each local filter of the track-to-track
architectures, whose registered rule then fuses the locals' estimates.

References written here from the formulas: one Al1 filter per sensor (`al1` of test_latency,
event-driven on that sensor's arrivals) with Millman's formula (MSC) and covariance
intersection (CI: the weight minimising tr P by a bounded scalar search); for HKF the centre
in information form, receiving each local's equivalent measurement H^T R^-1 z, H^T R^-1 H and
retrodicting it as x(k|d) = x(k|k) + C (I + I_d P(d|k))^-1 (i_d - I_d x(d|k)).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import ok
from scipy.optimize import minimize_scalar
from test_latency import RANDOM, H, al1, millman, retrodicted, scenario, transition

import fusionlog as fl

T2T = ("MSC", "MSC-GMF", "CI", "AVG", "ICI", "EI")


def arrivals(sim, run, S):
    """(i, j) -> the first instant t_k >= the reading's arrival (whole nanoseconds)."""
    K = len(sim.times) - 1
    tk = np.round(sim.times * 1e9)
    out = {}
    for j in range(S):
        arr = sim.arrival.get(f"s{j + 1}")
        for i in range(K + 1):
            a = tk[i] if arr is None else round(arr[run, i] * 1e9)
            out[i, j] = int(np.searchsorted(tk, a))
    return out


def local_al1(z, arrive, K, R, j):
    """Local j: Al1 on sensor j's readings alone."""
    return al1([z[j]], {(i, 0): arrive[i, j] for i in range(K + 1)}, K, [R[j]], 4)


def ci_two(a, b):
    """Covariance intersection of two estimates: w in [0, 1] minimising tr P, P^-1 = w Pa^-1
    + (1 - w) Pb^-1, x = P (w Pa^-1 xa + (1 - w) Pb^-1 xb)."""
    (xa, Pa), (xb, Pb) = a, b
    Ya, Yb = np.linalg.inv(Pa), np.linalg.inv(Pb)

    def fused(w):
        P = np.linalg.inv(w * Ya + (1 - w) * Yb)
        return P @ (w * Ya @ xa + (1 - w) * Yb @ xb), P

    w = minimize_scalar(
        lambda w: np.trace(fused(w)[1]), bounds=(0, 1), method="bounded",
        options={"xatol": 1e-12},
    ).x  # fmt: skip
    # the bounded search stops short of a vertex: take it where it is the minimum
    best = min((0.0, 1.0, w), key=lambda w: np.trace(fused(w)[1]))
    return (*fused(best), best)


@pytest.mark.parametrize("lats", [(None, 3.0, 1.0), RANDOM])
def test_msc_fuses_locals_each_retrodicting_its_own_readings(tmp_path, lats):
    R = (1.0, 1.0, 0.5)
    path = scenario(tmp_path, latencies=lats, R=R, late="retrodict", archs=("MSC",), runs=3)
    sim = fl.simulate(path)
    est = fl.estimate(path, sim, ["MSC"])["MSC"]
    K = len(sim.times) - 1
    for run in range(3):
        z = [sim.measurements[f"s{j + 1}"][run, :, 0] for j in range(3)]
        arrive = arrivals(sim, run, 3)
        locs = [local_al1(z, arrive, K, R, j) for j in range(3)]
        for k in range(K + 1):
            x, P = millman([loc[k] for loc in locs])
            np.testing.assert_allclose(est.mean[run, k], x, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(est.cov[run, k], P, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    "lats, R, interior",
    [((1.0, 3.0), (4.0, 0.01), False), (("{ min = 1.0, max = 3.0 }", None), (0.02, 2.0), True)],
)
def test_ci_fuses_locals_each_retrodicting_its_own_readings(tmp_path, lats, R, interior):
    """The weight moves from one local to the other as the late one's readings arrive (first
    case), and is strictly between them at some instants (second)."""
    path = scenario(tmp_path, latencies=lats, R=R, late="retrodict", archs=("CI",), runs=3)
    sim = fl.simulate(path)
    est = fl.estimate(path, sim, ["CI"])["CI"]
    K = len(sim.times) - 1
    weights = []
    for run in range(3):
        z = [sim.measurements[f"s{j + 1}"][run, :, 0] for j in range(2)]
        arrive = arrivals(sim, run, 2)
        locs = [local_al1(z, arrive, K, R, j) for j in range(2)]
        for k in range(K + 1):
            x, P, w = ci_two(locs[0][k], locs[1][k])
            weights.append(w)
            # the weight is found to ~1e-9 by both searches: the mean (~100) to ~1e-7
            np.testing.assert_allclose(est.mean[run, k], x, rtol=0, atol=1e-6)
            np.testing.assert_allclose(est.cov[run, k], P, rtol=1e-6, atol=1e-9)
    w = np.array(weights)
    assert interior or ((w == 0).any() and (w == 1).any())
    assert ((0.01 < w) & (w < 0.99)).any() == interior


def hkf_al1(z, arrive, K, R, W=4):
    """The HKF centre, event-driven, in information form: locals restarted from the fused
    prediction hand it their equivalent measurements; an older one is retrodicted (Al1, the
    updates since the newest stored estimate at or before its time as one measurement of
    x_k)."""
    groups = {}
    for j in range(len(R)):
        for i in range(K + 1):
            groups.setdefault((arrive[i, j], i), []).append(j)
    x, P, t = np.array([100.0, -1.0]), np.eye(2), 0
    stored = {0: (x, P)}
    out = []
    for k in range(K + 1):
        for i in sorted(i for a, i in groups if a == k):
            js = groups[k, i]
            Id = sum(H.T @ H / R[j] for j in js)  # the locals' equivalent measurements
            i_d = sum(H.T[:, 0] * z[j][i] / R[j] for j in js)
            if i >= t:
                Fi, Qi = transition(t, i)
                xp, Pp, t = Fi @ x, Fi @ P @ Fi.T + Qi, i
                Yp = np.linalg.inv(Pp)
                # each local: P_j^-1 x_j = Yp xp + H^T R^-1 z; the centre adds P_j^-1 x_j - Yp xp
                Y = Yp + Id
                P = np.linalg.inv(Y)
                x = P @ (Yp @ xp + i_d)
            else:
                xd, Pd, C = retrodicted(x, P, stored, i, t)  # C = cov(x_k, x_d)
                G = C @ np.linalg.inv(np.eye(2) + Id @ Pd)
                x = x + G @ (i_d - Id @ xd)
                P = P - G @ Id @ C.T
            stored[t] = (x, P)
        Fo, Qo = transition(t, k)
        out.append((Fo @ x, Fo @ P @ Fo.T + Qo))
    return out


@pytest.mark.parametrize("lats", [(None, 2.0), (None, 3.0, 1.0), RANDOM])
def test_hkf_centre_retrodicts_the_locals_equivalent_measurements(tmp_path, lats):
    R = (1.0, 0.5, 0.5)[: len(lats)]
    S = len(lats)
    path = scenario(tmp_path, latencies=lats, R=R, late="retrodict", archs=("HKF",), runs=3)
    sim = fl.simulate(path)
    est = fl.estimate(path, sim, ["HKF"])["HKF"]
    K = len(sim.times) - 1
    for run in range(3):
        z = [sim.measurements[f"s{j + 1}"][run, :, 0] for j in range(S)]
        for k, (x, P) in enumerate(hkf_al1(z, arrivals(sim, run, S), K, R)):
            np.testing.assert_allclose(est.mean[run, k], x, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(est.cov[run, k], P, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("lats", [(1.0, None, 2.5), RANDOM])
def test_retrodict_exact_equals_monte_carlo_in_every_architecture(tmp_path, lats):
    archs = ("CKF", "SKF:s3", "HKF") + T2T
    path = scenario(tmp_path, latencies=lats, late="retrodict", archs=archs, runs=2000, steps=8)
    sim = fl.simulate(path)
    summary = fl.evaluate(path, sim, fl.estimate(path, sim)).summary
    assert summary["late"] == "retrodict"
    assert set(summary["architectures"]) == set(archs)
    for a, s in summary["architectures"].items():
        assert s["expected"].get("conditional", False) is (lats == RANDOM)
        for key in ("mse", "anees"):
            gap = abs(s[key] - s["expected"][key])
            assert gap <= 4 * s["stderr"][key], (a, key, s[key], s["expected"][key])
    # MSC-GMF and AVG report C J C^T: with the locals' joint error covariance J right, that is
    # their true error covariance (the exact analysis's, `core.moments`) at every instant
    for a in ("MSC-GMF", "AVG"):
        assert summary["architectures"][a]["bound"]["worst"] == pytest.approx(1, abs=1e-8)


def test_retrodict_with_zero_latency_changes_no_number(tmp_path):
    """latency = 0 is on time whatever the policy: the summary of every architecture equals
    the one without latencies, bit for bit."""
    archs = ("CKF", "HKF") + T2T
    a = scenario(tmp_path, latencies=(0.0, 0, None), late="retrodict", archs=archs, name="a")
    b = scenario(tmp_path, latencies=(None, None, None), late="retrodict", archs=archs, name="b")
    out = {}
    for p in (a, b):
        ok("run", p, "--out-dir", tmp_path / p.stem)
        out[p.stem] = json.loads((tmp_path / p.stem / "summary.json").read_text())
    out["a"]["scenario"] = "b"
    assert out["a"] == out["b"]


def test_joint_covariance_of_retrodicting_locals_with_correlated_sensors(tmp_path):
    """s1 and s2 correlated (same latency): the locals' joint error covariance J carries
    K_1 R_12 K_2^T through the retrodictions; MSC-GMF's and AVG's C J C^T are then their true
    error covariance (the exact analysis's), which without the cross term they would not be."""
    path = scenario(tmp_path, latencies=(2.0, 2.0, None), late="retrodict",
                    archs=("MSC-GMF", "AVG"), runs=50, steps=8)  # fmt: skip
    with path.open("a") as f:
        f.write('\n[[correlations]]\nsensors = ["s1", "s2"]\ncov = [[0.6]]\n')
    sim = fl.simulate(path)
    summary = fl.evaluate(path, sim, fl.estimate(path, sim)).summary
    for a in ("MSC-GMF", "AVG"):
        assert summary["architectures"][a]["bound"]["worst"] == pytest.approx(1, abs=1e-8)


def test_retrodicting_locals_do_not_depend_on_the_blocks_of_runs(tmp_path):
    """Random delays: each block of runs builds its runs' retrodicting locals (and their joint
    covariance) from its own arrivals; the summary is that of one block."""
    path = scenario(tmp_path, latencies=RANDOM, late="retrodict", runs=40,
                    archs=("HKF", "MSC-GMF", "CI"))  # fmt: skip
    ok("run", path, "--out-dir", tmp_path / "a")
    ok("run", path, "--out-dir", tmp_path / "b", "--block-runs", "7")
    a, b = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("a", "b"))
    for arch, s in a["architectures"].items():
        t = b["architectures"][arch]
        assert t["mse"] == pytest.approx(s["mse"], rel=1e-9)
        assert t["expected"]["mse"] == pytest.approx(s["expected"]["mse"], rel=1e-9)
