"""Issue 30 in the EKF/UKF lanes: late sensors under reprocess, neglect and retrodict
(DESIGN.md "Late measurements"; `core.nonlinear.late`, `core.nonlinear.retrodict`).

References written here, one run at a time, from the definitions:
reprocess = an EKF (UKF) run from scratch at every output instant on exactly the readings that
have arrived by then; neglect = an event-driven filter that takes the arrivals in order,
drops one older than its last update and predicts to each output instant; retrodict with a
one-update lag = Bar-Shalom's Algorithm A (2002) with the EKF's Jacobians at the retrodicted
state. Arrivals: the first instant t_k >= the arrival time.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error

from fusionlog.core.architectures import Estimate
from fusionlog.core.model import Prior, System
from fusionlog.core.models import CoordinatedTurn, RangeBearingSensor
from fusionlog.core.nonlinear import estimate
from fusionlog.core.simulate import simulate
from fusionlog.core.timing import SensorTiming

PIPELINE = Path(__file__).resolve().parents[1] / "pipeline"
EPS = np.finfo(float).eps
K, M = 12, 4
TIMES = np.arange(K + 1.0)


def radar_system(turn: bool, filt: str, late: str, latency=(2.0, 2.0)) -> System:
    """Two range-bearing radars, 'a' on time and 'b' late by `latency` (s; a range: random),
    on a constant-velocity target (linear motion) or a coordinated turn."""
    a = RangeBearingSensor("a", np.array([0.0, 0.0]), (0, 2), 5, np.diag([25.0, 1e-3]))
    b = RangeBearingSensor("b", np.array([900.0, 100.0]), (0, 2), 5, np.diag([25.0, 1e-3]))
    b = dataclasses.replace(b, timing=SensorTiming(latency=latency))
    ct = CoordinatedTurn((0.1, 0.1), 1e-5)
    prior = Prior(np.array([300.0, 12.0, 400.0, -4.0, 0.04]), np.diag([100, 9, 100, 9, 1e-4]))
    if turn:
        F, Q = ct.jacobian(np.zeros(5), 1.0).copy(), ct.Q(1.0)
        return System(F, Q, (a, b), prior, motion_model=ct, filter=filt, late=late)
    F1, Q1 = np.array([[1.0, 1.0], [0.0, 1.0]]), 0.5 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    a, b = (dataclasses.replace(s, n=4) for s in (a, b))
    prior = Prior(prior.mean[:4], prior.cov[:4, :4])
    return System(np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1), (a, b), prior,
                  filter=filt, late=late)  # fmt: skip


def draw(system: System, seed: int, lo: float, hi: float, both: bool = False):
    """Readings of M runs, and their arrival times (M, K+1, 2) s: 'b' (and 'a' if `both`)
    delayed uniformly in [lo, hi]."""
    z = simulate(system, K, seed, 0, M)[1]
    rng = np.random.default_rng(seed)
    delay = np.stack([rng.uniform(lo, hi, (M, K + 1)) * both, rng.uniform(lo, hi, (M, K + 1))], -1)
    return z, TIMES[None, :, None] + delay


class Filter:
    """One run's EKF (`ukf` None) or UKF (alpha, beta, kappa) on stacked sensors. EKF:
    Jacobians at the prediction, Joseph update. UKF: points x, x +- columns of the lower
    Cholesky factor of (n + lambda) P, drawn afresh for each step; angle means on residuals
    about the central image; P+ = P - K S K^T."""

    def __init__(self, system: System, ukf=None) -> None:
        self.s, self.ukf = system, ukf

    def predict(self, x, P):
        motion = self.s.motion
        Q = motion.Q(1.0)
        if self.ukf is None or motion.linear:
            F = motion.jacobian(x, 1.0)
            return motion.f(x, 1.0), F @ P @ F.T + Q
        X, Wm, Wc = self.points(x, P)
        Y = np.array([motion.f(p, 1.0) for p in X])
        xp = Wm @ Y
        return xp, (Wc[:, None] * (Y - xp)).T @ (Y - xp) + Q

    def points(self, x, P):
        n = len(x)
        alpha, beta, kappa = self.ukf
        lam = alpha**2 * (n + kappa) - n
        L = np.linalg.cholesky((n + lam) * P)
        Wm = np.full(2 * n + 1, 1 / (2 * (n + lam)))
        Wc = Wm.copy()
        Wm[0], Wc[0] = lam / (n + lam), lam / (n + lam) + 1 - alpha**2 + beta
        return np.vstack([x, x + L.T, x - L.T]), Wm, Wc

    def update(self, x, P, readings):
        """readings: [(sensor, z)]."""
        sens = [s for s, _ in readings]
        z = np.concatenate([v for _, v in readings])
        R = np.zeros((len(z), len(z)))
        i = 0
        for s in sens:
            R[i : i + s.dim, i : i + s.dim] = s.R
            i += s.dim

        def h(v):
            return np.concatenate([s.h(v) for s in sens])

        def res(u, v):
            out, i = [], 0
            for s in sens:
                out.append(s.residual(u[i : i + s.dim], v[i : i + s.dim]))
                i += s.dim
            return np.concatenate(out)

        if self.ukf is None:
            H = np.concatenate([s.jacobian(x) for s in sens])
            S = H @ P @ H.T + R
            G = np.linalg.solve(S, H @ P).T
            A = np.eye(len(x)) - G @ H
            return x + G @ res(z, h(x)), A @ P @ A.T + G @ R @ G.T, (H, S, res(z, h(x)))
        X, Wm, Wc = self.points(x, P)
        Z = [h(p) for p in X]
        zhat = Z[0] + sum(w * res(zi, Z[0]) for w, zi in zip(Wm, Z, strict=True))
        dZ = np.array([res(zi, zhat) for zi in Z])
        S = (Wc[:, None] * dZ).T @ dZ + R
        G = np.linalg.solve(S, ((Wc[:, None] * (X - x)).T @ dZ).T).T
        return x + G @ res(z, zhat), P - G @ S @ G.T, None


def readings(system, z, i, which, ok=lambda j: True):
    """[(sensor, z)] of instant i of one run z (K+1, m): the sensors `which` that measured."""
    out = []
    for j in which:
        v = z[i, system.sensor_slices[j]]
        if not np.isnan(v).any() and ok(j):
            out.append((system.sensors[j], v))
    return out


def from_scratch(f: Filter, system, z, arrive, k, which):
    """The filter from the prior over instants 0..k on the readings arrived by k: (x_k, P_k)."""
    x, P = system.prior.mean.copy(), system.prior.cov.copy()
    for i in range(k + 1):
        if i:
            x, P = f.predict(x, P)
        got = readings(system, z, i, which, lambda j, i=i: arrive[i, j] <= k)
        if got:
            x, P, _ = f.update(x, P, got)
    return x, P


def close(est, r, k, x, P, tol):
    scale = np.abs(x).max()
    np.testing.assert_allclose(est.mean[r, k], x, rtol=0, atol=tol * scale)
    np.testing.assert_allclose(est.cov[r, k], P, rtol=0, atol=tol * np.abs(P).max())


def arrival_instants(arrival):
    return np.searchsorted(TIMES, arrival, side="left")


UKF = (1.0, 2.0, 0.0)


@pytest.mark.parametrize("filt", ["EKF", "UKF"])
@pytest.mark.parametrize("turn", [False, True])
@pytest.mark.parametrize("arch", ["CKF", "SKF:b"])
@pytest.mark.parametrize("latency", [(2.0, 2.0), (0.5, 3.5)])
def test_reprocess_is_the_filter_from_scratch_on_what_has_arrived(filt, turn, arch, latency):
    """At every output instant, in every run (random delays: each its own), the estimate is
    the EKF (UKF) run from the prior on exactly the readings that have arrived: the rewind
    relinearises. Tolerance: the reference sums in another order; 1e-9 relative is ~1e6 ulps,
    far above the rounding of 13 steps of these well-conditioned (cond P < 1e6) filters and far
    below a missed or extra reading (which moves the estimate by metres)."""
    system = radar_system(turn, filt, "reprocess", latency)
    z, arrival = draw(system, 3, *latency)
    if latency[0] == latency[1]:
        arrival[..., 1] = TIMES + latency[0]
    est = estimate(system, arch, z, TIMES, arrival=arrival)
    f = Filter(system, UKF if filt == "UKF" else None)
    which = [0, 1] if arch == "CKF" else [1]
    arrive = arrival_instants(arrival)
    for r in range(M):
        for k in range(K + 1):
            x, P = from_scratch(f, system, z[r], arrive[r], k, which)
            close(est, r, k, x, P, 1e-9)


def test_reprocess_in_hkf_is_its_equations_from_scratch():
    """HKF (eqs. 36-40 with EKF locals restarting from the fused prediction) rerun from the
    prior at each instant on the arrived readings, random delays on both radars."""
    system = radar_system(False, "EKF", "reprocess", (0.0, 2.5))
    system = dataclasses.replace(
        system,
        sensors=tuple(
            dataclasses.replace(s, timing=SensorTiming(latency=(0.0, 2.5))) for s in system.sensors
        ),
    )
    z, arrival = draw(system, 7, 0.0, 2.5, both=True)
    est = estimate(system, "HKF", z, TIMES, arrival=arrival)
    f = Filter(system)
    arrive = arrival_instants(arrival)
    for r in range(M):
        for k in range(K + 1):
            x, P = system.prior.mean.copy(), system.prior.cov.copy()
            for i in range(k + 1):
                if i:
                    x, P = f.predict(x, P)
                Yp = np.linalg.inv(P)
                Y, y = Yp.copy(), Yp @ x
                for j in (0, 1):
                    got = readings(
                        system, z[r], i, [j], lambda j, i=i, r=r, k=k: arrive[r, i, j] <= k
                    )
                    if got:
                        xj, Pj, _ = f.update(x, P, got)
                        Y += np.linalg.inv(Pj) - Yp
                        y += np.linalg.solve(Pj, xj) - Yp @ x
                P = np.linalg.inv(Y)
                x = P @ y
            close(est, r, k, x, P, 1e-8)


@pytest.mark.parametrize("arch", ["MSC-GMF", "CI", "AVG"])
def test_reprocess_in_track_to_track_is_the_architecture_on_what_has_arrived(arch):
    """The locals rewind in their own filters and the rule fuses them at each instant: equal
    to the architecture (its on-time path, checked against its equations in
    test_references_nonlinear) run at each instant on exactly the readings arrived by then."""
    system = radar_system(False, "EKF", "reprocess", (0.5, 3.5))
    z, arrival = draw(system, 11, 0.5, 3.5)
    est = estimate(system, arch, z, TIMES, arrival=arrival)
    on_time = radar_system(False, "EKF", "reprocess", (0.0, 0.0))
    arrive = arrival_instants(arrival)
    for k in range(K + 1):
        zk = z[:, : k + 1].copy()
        zk[np.repeat(arrive[:, : k + 1] > k, 2, axis=-1)] = np.nan
        ref = estimate(on_time, arch, zk, TIMES[: k + 1])
        np.testing.assert_allclose(est.mean[:, k], ref.mean[:, k], rtol=0, atol=1e-9 * 1e3)
        np.testing.assert_allclose(est.cov[:, k], ref.cov[:, k], rtol=1e-9, atol=0)


@pytest.mark.parametrize("filt", ["EKF", "UKF"])
@pytest.mark.parametrize("arch", ["CKF", "SKF:b"])
def test_neglect_is_the_event_driven_filter_that_drops_older_readings(filt, arch):
    """Arrivals taken in order (measurement-time order within an instant); one older than
    the filter's newest measurement time is dropped; the rest predicted to and fused at their
    time (a reading of the newest time itself, arriving later, is fused with that time's
    others: the update of that time redone); the estimate at t_k predicted to it."""
    system = radar_system(True, filt, "neglect", (0.0, 3.0))
    system = dataclasses.replace(
        system,
        sensors=tuple(
            dataclasses.replace(s, timing=SensorTiming(latency=(0.0, 3.0))) for s in system.sensors
        ),
    )
    z, arrival = draw(system, 5, 0.0, 3.0, both=True)
    est = estimate(system, arch, z, TIMES, arrival=arrival)
    f = Filter(system, UKF if filt == "UKF" else None)
    which = [0, 1] if arch == "CKF" else [1]
    arrive = arrival_instants(arrival)
    dropped = 0
    for r in range(M):
        # (time of the estimate, prediction there, readings fused there, x, P)
        t, xp, Pp, got = 0, system.prior.mean.copy(), system.prior.cov.copy(), []
        x, P, newest = xp, Pp, -1
        for k in range(K + 1):
            for i in range(k + 1):
                new = readings(
                    system, z[r], i, which, lambda j, i=i, r=r, k=k: arrive[r, i, j] == k
                )
                if not new:
                    continue
                if i < newest:
                    dropped += len(new)
                    continue
                if i > t or newest < 0:
                    for _ in range(i - t):
                        x, P = f.predict(x, P)
                    t, xp, Pp, got = i, x, P, []
                got = got + new
                order = sorted(got, key=lambda g: [s is g[0] for s in system.sensors].index(True))
                x, P, _ = f.update(xp, Pp, order)
                newest = i
            xo, Po = x, P
            for _ in range(k - t):
                xo, Po = f.predict(xo, Po)
            close(est, r, k, xo, Po, 1e-9)
    assert dropped >= 3  # the delays make neglect drop readings (else no test)


def algorithm_a(f: Filter, x, P, last, Pk1, sensor, zd):
    """Bar-Shalom 2002's Algorithm A for a reading zd of the instant before the last update
    (one interval), whose H, S, innovation are `last` and prior covariance Pk1; linear motion,
    the sensor's Jacobian at the retrodicted state."""
    F, Q = f.s.motion.F(1.0), f.s.motion.Q(1.0)
    Fi = np.linalg.inv(F)
    H, S, nu = last
    SiH = np.linalg.solve(S, H)
    xd = Fi @ (x - Q @ H.T @ np.linalg.solve(S, nu))
    Pxv = Q - Pk1 @ H.T @ SiH @ Q
    Pvv = Q - Q @ H.T @ SiH @ Q
    Pd = Fi @ (P + Pvv - Pxv - Pxv.T) @ Fi.T
    Hd = sensor.jacobian(xd)
    Sd = Hd @ Pd @ Hd.T + sensor.R
    Pxz = (P - Pxv) @ Fi.T @ Hd.T
    Wg = np.linalg.solve(Sd, Pxz.T).T
    return x + Wg @ sensor.residual(zd, sensor.h(xd)), P - Wg @ Pxz.T


