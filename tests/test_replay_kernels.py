"""The plan-free replay's compiled per-instant loops (issue 34, `core.architectures.replay_kernels`
behind `replay_filters`) against references written from the formulas, independently of the
plans: FilterPy's `predict`/`update` (Joseph form) with each interval's F, Q and each instant's
R restricted to the readings present, its `rts_smoother` for FBS, and HKF's and MSC's fusions
(eqs. 32-34, 36-40) written here, on an irregular log (intervals 0.1 s +- 40 %, a covariance per
message, readings missing: whole sensors and single components); the tolerance is what
rounding-level changes of the model move the reference by (`conditioning.sensitivity`), not
this machine's rounding. A log in blocks of time equals the whole log bit for bit (the same
kernels on the same numbers); a singular innovation covariance hands the log to the plans.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from conditioning import assert_agree, sensitivity
from filterpy.kalman import predict, rts_smoother, update

from fusionlog.core.architectures.replay import replay_estimates
from fusionlog.core.architectures.replay_filters import (
    Slots,
    affine_recursion,
    backward_information,
    backward_means,
    information,
    joint_recursion,
    masked_rows,
    run_bank,
)
from fusionlog.core.model import Prior, Sensor, System

K1 = 300
RTOL = 1e-12  # the floor of the tolerances (`Sensitivity.tolerance`)


def _log(seed: int = 34) -> tuple[System, np.ndarray]:
    """Constant velocity [p, v] on irregular instants (F, Q of each interval in closed form),
    sensor a reading p, sensor b reading (p, v) with correlated components, R per message;
    a sensor absent at 5 % of the instants, b's v alone at another 10 %: system, z (1, K1, 3)."""
    rng = np.random.default_rng(seed)
    dt = 0.1 * (1 + 0.4 * rng.uniform(-1, 1, K1 - 1))
    q = 2.0
    Fs = np.zeros((K1 - 1, 2, 2))
    Fs[:, 0, 0] = Fs[:, 1, 1] = 1.0
    Fs[:, 0, 1] = dt
    Qs = q * np.stack([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]).transpose(2, 0, 1)
    Ra, Rb = np.array([[0.04]]), np.array([[0.09, 0.01], [0.01, 0.25]])
    sensors = (
        Sensor("a", np.array([[1.0, 0.0]]), Ra),
        Sensor("b", np.array([[1.0, 0.0], [0.0, 1.0]]), Rb),
    )
    R = np.zeros((3, 3))
    R[:1, :1], R[1:, 1:] = Ra, Rb
    Rs = R * (0.5 + rng.random(K1))[:, None, None]
    prior = Prior(np.array([1.0, 0.0]), np.diag([1.0, 0.5]))
    system = System(F=Fs[0], Q=Qs[0], sensors=sensors, prior=prior, Fs=Fs, Qs=Qs, Rs=Rs)
    x = np.zeros((K1, 2))
    x[0] = prior.mean + np.linalg.cholesky(prior.cov) @ rng.standard_normal(2)
    for k in range(1, K1):
        x[k] = Fs[k - 1] @ x[k - 1] + np.linalg.cholesky(Qs[k - 1]) @ rng.standard_normal(2)
    H = system.linear_measurement()
    z = np.einsum("ij,kj->ki", H, x)
    z += np.einsum("kij,kj->ki", np.linalg.cholesky(Rs), rng.standard_normal((K1, 3)))
    z[rng.random(K1) < 0.05, :1] = np.nan
    z[rng.random(K1) < 0.05, 1:] = np.nan
    z[rng.random(K1) < 0.10, 2] = np.nan
    assert np.isnan(z).any(axis=1).mean() > 0.15
    return system, z[None]


def _kf(system: System, z: np.ndarray, rows: np.ndarray, x0=None, P0=None):
    """FilterPy's Kalman filter on the components `rows` of z (K1, m): at each instant the
    prediction with that interval's F and G Q G' (none at instant 0) and, where readings are
    present, the update with H and R restricted to them. Filtered means, covariances and the
    gains (K1, n, m) in z's columns (zero where absent)."""
    H, n = system.linear_measurement(), system.n
    x = system.prior.mean.copy() if x0 is None else x0
    P = system.prior.cov.copy() if P0 is None else P0
    xs, Ps, Ks = np.zeros((K1, n)), np.zeros((K1, n, n)), np.zeros((K1, n, z.shape[1]))
    for k in range(K1):
        if k:
            x, P = predict(x, P, system.Fs[k - 1], system.Qs[k - 1])
        use = rows[~np.isnan(z[k, rows])]
        if use.size:
            x, P, _, K, _, _ = update(
                x, P, z[k, use], system.Rs[k][np.ix_(use, use)], H[use], return_all=True
            )
            Ks[k][:, use] = K
        xs[k], Ps[k] = x, P
    return xs, Ps, Ks


