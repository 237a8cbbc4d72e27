"""``fusionlog identify``: noise covariances (R, Q, n0, cross-covariances, the prior's) from the
data by maximum likelihood, their standard errors, and what the believed values cost.

The likelihood is that of the readings through the filter's innovations
(`core.likelihood.loglik`: exact for linear models; the EKF's approximation for nonlinear ones),
pooled over the runs; with the truth (``with_truth``) the joint likelihood of readings and
truth. Each trial value is applied to a copy of the scenario's document and validated by the
scenario loader (`grid.key_path` / `identify_params`: the sweep's keys, one validation path),
and only the noise it gives (the prior's covariance, Q per interval, R per instant) varies
between candidates, so that the finite differences of the gradient and of the Hessian are one
pass over the data each (`_Objective`).

The optimiser is scipy's BFGS from the file's values in the unconstrained coordinates of
`identify_params`; the standard errors come from the observed information, the Hessian of the
log-likelihood at the optimum by central second differences, inverted (the delta method maps
them to the values' entries). A Hessian that is not positive definite, or whose smallest
eigenvalue is lost in the rounding of the likelihood, means the data do not tell that
parameter apart (a flat likelihood): refused, naming the parameter that dominates the flat
direction.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fusionlog.core.likelihood import Noise, loglik
from fusionlog.core.model import System
from fusionlog.errors import FusionlogError
from fusionlog.scenario import Scenario, scenario_from_doc, toml

from . import identify_params as ip
from .common import Counter
from .noise import with_covariances
from .simulation import Simulation, state_scenario

__all__ = ["Identification", "identify"]

#: Candidates evaluated in one pass of the likelihood (their noise arrays and filters' states
#: side by side): the gradient of up to 15 coordinates is one pass, a Hessian a few.
CHUNK = 32
#: Steps of the finite differences, relative to each coordinate's scale (`identify_params.
#: scales`). The gradient's central difference errs by h^2 f''' / 6 and the likelihood's
#: rounding / h; the Hessian's second difference by h^2 f'''' / 12 and rounding / h^2. The
#: rounding is that of the filter's recursion, not of the sum alone: on evo's bag with the
#: truth (|log p| = 2.3e7: innovations of centimetres against positions of metres) it is
#: ~3e-13 of |log p|, and a step of 1e-4 gave a Hessian off by 2,500 in entries of 6.6e4,
#: with negative eigenvalues at a maximum; 3e-3 puts the rounding near 1 and the truncation
#: (h^2 / 12 of the curvature in the log coordinates) near 1e-6 of it.
H_GRAD, H_HESS = 1e-5, 3e-3
#: The likelihood's rounding, relative to its size (see above).
ROUNDING = 3e-13
#: The smallest Hessian eigenvalue (information) below this share of the largest, or within
#: what rounding moves the second differences by, is a flat likelihood.
FLAT_RTOL = 1e-9
MAX_ITER = 200


@dataclass
class Identification:
    """The identified values (each in the file's form: a number, a list, a matrix), their
    standard errors (same shapes), the log-likelihood at the optimum and at the file's values,
    the tuned scenario (its TOML text `toml`), and the cost of the file's values (`cost`,
    `core.exact` per architecture; `identify_cost`)."""

    keys: list[str]
    values: dict[str, Any]
    stderr: dict[str, Any]
    given: dict[str, Any]
    loglik: float
    loglik_given: float
    with_truth: bool
    exact: bool  # a linear model: the likelihood is exact (else the EKF's approximation)
    scenario: Scenario
    toml: str
    iterations: int
    observations: int
    cost: dict[str, dict[str, float | None] | None] = field(default_factory=dict)
    whiteness: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def report(self) -> dict[str, Any]:
        """REPORT.json (DESIGN.md "Noise from the data")."""
        return {
            "method": "ml",
            "with_truth": self.with_truth,
            "loglik": self.loglik,
            "parameters": {
                k: {"value": self.values[k], "stderr": self.stderr[k], "given": self.given[k]}
                for k in self.keys
            },
            "cost": self.cost,
        }

    def table(self) -> str:
        """The printed summary (`identify_cost.format_identification`)."""
        from .identify_cost import format_identification

        return format_identification(self)


@dataclass
class _Data:
    """What the likelihood reads: the readings (M, K+1, m), the truth's states and values."""

    system: System  # the scenario's model on the log's instants (F, H, prior mean shared)
    z: np.ndarray
    truth: np.ndarray | None
    truth_rows: np.ndarray | None
    sim: Simulation