def test_retrodict_with_a_one_update_lag_is_algorithm_a():
    """Radar 'a' on time, 'b' 1.5 s late: each 'b' reading taken at t_d arrives at t_d + 2,
    after one update ('a' at t_d + 1) beyond the stored estimate at t_d: Bar-Shalom 2002's
    Algorithm A, exact there, with the EKF's Jacobians at the retrodicted state. Written with
    the last update's own H, S, innovation; the lanes use Al1's equivalent measurement
    (inverses of P(k|k-1)): the two agree to cond(P(k|k-1)) x eps, amplified a few times."""
    system = radar_system(False, "EKF", "retrodict", (1.5, 1.5))
    z, arrival = draw(system, 9, 1.5, 1.5)
    arrival[..., 1] = TIMES + 1.5
    est = estimate(system, "CKF", z, TIMES, arrival=arrival)
    f = Filter(system)
    a, b = system.sensors
    for r in range(M):
        x, P = system.prior.mean.copy(), system.prior.cov.copy()
        conds, last, Pk1 = [], None, None
        for k in range(K + 1):
            if k >= 2:  # b's reading of d = k - 2 against the update at k - 1 (lag one)
                x, P = algorithm_a(f, x, P, last, Pk1, b, z[r, k - 2, 2:])
            if k:
                x, P = f.predict(x, P)
            Pk1 = P
            conds.append(np.linalg.cond(P))
            x, P, last = f.update(x, P, [(a, z[r, k, :2])])
            tol = 1e3 * max(conds) * EPS
            close(est, r, k, x, P, tol)


