"""Nonlinear sensors and motion in the core (DESIGN.md, "Nonlinear sensors and motion"), against
independent computations: finite-difference Jacobians, closed forms of the turn, FilterPy's
`ExtendedKalmanFilter` run per run, a plain per-run UKF written here from the contract's formulas,
the linear filters (which the EKF and UKF must equal on a linear model), and the exact CKF
covariance (which the PCRB must equal on a linear model).

Tolerances: the filters are compared to 1e-9 relative to the size of the numbers (positions of
~10^3 m, covariances of ~10^2): the computations differ only in the order of roundings (a solve
against an inverse), whose effect is a few ulps times the condition of S (< 10^4 here).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import pytest
from conditioning import EPS
from filterpy.kalman import ExtendedKalmanFilter

from fusionlog.core.architectures import build_plan
from fusionlog.core.architectures import estimate as linear_estimate
from fusionlog.core.model import Prior, Sensor, System, constant_velocity
from fusionlog.core.models import (
    BearingSensor,
    CoordinatedTurn,
    MotionModel,
    RangeBearingSensor,
    RangeSensor,
)
from fusionlog.core.models.polar import wrap
from fusionlog.core.nonlinear import PcrbAccumulator, estimate, pcrb_summary
from fusionlog.core.simulate import simulate
from fusionlog.errors import NumericalError

ARCHS = ["CKF", "SKF", "SKF:b", "HKF", "MSC", "MSC-GMF", "CI", "AVG", "FBS"]
RB_R = np.diag([25.0, 1e-3])


def _cv(dt: float = 1.0, q: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    F1, Q1 = constant_velocity(dt, q * dt)
    return np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1)


def _radar(filt: str = "EKF", n: int = 4, turn: bool = False) -> System:
    """Two sensors 'a' (range-bearing) and 'b' (bearing) of a [x, vx, y, vy(, omega)] target."""
    a = RangeBearingSensor("a", np.array([0.0, 0.0]), (0, 2), n, RB_R)
    b = BearingSensor("b", np.array([900.0, 100.0]), (0, 2), n, np.array([[4e-4]]))
    mean = [300.0, 12.0, 400.0, -4.0] + ([0.04] if turn else [])
    cov = np.diag([100.0, 9.0, 100.0, 9.0] + ([1e-4] if turn else []))
    if turn:
        ct = CoordinatedTurn((0.1, 0.1), 1e-5)
        F, Q = ct.jacobian(np.zeros(5), 1.0).copy(), ct.Q(1.0)
        names = ("x", "vx", "y", "vy", "omega")
        return System(F, Q, (a, b), Prior(np.array(mean), cov), state_names=names,
                      motion_model=ct, filter=filt)  # fmt: skip
    F, Q = _cv()
    return System(F, Q, (a, b), Prior(np.array(mean), cov), filter=filt,
                  state_names=("x", "vx", "y", "vy"))  # fmt: skip


def _data(system: System, runs: int, steps: int, seed: int = 1, drop: float = 0.0):
    x, z = simulate(system, steps, seed, 0, runs)
    if drop:
        lost = np.random.default_rng(seed).random(z.shape[:2] + (len(system.sensors),)) < drop
        for j, sl in enumerate(system.sensor_slices):
            z[:, :, sl][lost[:, :, j]] = np.nan
    return x, z


def _close(a: np.ndarray, b: np.ndarray, rtol: float = 1e-9) -> None:
    scale = max(1.0, float(np.abs(b).max()))
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


# --------------------------------------------------------------------------------------------
# Models


def test_wrap_maps_every_angle_into_the_half_open_interval() -> None:
    a = np.array([math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 0.5, -0.5, 7.0, -7.0])
    w = wrap(a)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    assert w[0] == math.pi and w[1] == math.pi  # -pi is pi
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-15)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-14)


def test_wrap_is_the_mod_formula_to_the_last_bit() -> None:
    """`wrap` skips np.mod where pi - a is already in [0, 2 pi): the same numbers as
    pi - ((pi - a) mod 2 pi) everywhere, the sign of zero included, except where np.mod rounds
    up to 2 pi (just above pi): the formula's -pi, outside (-pi, pi], is pi."""
    rng = np.random.default_rng(5)
    edges = [math.pi, -math.pi, 0.0, -0.0, 2 * math.pi, -2 * math.pi, 3 * math.pi, 1e-300]
    edges += [np.nextafter(math.pi, 4), np.nextafter(-math.pi, -4), 1e300, -1e300]
    a = np.concatenate([rng.uniform(-50, 50, 10**5), rng.uniform(-4, 4, 10**5), edges])
    expected = math.pi - np.mod(math.pi - a, 2.0 * math.pi)
    assert (expected == -math.pi).sum() == 1  # np.nextafter(math.pi, 4)'s
    expected[expected == -math.pi] = math.pi
    got = wrap(a)
    assert np.array_equal(got, expected) and np.array_equal(np.signbit(got), np.signbit(expected))
    assert wrap(-math.pi) == math.pi
    assert wrap(np.nextafter(math.pi, 4)) == math.pi and wrap(np.float64(-math.pi)) == math.pi
    assert np.all(got > -math.pi) and np.all(got <= math.pi)
    assert wrap(np.array(7.0)) == math.pi - np.mod(math.pi - 7.0, 2.0 * math.pi)


