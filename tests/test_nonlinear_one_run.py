"""A long one-run nonlinear log (issue 34, "Hour-long logs"): the EKF/UKF locals of one run go
through numpy's stacked products (fewer runs than `kernels.KERNEL_MIN_BATCH`), many runs
through the batch kernels (the lanes, one numpy call per matrix entry). Both are the same
filters: here every architecture, EKF and UKF, on one run in blocks of time
(`long_log.estimate_blocks`, four blocks) against the lanes path forced for that run
(KERNEL_MIN_BATCH lowered to 1) and, for the CKF, against FilterPy's ExtendedKalmanFilter run on
the same readings; a few readings are lost, so the masked updates are compared too.

Tolerances: the two paths make the Joseph update from the same numbers in another order of
roundings (products of whole matrices against the lanes' |q| x |q| core; LU's solve against
the Cholesky kernel's), a few ulps times the condition of S (< 10^4 here) per step, which the
filters do not amplify (their error dynamics are contractive): 1e-9 relative to the size of
the numbers (positions of ~10^3 m, covariances of ~10^2), as tests/test_nonlinear_core.py
compares the EKF with FilterPy. CI's weights come out of a Newton iteration stopped at a
tolerance: the same inputs to rounding give the same weights to rounding while the stopping
test decides alike, which it does on these logs (a looser bound would hide a real change).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter
from references import PIPELINE

from fusionlog.core import kernels
from fusionlog.core.models.polar import wrap
from fusionlog.core.nonlinear.long_log import estimate_blocks
from fusionlog.core.simulate import simulate
from fusionlog.scenario import load_scenario

INSTANTS, BLOCK = 161, 50  # four blocks, the last one short

CASES = [("radar_tracking.toml", "EKF"), ("radar_tracking.toml", "UKF"),
         ("coordinated_turn.toml", "UKF"), ("coordinated_turn.toml", "EKF")]  # fmt: skip


def _log(name: str, filt: str):
    """The scenario's system with local filter `filt`, one run's readings (1, K+1, m) with
    10 % of each sensor's readings lost, the instants and the architectures."""
    sc = load_scenario(PIPELINE / name, runs=1, steps=INSTANTS - 1)
    system = dataclasses.replace(sc.system, filter=filt)
    times = np.arange(INSTANTS) * system.dt
    _, z = simulate(system.on_times(times), INSTANTS - 1, 34, 0, 1)
    lost = np.random.default_rng(34).random((INSTANTS, len(system.sensors))) < 0.1
    for j, sl in enumerate(system.sensor_slices):
        z[0, lost[:, j], sl] = np.nan
    return system, z, times, list(sc.architectures)


def _blocked(system, archs, z, times) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every architecture's estimates of the one run, block after block, joined."""
    parts: dict[str, list] = {a: [] for a in archs}
    for _, _, out in estimate_blocks(system, archs, lambda a, b: z[:, a:b], times, BLOCK):
        for a, (mean, cov) in out.items():
            parts[a].append((mean[0].copy(), cov[0].copy()))
    return {a: (np.concatenate([p[0] for p in v]), np.concatenate([p[1] for p in v]))
            for a, v in parts.items()}  # fmt: skip


def _close(a: np.ndarray, b: np.ndarray, rtol: float = 1e-9) -> None:
    scale = max(1.0, float(np.abs(b).max()))
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


@pytest.fixture(scope="module", params=CASES, ids=[f"{n.split('.')[0]} {f}" for n, f in CASES])
def both_paths(request):
    """(system, z, the few-runs path's estimates, the lanes path's) of one case."""
    system, z, times, archs = _log(*request.param)
    few = _blocked(system, archs, z, times)
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(kernels, "KERNEL_MIN_BATCH", 1)  # one run is "many": the lanes path
        lanes = _blocked(system, archs, z, times)
    finally:
        mp.undo()
    return system, z, few, lanes


def test_one_run_equals_the_lanes_path_in_every_architecture(both_paths) -> None:
    _, z, few, lanes = both_paths
    assert len(few) >= 7 and all(v[0].shape[0] == z.shape[1] for v in few.values())
    for arch in few:
        _close(few[arch][0], lanes[arch][0])
        _close(few[arch][1], lanes[arch][1])


def _filterpy_ckf(system, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """FilterPy's ExtendedKalmanFilter on one run z (K+1, m): the prediction by the motion model
    (f and its Jacobian, dt = 1), the update with the sensors that measured stacked (their
    models' h and Jacobian), the bearings' residuals wrapped."""
    motion = system.motion
    ekf = ExtendedKalmanFilter(dim_x=system.n, dim_z=system.m)
    ekf.x, ekf.P = system.prior.mean[:, None].copy(), system.prior.cov.copy()
    ekf.Q = motion.Q(1.0)
    means, covs = [], []
    for k in range(z.shape[0]):
        if k:
            x = ekf.x.ravel()
            ekf.F = motion.jacobian(x, 1.0) if not motion.linear else motion.F(1.0)
            ekf.predict()
            ekf.x = (motion.f(x, 1.0) if not motion.linear else motion.F(1.0) @ x)[:, None]
        use = [(s, sl) for s, sl in zip(system.sensors, system.sensor_slices, strict=True)
               if not np.isnan(z[k, sl]).any()]  # fmt: skip
        if use:
            zk = np.concatenate([z[k, sl] for _, sl in use])
            angles = np.concatenate([s.angles for s, _ in use])
            R = np.zeros((len(zk), len(zk)))
            i = 0
            for s, _ in use:
                R[i : i + s.dim, i : i + s.dim] = s.R
                i += s.dim

            def H(x, use=use):
                return np.concatenate([s.jacobian(x.ravel()) for s, _ in use])

            def hx(x, use=use):
                return np.concatenate([s.h(x.ravel()) for s, _ in use])[:, None]

            def residual(a, b, angles=angles):
                d = a - b
                d[angles] = wrap(d[angles])
                return d

            ekf.update(zk[:, None], H, hx, R=R, residual=residual)
        means.append(ekf.x.ravel().copy())
        covs.append(ekf.P.copy())
    return np.array(means), np.array(covs)


def test_one_run_ckf_equals_filterpy(both_paths) -> None:
    system, z, few, _ = both_paths
    if system.filter != "EKF":
        pytest.skip("FilterPy's EKF is the reference of the EKF")
    mean, cov = _filterpy_ckf(system, z[0])
    _close(few["CKF"][0], mean)
    _close(few["CKF"][1], cov)


def test_wrap_of_a_few_angles_is_the_formula_to_the_last_bit() -> None:
    """`wrap` tests a few angles in Python: each one alone gives the numbers of the formula
    pi - ((pi - a) mod 2 pi) as numpy computes it (the edges of the interval included)."""
    edges = [math.pi, -math.pi, 0.0, -0.0, 2 * math.pi, 3 * math.pi, 1e-300, -1e-300, 0.5, -3.0]
    edges += [float(np.nextafter(math.pi, 4)), float(np.nextafter(-math.pi, -4))]
    for a in edges:
        got = wrap(np.array([a]))[0]
        t = np.mod(np.subtract(math.pi, a), 2 * math.pi)
        want = math.pi - (t if t < 2 * math.pi else 0.0)
        assert got == want and math.copysign(1, got) == math.copysign(1, want), a
    assert np.isnan(wrap(np.array([np.nan, 1.0]))[0])