def alternating_arrivals(system):
    """Both radars late by 1.5 s (arriving two instants on) at every other instant, 'a' at the
    instants of one parity and 'b' at the other's, the parity swapped from run to run: each
    local's late reading lags one update of its own (the on-time reading after it)."""
    system = dataclasses.replace(
        system,
        sensors=tuple(
            dataclasses.replace(s, timing=SensorTiming(latency=(0.0, 1.5))) for s in system.sensors
        ),
    )
    late = (np.arange(K + 1)[None, :, None] + np.arange(M)[:, None, None] + [0, 1]) % 2 == 0
    return system, TIMES[None, :, None] + 1.5 * late, late


def test_retrodicting_locals_are_algorithm_a_each_fused_by_msc():
    """MSC with retrodicting EKF locals: each local is its own EKF on its radar whose late
    readings (one update behind) go through Algorithm A with the Jacobian at the retrodicted
    state, and Millman's formula (32)-(34) fuses them at each instant: P = (sum P_j^-1)^-1,
    x = P sum P_j^-1 x_j. Tolerance as in the one-filter test (cond P(k|k-1) x eps, amplified)
    and the fusion's cond(P_j)."""
    system, arrival, late = alternating_arrivals(radar_system(False, "EKF", "retrodict"))
    z = simulate(system, K, 13, 0, M)[1]
    assert not np.isnan(z).any()
    est = estimate(system, "MSC", z, TIMES, arrival=arrival)
    f = Filter(system)
    retrodicted = 0
    for r in range(M):
        locs = []
        for j, s in enumerate(system.sensors):
            zj = z[r, :, system.sensor_slices[j]]
            x, P = system.prior.mean.copy(), system.prior.cov.copy()
            tau, last, Pk1, out, conds = 0, None, None, [], []
            for k in range(K + 1):
                if k >= 2 and late[r, k - 2, j]:  # the reading of k - 2 arrives
                    assert tau == k - 1
                    x, P = algorithm_a(f, x, P, last, Pk1, s, zj[k - 2])
                    retrodicted += 1
                if not late[r, k, j]:  # on time: predict from the last update, update
                    for _ in range(k - tau):
                        x, P = f.predict(x, P)
                    Pk1, tau = P, k
                    conds.append(np.linalg.cond(P))
                    x, P, last = f.update(x, P, [(s, zj[k])])
                xo, Po = x, P
                for _ in range(k - tau):
                    xo, Po = f.predict(xo, Po)
                out.append((xo, Po))
            locs.append((out, max(conds)))
        for k in range(K + 1):
            Ys = [np.linalg.inv(o[k][1]) for o, _ in locs]
            Pf = np.linalg.inv(sum(Ys))
            xf = Pf @ sum(Y @ o[k][0] for Y, (o, _) in zip(Ys, locs, strict=True))
            cond = max(c for _, c in locs) * max(np.linalg.cond(o[k][1]) for o, _ in locs)
            close(est, r, k, xf, Pf, 1e3 * cond * EPS)
    assert retrodicted >= M * K // 2 - M  # the late readings went through Algorithm A