@pytest.mark.parametrize("cls", [RangeBearingSensor, RangeSensor, BearingSensor])
def test_polar_linearised_is_h_and_the_jacobian(cls) -> None:
    """The EKF's `linearised` (lanes, x and y columns only) against `h` and `jacobian`: the
    same bearings and Jacobian; its range is sqrt(dx^2 + dy^2), within 1.5 ulp of `h`'s
    hypot (three roundings of relative eps/2 before the square root halves them, one
    after), i.e. within 3 eps."""
    rng = np.random.default_rng(4)
    s = cls("s", np.array([3.0, -2.0]), (0, 2), 4, np.eye(len(cls.components)))
    x = rng.normal(0.0, 50.0, (7, 4))
    h, J, cols = s.linearised(x)
    assert cols == (0, 2)
    ranges = np.array([c == "range" for c in cls.components])
    np.testing.assert_array_equal(h.T[:, ~ranges], s.h(x)[:, ~ranges])
    np.testing.assert_allclose(h.T[:, ranges], s.h(x)[:, ranges], rtol=3 * EPS, atol=0)
    np.testing.assert_array_equal(J.transpose(2, 0, 1), s.jacobian(x)[:, :, [0, 2]])


@pytest.mark.parametrize("cls", [RangeBearingSensor, RangeSensor, BearingSensor])
def test_polar_jacobians_match_finite_differences(cls) -> None:
    rng = np.random.default_rng(3)
    dim = len(cls.components)
    s = cls("s", np.array([10.0, -20.0]), (2, 0), 4, np.eye(dim))
    x = rng.uniform(-500, 500, (6, 4))
    J = s.jacobian(x)
    h = 1e-4  # central differences: error ~ h^2 |h'''| ~ 1e-8 / r^3 relative, r ~ 10^2
    num = np.stack([(s.h(x + h * e) - s.h(x - h * e)) / (2 * h) for e in np.eye(4)], axis=-1)
    np.testing.assert_allclose(J, num, atol=1e-8 * np.abs(J).max())
    # what the sensor measures, in closed form
    dx, dy = x[:, 2] - 10.0, x[:, 0] + 20.0
    want = {"range": np.hypot(dx, dy), "bearing": np.arctan2(dy, dx)}
    np.testing.assert_allclose(s.h(x), np.stack([want[c] for c in cls.components], -1))


@pytest.mark.parametrize("omega", [0.0, 1e-9, 3e-3, 0.0099, 0.0101, 0.3, -0.7])
def test_turn_jacobian_matches_finite_differences(omega: float) -> None:
    ct = CoordinatedTurn((1.0, 1.0), 1.0)
    x = np.array([[5.0, 12.0, -3.0, 4.0, omega]])
    dt = 1.0
    J = ct.jacobian(x, dt)[0]
    h = 1e-6
    num = np.stack(
        [(ct.f(x + h * e, dt) - ct.f(x - h * e, dt))[0] / (2 * h) for e in np.eye(5)], -1
    )
    np.testing.assert_allclose(J, num, atol=1e-7 * np.abs(J).max())


def _turn_slopes(theta: float) -> tuple[Fraction, Fraction]:
    """d/dtheta of sin(theta)/theta and of (1 - cos theta)/theta, exactly from their series
    (20 terms: the remainder is far below a double's last bit for |theta| < 0.1)."""
    t = Fraction(theta)
    da = sum(Fraction((-1) ** k * 2 * k, math.factorial(2 * k + 1)) * t ** (2 * k - 1)
             for k in range(1, 21))  # fmt: skip
    db = sum(Fraction((-1) ** (k + 1) * (2 * k - 1), math.factorial(2 * k)) * t ** (2 * k - 2)
             for k in range(1, 21))  # fmt: skip
    return da, db