class _Objective:
    """The log-likelihood of candidate coordinates theta, many at once."""

    def __init__(self, sc: Scenario, doc: dict, params: list[ip.Param], data: _Data) -> None:
        self.sc, self.doc, self.params, self.data = sc, doc, params, data
        self.file = sc.path or sc.name
        base = data.system
        K = data.z.shape[1] - 1
        if base.Qs is None:
            self.q_first, self.q_at = None, np.zeros(K, dtype=int)
        else:  # Q depends on the interval only: one per distinct interval
            _, self.q_first, self.q_at = np.unique(
                np.diff(data.sim.times), return_index=True, return_inverse=True
            )
        self.r_at = np.zeros(K + 1, dtype=int) if base.Rs is None else np.arange(K + 1)
        # whether a candidate moves the motion model: else its process noise is the file's, on
        # the log's instants once (a matrix exponential per interval is the costly part of a
        # candidate on a long irregular log: 20 ms on evo's bag, against 2 ms for the rest)
        self.moves = any(p.path[0] == "model" for p in params)
        self.Q = None if self.moves else self._Q(base)[None]
        self.calls = 0

    def system_of(self, values: list[np.ndarray], where: str | None = None) -> System:
        """The model with these values, through the scenario loader, on the log's instants
        (its motion left undiscretised when no candidate moves it: `noise` then takes the
        file's)."""
        doc = ip.edited(self.doc, self.params, values)
        sc = scenario_from_doc(doc, where or self.file, self.sc.source, self.sc.path)
        if self.moves:
            return self.data.sim.on_instants(sc.system)
        sim = self.data.sim
        return with_covariances(sc.system, sim.covariances, len(sim.times), sim.scenario.name)

    def _Q(self, s: System) -> np.ndarray:
        """The process noise (U, n, n) of the distinct intervals of `s` on the log's instants."""
        return s.GQG[None] if self.q_first is None else s.Qs[self.q_first]

    def noise(self, systems: list[System]) -> Noise:
        """The candidates' noise arrays (`core.likelihood.Noise`)."""
        P0 = [s.prior.cov for s in systems]
        Q = self.Q if self.Q is not None else np.array([self._Q(s) for s in systems])
        R = [s.R[None] if s.Rs is None else s.Rs for s in systems]
        return Noise(np.array(P0), Q, self.q_at, np.array(R), self.r_at)

    def __call__(self, thetas: np.ndarray) -> np.ndarray:
        """log p (C,) of each row of thetas (C, P); -inf where a value is refused by the
        loader (e.g. a cross-covariance that makes R indefinite) or S is not definite."""
        out = np.full(len(thetas), -np.inf)
        for a in range(0, len(thetas), CHUNK):
            systems = [self._system_or_none(t) for t in thetas[a : a + CHUNK]]
            ok = np.array([s is not None for s in systems])
            if ok.any():
                d = self.data
                noise = self.noise([s for s in systems if s is not None])
                ll = loglik(d.system, d.z, noise, d.truth, d.truth_rows)
                out[a : a + CHUNK][ok] = ll
        self.calls += len(thetas)
        return out

    def _system_or_none(self, theta: np.ndarray) -> System | None:
        if not np.isfinite(theta).all():
            return None
        try:
            return self.system_of(ip.from_theta(self.params, theta))
        except FusionlogError:
            return None


def _data(sc: Scenario, sim: Simulation, with_truth: bool) -> _Data:
    """The readings and (with_truth) the truth of `sim`, checked: some data, a prior."""
    file = sc.path or sc.name
    system = sim.on_instants(sc.system)
    if system.prior is None:
        raise FusionlogError(
            f"{file}: identify needs a [prior]: without one the filters start from no "
            "information, and the likelihood of the readings before the state is observable "
            "(the diffuse one) is not computed; give a [prior] (a wide one approaches it)"
        )
    z = sim.stacked(system)
    if not np.isfinite(z).any():
        raise FusionlogError(f"{file}: no data (no reading of any sensor)")
    truth = rows = None
    if with_truth:
        if sim.truth is None or not np.isfinite(sim.truth).any():
            raise FusionlogError(f"{file}: --with-truth, but the log has no truth")
        names = (sim.truth_info or {}).get("states") or list(system.state_names)
        rows = np.array([list(system.state_names).index(s) for s in names])
        truth = sim.truth[..., rows]
    return _Data(system, z, truth, rows, sim)