@pytest.mark.parametrize("arch", ["HKF", "MSC", "CI", "ICI", "EI"])
def test_retrodict_at_zero_delay_gives_the_on_time_numbers_bit_for_bit(arch):
    """Retrodicting HKF and track-to-track locals whose readings all arrive when taken: each
    step is the on-time one, to the bit."""
    on = radar_system(True, "EKF", "retrodict", (0.0, 0.0))
    z = simulate(on, K, 2, 0, M)[1]
    ref = estimate(on, arch, z, TIMES)
    system, _, _ = alternating_arrivals(on)
    arrival = np.broadcast_to(TIMES[None, :, None], (M, K + 1, 2))
    got = estimate(system, arch, z, TIMES, arrival=arrival)
    assert np.array_equal(got.mean, ref.mean) and np.array_equal(got.cov, ref.cov)


@pytest.mark.parametrize("arch", ["MSC-GMF", "AVG"])
def test_retrodict_refuses_a_rule_that_reads_the_joint_covariance(arch):
    """The lanes carry no joint error covariance of retrodicting locals: refused in one line
    naming the architecture, on a nonlinear model (`late_refusal`, before any work) and on a
    linear one run through the lanes."""
    from fusionlog.errors import FusionlogError

    for turn in (True, False):
        system, arrival, _ = alternating_arrivals(radar_system(turn, "EKF", "retrodict"))
        z = simulate(system, K, 1, 0, M)[1]
        with pytest.raises(FusionlogError, match=rf"^architecture {arch}: .*joint error cov"):
            estimate(system, arch, z, TIMES, arrival=arrival)