@pytest.mark.parametrize("theta", [1e-4, 1e-3, 5e-3, 0.0099, -0.0099, 0.0101])
def test_turn_jacobian_omega_column_to_the_last_bits(theta: float) -> None:
    """d x'/d omega = da vx - db vy and d y'/d omega = db vx + da vy (dt = 1) against their
    exact series on both sides of the switch to the Taylor series: a few ulps below it (da's
    series once stopped at theta^3: 3.6e-11 off just below the switch), what the closed
    forms' cancellation leaves above it (~eps / theta^2)."""
    ct = CoordinatedTurn((1.0, 1.0), 1.0)
    J = ct.jacobian(np.array([[0.0, 1.0, 0.0, 0.0, theta]]), 1.0)[0]
    da, db = _turn_slopes(theta)
    tol = 8 * EPS if abs(theta) < 0.01 else 8 * EPS / theta**2
    for got, want in ((J[0, 4], da), (J[2, 4], db)):
        assert abs((Fraction(float(got)) - want) / want) < tol, (theta, float(got), want)


def test_turn_is_the_exact_arc_and_tends_to_constant_velocity() -> None:
    ct = CoordinatedTurn((1.0, 1.0), 1.0)
    v, om = 20.0, 0.1
    T = (math.pi / 2) / om  # a quarter turn: from heading east to heading north
    x1 = ct.f(np.array([0.0, v, 0.0, 0.0, om]), T)
    np.testing.assert_allclose(x1, [v / om, 0.0, v / om, v, om], atol=1e-12 * v / om)
    F, _ = _cv(dt=2.0)
    x = np.array([1.0, 2.0, 3.0, -4.0])
    for tiny in (0.0, 1e-15, -1e-15):  # the turn itself moves ~omega dt^2 |v| (< 1e-13)
        np.testing.assert_allclose(ct.f(np.append(x, tiny), 2.0)[:4], F @ x, rtol=1e-12)
    # just inside the series' range, the closed form itself (accurate to ~eps/theta^2 there)
    th = 0.0099
    got = ct.f(np.array([0.0, v, 0.0, 1.0, th]), 1.0)
    a, b = math.sin(th) / th, (1 - math.cos(th)) / th
    want = [a * v - b, math.cos(th) * v - math.sin(th), b * v + a, math.sin(th) * v + math.cos(th)]
    np.testing.assert_allclose(got[:4], want, rtol=1e-10)
    Q = ct.Q(2.0)
    np.testing.assert_allclose(Q[:2, :2], [[8 / 3, 2.0], [2.0, 2.0]])
    assert Q[4, 4] == 2.0 and not Q[:4, 4].any()


def _turn_values(theta: float) -> tuple[Fraction, Fraction, Fraction, Fraction]:
    """sin(theta)/theta, (1 - cos theta)/theta, cos theta and sin theta exactly from their
    series (20 terms: the remainder is far below a double's last bit for |theta| < 0.1)."""
    t = Fraction(theta)
    sin = sum(Fraction((-1) ** k, math.factorial(2 * k + 1)) * t ** (2 * k + 1) for k in range(20))
    one_minus_cos = -sum(
        Fraction((-1) ** k, math.factorial(2 * k)) * t ** (2 * k) for k in range(1, 20)
    )
    return sin / t, one_minus_cos / t, 1 - one_minus_cos, sin