def _gradient(f: _Objective, theta: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
    """-log p / scale and its gradient by central differences, one pass."""
    P = len(theta)
    steps = H_GRAD * ip.scales(f.params, theta)
    pts = np.vstack([theta, theta + np.diag(steps), theta - np.diag(steps)])
    ll = f(pts)
    if not np.isfinite(ll[0]):
        return np.inf, np.zeros(P)
    g = (ll[1 : P + 1] - ll[P + 1 :]) / (2 * steps)
    g = np.where(np.isfinite(g), g, 0.0)
    return -ll[0] / scale, -g / scale


def _hessian(f: _Objective, theta: np.ndarray) -> tuple[np.ndarray, float]:
    """The Hessian of log p at theta by central second differences (one pass), and the
    rounding level of its entries."""
    P = len(theta)
    h = H_HESS * ip.scales(f.params, theta)
    pts = [theta]
    for i in range(P):
        pts += [theta + h[i] * np.eye(P)[i], theta - h[i] * np.eye(P)[i]]
    pairs = [(i, j) for i in range(P) for j in range(i + 1, P)]
    for i, j in pairs:
        ei, ej = h[i] * np.eye(P)[i], h[j] * np.eye(P)[j]
        pts += [theta + ei + ej, theta + ei - ej, theta - ei + ej, theta - ei - ej]
    ll = f(np.array(pts))
    f0 = ll[0]
    H = np.zeros((P, P))
    for i in range(P):
        H[i, i] = (ll[1 + 2 * i] - 2 * f0 + ll[2 + 2 * i]) / h[i] ** 2
    at = 1 + 2 * P
    for i, j in pairs:
        a, b, c, d = ll[at : at + 4]
        H[i, j] = H[j, i] = (a - b - c + d) / (4 * h[i] * h[j])
        at += 4
    rounding = ROUNDING * max(1.0, abs(f0)) / float(np.min(h)) ** 2
    return H, rounding


def _flat(params: list[ip.Param], info: np.ndarray, rounding: float) -> tuple[str, str] | None:
    """The key of the parameter along the flattest direction of the information matrix
    (minus the Hessian), when that direction is flat or curves up (then not a maximum), and
    which of the two; None when every one is curved down."""
    if not np.isfinite(info).all():
        return params[0].key, "flat"
    w, V = np.linalg.eigh(info)
    if w[0] > max(FLAT_RTOL * max(w[-1], 0.0), 10 * rounding):
        return None
    return _owner(params, V[:, 0]), "flat" if w[0] >= -10 * rounding else "up"


def _owner(params: list[ip.Param], direction: np.ndarray) -> str:
    """The key of the parameter with the largest share of a direction in theta."""
    owner = np.repeat(np.arange(len(params)), [p.size for p in params])
    share = np.bincount(owner, weights=direction**2, minlength=len(params))
    return params[int(np.argmax(share))].key


def _flat_at(f: _Objective, theta: np.ndarray, ll: float) -> int | None:
    """The first coordinate along which the likelihood does not move at all at theta (to
    rounding, both ways): a parameter the data say nothing of (say a cross-covariance of two
    sensors that never measure at the same instant). Checked at the file's values, before
    the optimiser wanders along it."""
    h = H_HESS * ip.scales(f.params, theta)
    P = len(theta)
    ll_pm = f(np.vstack([theta + np.diag(h), theta - np.diag(h)]))
    still = np.abs(ll_pm - ll) <= 1e-13 * max(1.0, abs(ll))
    flat = np.flatnonzero(still[:P] & still[P:])
    return int(flat[0]) if len(flat) else None


def _refuse_flat(params: list[ip.Param], flat: int | tuple[str, str] | None) -> None:
    """The one-line refusal of a parameter the data cannot tell (a coordinate, or a key and
    how the likelihood is shaped along it: "flat", "up" or "rising")."""
    if flat is None:
        return
    how = "flat"
    if isinstance(flat, int):
        owner = np.repeat(np.arange(len(params)), [p.size for p in params])
        key = params[int(owner[flat])].key
    else:
        key, how = flat
    why = {
        "rising": f"no maximum of the likelihood within {MAX_ITER} iterations: it still rises "
        "along it",
        "up": "the likelihood curves up along it where the optimiser stopped: not a maximum",
        "flat": "the likelihood is flat along it: its information matrix is singular",
    }[how]
    raise FusionlogError(f"--param {key}: not identifiable from these data ({why})")


def identify(
    scenario: Scenario | str | os.PathLike[str],
    sim: Simulation,
    params: list[str] | str,
    *,
    with_truth: bool = False,
    cost: bool = True,
) -> Identification:
    """Maximum-likelihood values of the scenario's `params` (dotted keys) from the runs of
    `sim` (`fusionlog.simulate`, or a replay's recorded readings), with standard errors; the
    cost of the file's values (`identify_cost.cost_of`) unless `cost` is false. One-line
    FusionlogError naming the parameter or the file on bad input."""
    sc = state_scenario(scenario)
    if isinstance(params, str):
        params = [params]
    file = sc.path or sc.name
    if not sc.source:
        raise FusionlogError(f"{file}: identify needs the scenario's TOML text (fusionlog.load)")
    doc = toml.parse_toml(sc.source, file)
    plist = ip.params_of(doc, list(params), file)
    data = _data(sc, sim, with_truth)
    f = _Objective(sc, doc, plist, data)
    theta0 = ip.to_theta(plist, [p.given for p in plist])
    f.system_of([p.given for p in plist])  # the file's values go through the loader
    ll0 = float(f(theta0[None])[0])
    if not np.isfinite(ll0):
        raise FusionlogError(
            f"{file}: the likelihood is not finite at the file's values (a predicted reading "
            "with a covariance that is not positive definite, or a reading beyond the float "
            "range)"
        )
    _refuse_flat(plist, _flat_at(f, theta0, ll0))
    observations = int(np.isfinite(data.z).sum())
    if data.truth is not None:
        observations += int(np.isfinite(data.truth).sum())
    theta, iterations, converged = _maximise(f, theta0, observations)
    if not converged:  # the parameter the likelihood still rises along most
        _refuse_flat(plist, (_owner(plist, _gradient(f, theta, 1.0)[1]), "rising"))
    info, rounding = _hessian(f, theta)
    info = -info
    _refuse_flat(plist, _flat(plist, info, rounding))
    cov_theta = np.linalg.inv(info)
    values = ip.from_theta(plist, theta)
    J = ip.jacobian(plist, theta)
    se = np.sqrt(np.maximum(np.diag(J @ cov_theta @ J.T), 0.0))
    stderr, at = {}, 0
    for p, v in zip(plist, values, strict=True):
        stderr[p.key] = p.value(se[at : at + v.size].reshape(v.shape))
        at += v.size
    text = ip.written_back(sc.source, doc, plist, values, file)
    out = Identification(
        keys=[p.key for p in plist],
        values={p.key: p.value(v) for p, v in zip(plist, values, strict=True)},
        stderr=stderr,
        given={p.key: p.value(p.given) for p in plist},
        loglik=float(f(theta[None])[0]),
        loglik_given=ll0,
        with_truth=with_truth,
        exact=data.system.linear,
        scenario=scenario_from_doc(ip.edited(doc, plist, values), file, text, sc.path),
        toml=text,
        iterations=iterations,
        observations=observations,
    )
    if cost:
        from .identify_cost import cost_of, whiteness_of

        out.cost = cost_of(sc, out.scenario, sim)
        out.whiteness = whiteness_of(out.scenario, sim)
    return out


def _maximise(f: _Objective, theta0: np.ndarray, scale: float) -> tuple[np.ndarray, int, bool]:
    """BFGS on -log p / (number of observations) from theta0; (theta, iterations, whether it
    stopped before using all MAX_ITER: converged, or no longer able to improve)."""
    from scipy.optimize import minimize

    bar = Counter("identify", "iteration")
    try:
        res = minimize(
            lambda t: _gradient(f, t, scale),
            theta0,
            jac=True,
            method="BFGS",
            options={"gtol": 1e-7, "maxiter": MAX_ITER},
            callback=lambda *_: bar.update(),
        )
    finally:
        bar.close()
    return np.asarray(res.x, dtype=float), int(res.nit), int(res.nit) < MAX_ITER