def test_arrivals_at_the_measurement_times_give_the_on_time_numbers_bit_for_bit():
    """A late system whose readings all arrive when taken (and a latency of 0) gives today's
    numbers exactly: the rewinding path reruns nothing, each step is the on-time one."""
    on = radar_system(True, "EKF", "reprocess", (0.0, 0.0))
    z = simulate(on, K, 2, 0, M)[1]
    ref = estimate(on, "MSC-GMF", z, TIMES)
    for late in ("reprocess", "neglect", "retrodict"):
        system = radar_system(True, "EKF", late, (0.0, 2.0))
        arrival = np.broadcast_to(TIMES[None, :, None], (M, K + 1, 2))
        arch = "CKF" if late == "retrodict" else "MSC-GMF"
        got = estimate(system, arch, z, TIMES, arrival=arrival)
        want = ref if arch == "MSC-GMF" else estimate(on, "CKF", z, TIMES)
        assert np.array_equal(got.mean, want.mean) and np.array_equal(got.cov, want.cov)


# --------------------------------------------------------------------------------------------
# The command line


def radar_file(tmp_path: Path, latency: str, late: str, archs: str, name: str = "r") -> Path:
    text = (PIPELINE / "radar_tracking.toml").read_text()
    text = text.replace("runs = 1000", "runs = 200")
    text = text.replace("position = [5000.0, 0.0]", f"position = [5000.0, 0.0]\n{latency}")
    old = 'architectures = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "AVG", "FBS"]'
    assert old in text
    text = text.replace(old, f"architectures = {archs}\n{late}")
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


ARCHS = '["CKF", "HKF", "MSC-GMF", "SKF"]'


@pytest.mark.parametrize(
    "latency, late",
    [("latency = 2.0", "reprocess"), ("latency = {min = 0.5, max = 3.0}", "neglect"),
     ("latency = 1.5", "retrodict")],
)  # fmt: skip
def test_run_of_a_radar_scenario_with_a_late_radar(tmp_path, latency, late):
    """summary.json says the policy; the centralised MSE with radar2 late lies between the
    on-time one and radar1's alone (SKF, its first sensor, on time: unchanged); the PCRB of
    the on-time readings stays beside them (it bounds any estimator using readings taken by
    t_k)."""
    archs = '["CKF", "HKF", "MSC", "SKF"]' if late == "retrodict" else ARCHS
    on = radar_file(tmp_path, "", "", archs, "on")
    f = radar_file(tmp_path, latency, f'late = "{late}"', archs)
    ok("run", on, "--out-dir", tmp_path / "on")
    ok("run", f, "--out-dir", tmp_path / "late")
    s_on = json.loads((tmp_path / "on" / "summary.json").read_text())
    s = json.loads((tmp_path / "late" / "summary.json").read_text())
    assert s["late"] == late and "late" not in s_on
    mse = {a: v["mse"] for a, v in s["architectures"].items()}
    mse_on = {a: v["mse"] for a, v in s_on["architectures"].items()}
    assert mse["SKF"] == pytest.approx(mse_on["SKF"], rel=1e-12)
    assert mse_on["CKF"] < mse["CKF"] < mse["SKF"]
    assert mse_on["HKF"] < mse["HKF"] < mse["SKF"]  # retrodicting HKF too
    assert s["pcrb"] == s_on["pcrb"]