def _reference(system: System, z: np.ndarray) -> dict[str, SimpleNamespace]:
    """CKF, SKF, MSC, HKF and FBS from the formulas (FilterPy's filters, fusions written here)."""
    zz, n = z[0], system.n
    S = len(system.sensors)
    rows = [np.arange(system.m)[sl] for sl in system.sensor_slices]
    out = {}
    x, P, K = _kf(system, zz, np.arange(system.m))
    out["CKF"] = SimpleNamespace(mean=x, cov=P, gain=K)
    locs = [_kf(system, zz, r) for r in rows]
    for s, (xl, Pl, _) in zip(system.sensors, locs, strict=True):
        out[f"SKF:{s.name}"] = SimpleNamespace(mean=xl, cov=Pl)
    # MSC, eqs. (32)-(34): P = (sum_j P_j^-1)^-1, x = P sum_j P_j^-1 x_j
    Yl = [np.linalg.inv(Pl) for _, Pl, _ in locs]
    Pm = np.linalg.inv(sum(Yl))
    xm = np.einsum("kij,kj->ki", Pm, sum(np.einsum("kij,kj->ki", Y, xl) for Y, (xl, _, _) in
                                         zip(Yl, locs, strict=True)))  # fmt: skip
    out["MSC"] = SimpleNamespace(mean=xm, cov=Pm)
    # HKF with feedback, eqs. (36)-(40): each local updates the fused prediction with its own
    # readings; Y = (1 - S) Y_pred + sum_j Y_j, y = (1 - S) Y_pred x_pred + sum_j Y_j x_j
    xh, Ph = np.zeros((K1, n)), np.zeros((K1, n, n))
    x, P = system.prior.mean.copy(), system.prior.cov.copy()
    for k in range(K1):
        if k:
            x, P = predict(x, P, system.Fs[k - 1], system.Qs[k - 1])
        Y = (1 - S) * np.linalg.inv(P)
        y = Y @ x
        for r in rows:
            use = r[~np.isnan(zz[k, r])]
            xj, Pj = x, P
            if use.size:
                R = system.Rs[k][np.ix_(use, use)]
                xj, Pj = update(x, P, zz[k, use], R, system.linear_measurement()[use])
            Yj = np.linalg.inv(Pj)
            Y, y = Y + Yj, y + Yj @ xj
        P = np.linalg.inv(Y)
        x = P @ y
        xh[k], Ph[k] = x, P
    out["HKF"] = SimpleNamespace(mean=xh, cov=Ph)
    # FBS: the CKF smoothed by Rauch-Tung-Striebel (eqs. 25-28 give the same estimates)
    Fs = np.concatenate([system.Fs, np.eye(n)[None]])
    Qs = np.concatenate([system.Qs, np.zeros((1, n, n))])
    xs, Ps, _, _ = rts_smoother(out["CKF"].mean, out["CKF"].cov, Fs, Qs)
    out["FBS"] = SimpleNamespace(mean=xs, cov=Ps)
    return out


ARCHS = ["CKF", "SKF:a", "SKF:b", "MSC", "HKF", "FBS"]


@pytest.fixture(scope="module")
def irregular():
    return _log()


@pytest.mark.parametrize("arch", ARCHS)
def test_each_filter_equals_the_formulas_on_an_irregular_log(irregular, arch) -> None:
    system, z = irregular
    got = replay_estimates(system, ARCHS, z)
    assert got is not None

    def ref(s):
        return _reference(s, z)[arch]

    sens = sensitivity(ref, system, ("mean", "cov"))
    want = ref(system)
    for f, mine in (("mean", got[arch].mean[0]), ("cov", got[arch].cov)):
        assert_agree(mine, getattr(want, f), sens.tolerance(f, RTOL), sens.unsettled, arch + f)


def test_the_gains_equal_filterpy_s_and_are_zero_where_a_reading_is_absent(irregular) -> None:
    """run_bank's CKF slot: its gain columns as FilterPy's K where present, exactly 0 where
    absent; its P and I - K H consistent with them."""
    system, z = irregular
    present = ~np.isnan(z[0])
    H = system.linear_measurement()
    Hm, Rm = masked_rows(H, system.Rs, present[:, None, :])
    slots = Slots(np.ones((1, system.m), bool), np.array([0]), 1, None)
    bank = run_bank(slots, system.prior.cov, system.Fs, system.Qs, Hm, Rm)

    def ref(s):
        _, P, K = _kf(s, z[0], np.arange(s.m))
        return SimpleNamespace(cov=P, gain=K)

    sens = sensitivity(ref, system, ("cov", "gain"))
    want = ref(system)
    K = bank.K[:, 0]
    assert_agree(K, want.gain, sens.tolerance("gain", RTOL), sens.unsettled, "gain")
    assert_agree(bank.P[:, 0], want.cov, sens.tolerance("cov", RTOL), sens.unsettled, "P")
    assert (K.swapaxes(-1, -2)[~present] == 0.0).all()
    np.testing.assert_array_equal(bank.IKH[:, 0][~present.any(axis=1)], np.eye(2)[None])
    ikh = np.eye(2) - K @ H
    np.testing.assert_allclose(bank.IKH[:, 0], ikh, rtol=0, atol=8 * np.finfo(float).eps)