@pytest.mark.parametrize("theta", [0.09, -0.0875, 0.07])
def test_turn_below_a_tenth_is_the_exact_turn_to_the_closed_form_s_rounding(theta: float) -> None:
    """f and the Jacobian's omega column at omega dt a little below 0.1 (dt = 1) against the
    exact turn: there the closed forms are used and lose only ~eps/theta^2 to the cancellation
    in 1 - cos theta (cos rounded by half an ulp of ~1, divided by theta^2/2): 8 eps/theta^2
    (2.2e-13 at 0.09) bounds them. A Taylor series taken up to 0.1 is off by its first omitted
    term, theta^6/5040 of a (1e-10 at 0.09), theta^6/40320 of b, more for the slopes."""
    ct = CoordinatedTurn((1.0, 1.0), 1.0)
    vx, vy = 3.0, -2.0
    x = np.array([[0.0, vx, 0.0, vy, theta]])
    a, b, c, s = _turn_values(theta)
    da, db = _turn_slopes(theta)
    terms = {  # each a sum of two rounded products: its error is relative to their sizes
        "x'": (a * vx, -b * vy),
        "vx'": (c * vx, -s * vy),
        "y'": (b * vx, a * vy),
        "vy'": (s * vx, c * vy),
        "dx'/domega": (da * vx, -db * vy),
        "dy'/domega": (db * vx, da * vy),
    }
    f, J = ct.f(x, 1.0)[0], ct.jacobian(x, 1.0)[0]
    got = dict(zip(terms, [f[0], f[1], f[2], f[3], J[0, 4], J[2, 4]], strict=True))
    tol = 8 * EPS / theta**2
    for name, (p, q) in terms.items():
        err = abs(Fraction(float(got[name])) - (p + q)) / (abs(p) + abs(q))
        assert err < tol, (theta, name, float(err), tol)


def test_turn_process_noise_takes_each_axis_its_own_density() -> None:
    """Q(dt) of the coordinated turn with q_x != q_y, by hand (dt = 2: the white-acceleration
    block [[dt^3/3, dt^2/2], [dt^2/2, dt]] is [[8/3, 2], [2, 2]]): q_x's block on [x, vx],
    q_y's on [y, vy], q_turn dt on omega, nothing between them."""
    qx, qy, qt = 0.25, 4.0, 1e-3
    Q = CoordinatedTurn((qx, qy), qt).Q(2.0)
    block = np.array([[8 / 3, 2.0], [2.0, 2.0]])
    want = np.zeros((5, 5))
    want[0:2, 0:2] = qx * block
    want[2:4, 2:4] = qy * block
    want[4, 4] = qt * 2.0
    np.testing.assert_allclose(Q, want, rtol=4 * EPS, atol=0)


# --------------------------------------------------------------------------------------------
# EKF and UKF against independent per-run implementations


class _TurnEKF(ExtendedKalmanFilter):
    """FilterPy's EKF with the coordinated turn's f as its prediction of the mean."""

    def __init__(self, motion, dt, *a, **kw):
        super().__init__(*a, **kw)
        self.motion, self.dt = motion, dt

    def predict_x(self, u=0):
        self.x = self.motion.f(self.x.ravel(), self.dt)[:, None]