@pytest.mark.parametrize(
    "edit, args, fragments",
    [
        ('late = "retrodict"\n', ["--filter", "UKF"], ["retrodict needs the EKF"]),
        ('late = "retrodict"\n', ["--arch", "MSC-GMF"], ["MSC-GMF", "joint error covariance"]),
        ("", ["--late", "later"], ["--late", "'later' is not one of"]),
        ('late = "reprocess"\n', ["--arch", "FBS"], ["FBS", "smoother"]),
    ],
)
def test_bad_input_is_one_line(tmp_path, edit, args, fragments):
    f = radar_file(tmp_path, "latency = 2.0", edit, '["CKF"]')
    one_line_error(cli("run", f, "--out-dir", tmp_path / "o", *args), *fragments)
    assert not (tmp_path / "o" / "summary.json").exists()


def test_a_ukf_with_retrodict_in_the_file_is_refused_on_load(tmp_path):
    f = radar_file(tmp_path, "latency = 2.0", 'late = "retrodict"', '["CKF"]')
    f.write_text(f.read_text().replace('filter = "EKF"', 'filter = "UKF"'))
    one_line_error(cli("simulate", f, "-o", tmp_path / "s.mcap"), str(f), "retrodict needs the EKF")


# --------------------------------------------------------------------------------------------
# A recorded log's delays (arrival = "log_time") with range-bearing readings

NS = 1_000_000_000
T0 = 1_700_000_000 * NS
B_DELAYS = [0.12, 0.03, 0.25, 0.04, 0.0, 0.31, 0.07, 0.16, 0.02, 0.09]