@pytest.mark.parametrize("cut", [1, 7, 150, 298])
def test_the_recursions_cut_in_two_equal_them_whole_bit_for_bit(irregular, cut) -> None:
    """Each compiled recursion run over instants [0, cut) then [cut, K1) from the state carried
    across equals it run whole, to the bit (the same kernel on the same numbers): the slots'
    covariances, gains, I - K H and HKF's informations (CKF, the locals, HKF); FBS's backward
    information filter from the log's end and its vectors; the means and eq. (35)'s J. (The
    rules' batched fusions after them are compared to rounding by test_long_replay.)"""
    system, z = irregular
    m, n = system.m, system.n
    rows = np.zeros((2, m), bool)
    rows[0, :1] = rows[1, 1:] = True
    use = np.array([np.ones(m, bool), *rows, np.zeros(m, bool), *rows])
    slots = Slots(use, np.array([0, 1, 2, 3, 3, 3]), 4, 3)
    Hm, Rm = masked_rows(system.linear_measurement(), system.Rs, ~np.isnan(z[0])[:, None] & use)
    Fs, Qs = system.Fs, system.Qs
    whole = run_bank(slots, system.prior.cov, Fs, Qs, Hm, Rm)
    head = run_bank(slots, system.prior.cov, Fs[: cut - 1], Qs[: cut - 1], Hm[:cut], Rm[:cut])
    carried = head.P[-1, :4]
    tail = run_bank(slots, carried, Fs[cut - 1 :], Qs[cut - 1 :], Hm[cut:], Rm[cut:], True)
    for f in ("P", "K", "IKH", "P_hkf", "Y_hkf"):
        got = np.concatenate([getattr(head, f), getattr(tail, f)])
        np.testing.assert_array_equal(got, getattr(whole, f), err_msg=f)
    W, c = information(Hm[:, 0], Rm[:, 0], np.nan_to_num(z[0]))
    L, S = backward_information(W, Fs, Qs)
    y = backward_means(L, c)
    L2, S2 = backward_information(W[cut - 1 :], Fs[cut - 1 :], Qs[cut - 1 :])
    y2 = backward_means(L2, c[cut - 1 :])
    L1, S1 = backward_information(W[:cut], Fs[: cut - 1], Qs[: cut - 1], S2[0])
    y1 = backward_means(L1, c[:cut], y2[0])
    np.testing.assert_array_equal(np.concatenate([L1, L2]), L)
    np.testing.assert_array_equal(np.concatenate([S1, S2[1:]]), S)
    np.testing.assert_array_equal(np.concatenate([y1, y2[1:]]), y)
    A = whole.IKH[:, None, 0] @ np.concatenate([np.eye(n)[None], Fs])[:, None]
    b = np.einsum("kij,kj->ki", whole.K[:, 0], np.nan_to_num(z[0]))[:, None]
    x = affine_recursion(A, b, system.prior.mean[None])
    x1 = affine_recursion(A[:cut], b[:cut], system.prior.mean[None])
    np.testing.assert_array_equal(
        np.concatenate([x1, affine_recursion(A[cut:], b[cut:], x1[-1])]), x
    )
    C = whole.P[:, 1:3].reshape(K1, 2 * n, n) @ whole.P[:, 1:3].reshape(K1, 2 * n, n).swapaxes(1, 2)
    Aj = np.zeros((K1, 2 * n, 2 * n))
    Aj[:, :n, :n], Aj[:, n:, n:] = A[:, 0], whole.IKH[:, 2]
    J = joint_recursion(Aj, C, np.eye(2 * n))
    J1 = joint_recursion(Aj[:cut], C[:cut], np.eye(2 * n))
    np.testing.assert_array_equal(
        np.concatenate([J1, joint_recursion(Aj[cut:], C[cut:], J1[-1])]), J
    )


def test_a_singular_innovation_covariance_goes_to_the_plans(irregular) -> None:
    """A prior and noises of zero: H P H' + R = 0 at instant 0, which numpy's solve refuses;
    the compiled LU reports it and the replay path hands the log over (None)."""
    system, z = irregular
    zero = np.zeros((2, 2))
    singular = dataclasses.replace(
        system, prior=Prior(system.prior.mean, zero), Qs=np.zeros_like(system.Qs),
        Rs=np.zeros_like(system.Rs),
    )  # fmt: skip
    assert replay_estimates(singular, ["CKF"], z) is None
    assert replay_estimates(system, ["CKF"], z) is not None