def _filterpy_run(system: System, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """FilterPy's ExtendedKalmanFilter on one run (z: (K+1, m)), the CKF's stacked update with
    the sensors that measured, the Jacobians of the models, wrapped bearing residuals."""
    n = system.n
    motion = system.motion
    ekf = _TurnEKF(motion, 1.0, dim_x=n, dim_z=system.m)
    ekf.x, ekf.P = system.prior.mean[:, None].copy(), system.prior.cov.copy()
    ekf.Q = motion.Q(1.0)
    means, covs = [], []
    for k in range(z.shape[0]):
        if k:
            ekf.F = motion.jacobian(ekf.x.ravel(), 1.0)
            ekf.predict()
        use = [
            (s, sl) for s, sl in zip(system.sensors, system.sensor_slices, strict=True)
            if not np.isnan(z[k, sl]).any()
        ]  # fmt: skip
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


@pytest.mark.parametrize("turn", [False, True])
def test_ckf_ekf_equals_filterpy_per_run(turn: bool) -> None:
    system = _radar("EKF", n=5 if turn else 4, turn=turn)
    _, z = _data(system, 6, 20, drop=0.3)
    tr = estimate(system, "CKF", z, np.arange(21.0))
    for r in range(z.shape[0]):
        mean, cov = _filterpy_run(system, z[r])
        _close(tr.mean[r], mean)
        _close(tr.cov[r], cov)


def _plain_ukf_update(x, P, z, sensors, alpha=1.0, beta=2.0, kappa=0.0):
    """The contract's UKF update for one run, written out plainly."""
    n = len(x)
    lam = alpha**2 * (n + kappa) - n
    L = np.linalg.cholesky((n + lam) * P)
    X = [x] + [x + L[:, i] for i in range(n)] + [x - L[:, i] for i in range(n)]
    Wm = [lam / (n + lam)] + [1 / (2 * (n + lam))] * (2 * n)
    Wc = [lam / (n + lam) + 1 - alpha**2 + beta] + [1 / (2 * (n + lam))] * (2 * n)
    h = lambda v: np.concatenate([s.h(v) for s in sensors])  # noqa: E731
    ang = np.concatenate([s.angles for s in sensors])
    R = np.zeros((len(ang), len(ang)))
    i = 0
    for s in sensors:
        R[i : i + s.dim, i : i + s.dim] = s.R
        i += s.dim

    def diff(a, b):
        d = a - b
        d[ang] = wrap(d[ang])
        return d

    Z = [h(p) for p in X]
    zhat = Z[0] + sum(w * diff(zi, Z[0]) for w, zi in zip(Wm, Z, strict=True))
    zhat[ang] = wrap(zhat[ang])
    S = R + sum(w * np.outer(diff(zi, zhat), diff(zi, zhat)) for w, zi in zip(Wc, Z, strict=True))
    C = sum(w * np.outer(p - x, diff(zi, zhat)) for w, p, zi in zip(Wc, X, Z, strict=True))
    K = C @ np.linalg.inv(S)
    return x + K @ diff(z, zhat), P - K @ S @ K.T


def _plain_ukf_predict(x, P, motion, Q, alpha=1.0, beta=2.0, kappa=0.0):
    n = len(x)
    lam = alpha**2 * (n + kappa) - n
    L = np.linalg.cholesky((n + lam) * P)
    X = [x] + [x + L[:, i] for i in range(n)] + [x - L[:, i] for i in range(n)]
    Wm = [lam / (n + lam)] + [1 / (2 * (n + lam))] * (2 * n)
    Wc = [lam / (n + lam) + 1 - alpha**2 + beta] + [1 / (2 * (n + lam))] * (2 * n)
    Y = [motion.f(p, 1.0) for p in X]
    m = sum(w * y for w, y in zip(Wm, Y, strict=True))
    return m, Q + sum(w * np.outer(y - m, y - m) for w, y in zip(Wc, Y, strict=True))


@pytest.mark.parametrize("params", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0)])
def test_ckf_ukf_equals_a_plain_per_run_implementation(params) -> None:
    system = dataclasses.replace(_radar("UKF", n=5, turn=True), ukf=params)
    _, z = _data(system, 4, 15, drop=0.3)
    tr = estimate(system, "CKF", z, np.arange(16.0))
    for r in range(z.shape[0]):
        x, P = system.prior.mean.copy(), system.prior.cov.copy()
        for k in range(z.shape[1]):
            if k:
                x, P = _plain_ukf_predict(x, P, system.motion, system.motion.Q(1.0), *params)
            use = [
                (s, sl) for s, sl in zip(system.sensors, system.sensor_slices, strict=True)
                if not np.isnan(z[r, k, sl]).any()
            ]  # fmt: skip
            if use:
                zk = np.concatenate([z[r, k, sl] for _, sl in use])
                x, P = _plain_ukf_update(x, P, zk, [s for s, _ in use], *params)
            _close(tr.mean[r, k], x)
            _close(tr.cov[r, k], P)


def test_bearing_residuals_wrap_across_pi() -> None:
    """A target due west of the sensor (bearing +-pi): the estimates are those of the same
    problem turned by pi (bearing ~ 0, no wrapping), turned back."""
    for filt in ("EKF", "UKF"):
        west = _radar(filt)
        prior = Prior(np.array([-400.0, 3.0, 0.5, -2.0]), np.diag([100.0, 4.0, 100.0, 4.0]))
        sensor = RangeBearingSensor("a", np.zeros(2), (0, 2), 4, RB_R)
        west = dataclasses.replace(west, sensors=(sensor,), prior=prior)
        turn = np.diag([-1.0, -1.0, -1.0, -1.0])  # (x, y) -> (-x, -y): a rotation by pi
        east = dataclasses.replace(west, prior=Prior(turn @ prior.mean, prior.cov))
        x, z = _data(west, 5, 12, seed=4)
        assert (z[..., 1] > 3.0).any() and (z[..., 1] < -3.0).any()  # both sides of +-pi
        z_east = z.copy()
        z_east[..., 1] = wrap(z[..., 1] + math.pi)
        tw = estimate(west, "CKF", z, np.arange(13.0))
        te = estimate(east, "CKF", z_east, np.arange(13.0))
        _close(tw.mean, te.mean @ turn.T, 1e-8)
        _close(tw.cov, te.cov, 1e-8)