def write_radar_log(path: Path) -> None:
    """/a: range-bearing from the origin every 0.1 s, on time; /b: from (900, 100) at 0.05 +
    0.1 i, logged late by B_DELAYS; a target moving at (12, -4) m/s from (300, 400)."""
    from mcap.writer import Writer

    rng = np.random.default_rng(4)

    def rb(t: float, at: tuple[float, float]) -> tuple[float, float]:
        dx, dy = 300 + 12 * t - at[0], 400 - 4 * t - at[1]
        return float(np.hypot(dx, dy) + 5 * rng.normal()), float(
            np.arctan2(dy, dx) + 0.03 * rng.normal()
        )

    msgs = []
    for i in range(10):
        s = T0 + i * NS // 10
        msgs.append((s, s, "/a", rb((s - T0) / NS, (0.0, 0.0))))
        s = T0 + (i * 100 + 50) * NS // 1000
        msgs.append((s, s + round(B_DELAYS[i] * NS), "/b", rb((s - T0) / NS, (900.0, 100.0))))
    schema = {"type": "object"}
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("Reading", "jsonschema", json.dumps(schema).encode())
        ch = {t: w.register_channel(t, "json", sid) for t in ("/a", "/b")}
        for stamp, log, t, (r, b) in sorted(msgs, key=lambda m: m[1]):
            body = {
                "header": {"stamp": {"sec": stamp // NS, "nanosec": stamp % NS}},
                "r": r,
                "b": b,
            }
            w.add_message(ch[t], log_time=log, data=json.dumps(body).encode(), publish_time=log)
        w.finish()


#: The log read with placeholder linear sensors (a replay's sensors are H z); the range-bearing
#: model comes with `estimate --model` (MODEL), radar b's delays from the imported log.
REPLAY = """
[scenario]
name = "radar_log"

[model]
kind = "constant-velocity"
axes = 2
n0 = 0.5

[prior]
mean = [300.0, 12.0, 400.0, -4.0]
cov = [[100.0, 0, 0, 0], [0, 9.0, 0, 0], [0, 0, 100.0, 0], [0, 0, 0, 9.0]]

[[sensors]]
name = "a"
H = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]
R = [[25.0, 0.0], [0.0, 1e-3]]
source = "log.mcap"
topic = "/a"
values = ["r", "b"]
time = "header.stamp"

[[sensors]]
name = "b"
H = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]
R = [[25.0, 0.0], [0.0, 1e-3]]
source = "log.mcap"
topic = "/b"
values = ["r", "b"]
time = "header.stamp"
arrival = "log_time"

[estimate]
architectures = ["CKF"]
"""

MODEL = """
[scenario]
name = "radar_model"

[model]
kind = "constant-velocity"
axes = 2
n0 = 0.5

[prior]
mean = [300.0, 12.0, 400.0, -4.0]
cov = [[100.0, 0, 0, 0], [0, 9.0, 0, 0], [0, 0, 100.0, 0], [0, 0, 0, 9.0]]

[[sensors]]
name = "a"
kind = "range-bearing"
position = [0.0, 0.0]
R = [[25.0, 0.0], [0.0, 1e-3]]

[[sensors]]
name = "b"
kind = "range-bearing"
position = [900.0, 100.0]
R = [[25.0, 0.0], [0.0, 1e-3]]
latency = {min = 0.0, max = 0.4}

[estimate]
filter = "EKF"
architectures = ["CKF"]
"""


@pytest.mark.parametrize("late", ["reprocess", "neglect", "retrodict"])
def test_a_recorded_radar_log_s_delays_in_the_ekf(tmp_path, late):
    """`import` of a log whose radar b is logged late (arrival = "log_time"), `estimate
    --model` with range-bearing sensors: the recorded arrivals reach the EKF. Reprocess: at
    each instant of the log the EKF from the prior on exactly the messages logged by then,
    each at its header stamp; every policy: the API's estimate with those arrivals."""
    from fusionlog.core.nonlinear import estimate as lanes
    from fusionlog.io.mcap import McapFile
    from fusionlog.io.mcap.arrival import read_arrivals
    from fusionlog.scenario import load_model

    write_radar_log(tmp_path / "log.mcap")
    (tmp_path / "replay.toml").write_text(REPLAY)
    model = tmp_path / "model.toml"
    model.write_text(MODEL.replace('filter = "EKF"', f'filter = "EKF"\nlate = "{late}"'))
    ok("import", tmp_path / "replay.toml", "-o", tmp_path / "s.mcap")
    ok("estimate", tmp_path / "s.mcap", "--model", model, "-o", tmp_path / "e.mcap")
    sens, est = McapFile(tmp_path / "s.mcap"), McapFile(tmp_path / "e.mcap")
    times = sens.times()
    ((_, _, data),) = sens.iter_run_blocks(["/sensors/a", "/sensors/b"], 1)
    ((_, _, (mean, cov)),) = (
        (o, r, d["/estimates/CKF"]) for o, r, d in est.iter_run_blocks(["/estimates/CKF"], 1)
    )
    cov = np.broadcast_to(cov, (1,) + cov.shape[-3:])
    arrival = read_arrivals(tmp_path / "s.mcap", ["/sensors/b"], 1, len(times))["/sensors/b"]
    assert np.nanmax(arrival[0] - times) > 0.3  # b's messages arrive up to 310 ms late
    # dt: the replay's nominal step (default 1 s), which scales n0 as `estimate --model` does
    system = load_model(model, "state", 1.0).on_times(times)
    z = np.concatenate([data["/sensors/a"], data["/sensors/b"]], -1)
    arr = np.stack([np.broadcast_to(times, (1, len(times))), arrival], -1)
    want = lanes(system, "CKF", z, times, arrival=arr)
    np.testing.assert_allclose(mean, want.mean, rtol=0, atol=1e-9 * np.abs(want.mean).max())
    if late != "reprocess":
        return
    a, b = system.sensors
    for k, tk in enumerate(times):
        x, P = system.prior.mean.copy(), system.prior.cov.copy()
        for i in range(k + 1):
            if i:
                F, Q = system.F_at(i), system.GQG_at(i)
                x, P = F @ x, F @ P @ F.T + Q
            got = [(a, z[0, i, :2])]
            if not np.isnan(arrival[0, i]) and arrival[0, i] <= tk + 1e-9:
                got.append((b, z[0, i, 2:]))
            got = [(s, v) for s, v in got if not np.isnan(v).any()]
            if got:
                x, P, _ = Filter(system).update(x, P, got)
        close(Estimate(mean, cov), 0, k, x, P, 1e-9)


def test_bad_arrivals_in_python_name_the_argument():
    """The lanes' `arrival` argument: random delays need it; its shape and an arrival before
    the reading was taken are refused in one line naming it."""
    from fusionlog.errors import FusionlogError

    system = radar_system(False, "EKF", "reprocess", (0.5, 1.5))
    z = simulate(system, K, 1, 0, M)[1]
    with pytest.raises(FusionlogError, match=r"^arrival: a sensor's latency is a range"):
        estimate(system, "CKF", z, TIMES)
    with pytest.raises(
        FusionlogError, match=r"^arrival: shape \(4, 13\), expected \(runs, 13, 2\)"
    ):
        estimate(system, "CKF", z, TIMES, arrival=np.zeros((M, K + 1)))
    early = np.broadcast_to(TIMES[None, :, None] - 0.5, (M, K + 1, 2))
    with pytest.raises(FusionlogError, match=r"^arrival: a reading arrives before it is taken"):
        estimate(system, "CKF", z, TIMES, arrival=early)


@pytest.mark.parametrize("late", ["reprocess", "neglect", "retrodict"])
@pytest.mark.parametrize("latency", [(2.0, 2.0), (0.5, 3.5)])
def test_on_a_linear_model_the_lanes_are_the_linear_plans(late, latency):
    """Linear sensors and motion run through the EKF lanes (whose Jacobians are then exact)
    give the linear plans' estimates: an independent construction (reprocess and neglect a
    Kalman filter on the state stacked over the latency window, retrodict Al1 compiled into a
    plan, `core.latency`), here with lags of several updates and random delays. Tolerance:
    two exact computations in different orders of 16 well-conditioned steps (cond P < 1e3)."""
    from fusionlog.core.models import LinearSensor
    from fusionlog.driver import PlanCache, estimate_block

    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.16 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    H = np.array([[1.0, 0.0]])
    s1 = LinearSensor("s1", H, np.array([[1.0]]))
    s2 = dataclasses.replace(
        LinearSensor("s2", H, np.array([[0.5]])), timing=SensorTiming(latency=latency)
    )
    system = System(F, Q, (s1, s2), Prior(np.array([100.0, -1.0]), np.eye(2)), late=late)
    K1 = 16
    times = np.arange(float(K1))
    z = simulate(system, K1 - 1, 3, 0, M)[1]
    rng = np.random.default_rng(1)
    delay = np.stack([np.zeros((M, K1)), rng.uniform(*latency, (M, K1))], -1)
    arrival = times[None, :, None] + delay
    got = estimate(dataclasses.replace(system, filter="EKF"), "CKF", z, times, arrival=arrival)
    cache = PlanCache.of(system, times)
    cache.arrivals = arrival
    want = estimate_block(system, ["CKF"], z, cache=cache).estimates["CKF"]
    np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-9 * np.abs(want.mean).max())
    cov = np.broadcast_to(want.cov, got.cov.shape)
    np.testing.assert_allclose(got.cov, cov, rtol=0, atol=1e-9 * np.abs(cov).max())


@pytest.mark.parametrize("arch", ["HKF", "MSC", "CI", "ICI", "EI"])
def test_on_a_linear_model_retrodicting_hkf_and_locals_are_the_linear_plans(arch):
    """Both sensors with random delays (lags of several updates, out of order within each
    local's own sensor): the lanes' retrodicting HKF centre and track-to-track locals, fused
    by the rule, give the linear plans' (`core.retrodict_fused`: HKF's centre as Al1 on the
    noise it believes, each local Al1 compiled on its sensor, the rule on their covariances).
    Tolerance as in the one-filter comparison above (plus the rules' own solves: ICI's and
    CI's omega found to the optimiser's tolerance from the same covariances, to rounding)."""
    from fusionlog.core.models import LinearSensor
    from fusionlog.driver import PlanCache, estimate_block

    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.16 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    H = np.array([[1.0, 0.0]])
    lat = SensorTiming(latency=(0.0, 3.5))
    s1 = dataclasses.replace(LinearSensor("s1", H, np.array([[1.0]])), timing=lat)
    s2 = dataclasses.replace(LinearSensor("s2", H, np.array([[0.5]])), timing=lat)
    prior = Prior(np.array([100.0, -1.0]), np.eye(2))
    system = System(F, Q, (s1, s2), prior, late="retrodict")
    K1 = 16
    times = np.arange(float(K1))
    z = simulate(system, K1 - 1, 3, 0, M)[1]
    arrival = times[None, :, None] + np.random.default_rng(4).uniform(0.0, 3.5, (M, K1, 2))
    got = estimate(dataclasses.replace(system, filter="EKF"), arch, z, times, arrival=arrival)
    cache = PlanCache.of(system, times)
    cache.arrivals = arrival
    want = estimate_block(system, [arch], z, cache=cache).estimates[arch]
    np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-9 * np.abs(want.mean).max())
    cov = np.broadcast_to(want.cov, got.cov.shape)
    np.testing.assert_allclose(got.cov, cov, rtol=0, atol=1e-9 * np.abs(cov).max())


def test_the_stages_read_each_run_s_arrivals_from_the_sensors_file(tmp_path):
    """Random delays: `simulate` writes each run's arrivals in the sensors file, `estimate`
    reads them back for the EKF lanes: the stages' summary is `run`'s, number for number."""
    f = radar_file(tmp_path, "latency = {min = 0.5, max = 3.0}", 'late = "reprocess"', ARCHS)
    ok("run", f, "--runs", "50", "--out-dir", tmp_path / "run")
    ok("simulate", f, "--runs", "50", "-o", tmp_path / "s.mcap")
    ok("estimate", tmp_path / "s.mcap", "-o", tmp_path / "e.mcap")
    ok("evaluate", tmp_path / "s.mcap", tmp_path / "e.mcap", "-o", tmp_path / "e.rrd",
       "--summary", tmp_path / "e.json")  # fmt: skip
    run = json.loads((tmp_path / "run" / "summary.json").read_text())["architectures"]
    staged = json.loads((tmp_path / "e.json").read_text())["architectures"]
    for a in json.loads(ARCHS):
        assert staged[a]["mse"] == pytest.approx(run[a]["mse"], rel=1e-12)