# --------------------------------------------------------------------------------------------
# Linear models: the EKF and the UKF are the KF; the PCRB is the CKF's covariance


def _linear_system(filt: str) -> System:
    F, Q = _cv()
    H1 = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    H2 = np.array([[1.0, 0, 0.5, 0]])
    sensors = (Sensor("a", H1, np.diag([4.0, 9.0])), Sensor("b", H2, np.array([[2.0]])))
    prior = Prior(np.array([1.0, 2.0, 3.0, 4.0]), np.diag([10.0, 4.0, 10.0, 4.0]))
    return System(F, Q, sensors, prior, filter=filt)


@pytest.mark.parametrize("filt", ["EKF", "UKF"])
@pytest.mark.parametrize("arch", ARCHS)
def test_on_a_linear_model_the_filters_equal_the_kf(filt: str, arch: str) -> None:
    system = _linear_system(filt)
    _, z = _data(system, 5, 12, drop=0.25)
    want = linear_estimate(system, z, arch)
    got = estimate(system, arch, z, np.arange(13.0))
    cov = want.cov if want.cov.ndim == 4 else np.broadcast_to(want.cov, got.cov.shape)
    _close(got.mean, want.mean, 1e-8)
    _close(got.cov, cov, 1e-8)


def test_pcrb_of_a_linear_model_is_the_ckf_covariance() -> None:
    system = _linear_system("EKF")
    steps = 15
    x, z = _data(system, 3, steps)
    mask = np.ones((steps + 1, system.m), dtype=bool)
    mask[1::3, 2] = False  # sensor b measures at two instants of three in every run
    z[:, ~mask] = np.nan
    acc = PcrbAccumulator(system, np.arange(steps + 1.0))
    acc.add(x, ~np.isnan(z[..., [0, 2]]))
    plan = build_plan(system, "CKF", steps, mask)
    _close(acc.bound(), plan.reported_cov, 1e-10)
    s = pcrb_summary(acc.bound())
    want = np.trace(plan.reported_cov, axis1=1, axis2=2).mean() / 4
    assert s["mse"] == pytest.approx(want, rel=1e-12)


@dataclass(frozen=True)
class _LinearAsNonlinear(MotionModel):
    """A linear motion that says it is not (the PCRB then takes the D11/D12/D22 form)."""

    F_: np.ndarray
    Q_: np.ndarray
    kind = "test-linear"

    @property
    def n(self) -> int:
        return self.F_.shape[0]

    def f(self, x, dt):
        return x @ self.F_.T

    def jacobian(self, x, dt):
        return np.broadcast_to(self.F_, np.shape(x)[:-1] + self.F_.shape)

    def Q(self, dt):
        return self.Q_


def test_pcrb_nonlinear_form_reduces_to_the_linear_one() -> None:
    """Tichavsky's D11/D12/D22 recursion with a constant Jacobian is (Q + F J^-1 F')^-1."""
    system = _radar()
    x, z = _data(system, 50, 10)
    present = ~np.isnan(z[..., [0, 2]])
    lin = PcrbAccumulator(system, np.arange(11.0))
    lin.add(x, present)
    dressed = dataclasses.replace(system, motion_model=_LinearAsNonlinear(system.F, system.Q))
    non = PcrbAccumulator(dressed, np.arange(11.0))
    non.add(x[:20], present[:20])  # two blocks: the same averages
    non.add(x[20:], present[20:])
    _close(non.bound(), lin.bound(), 1e-9)


def test_runs_are_independent_of_their_block() -> None:
    """Each run's estimates are the same alone as among others (batched, never mixed)."""
    system = _radar("UKF", n=5, turn=True)
    _, z = _data(system, 7, 10, drop=0.2)
    for arch in ("CKF", "MSC-GMF", "CI", "FBS"):
        all_runs = estimate(system, arch, z, np.arange(11.0))
        one = estimate(system, arch, z[3:4], np.arange(11.0))
        _close(one.mean[0], all_runs.mean[3], 1e-9)


def test_estimate_on_the_sensor_names_run_and_instant() -> None:
    system = _radar()
    on_sensor = Prior(np.array([0.0, 1.0, 0.0, 1.0]), system.prior.cov)
    system = dataclasses.replace(system, prior=on_sensor)
    _, z = _data(system, 4, 3)
    with pytest.raises(NumericalError, match=r"sensor 'a'.*range 0.*run 7, instant 0"):
        estimate(system, "CKF", z, np.arange(4.0), run_offset=7)
