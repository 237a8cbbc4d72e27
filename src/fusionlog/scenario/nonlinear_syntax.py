"""The scenario syntax of nonlinear sensors and motion (DESIGN.md, "Nonlinear sensors and
motion"): the range-bearing family's ``[[sensors]]`` tables, ``[model] kind =
"coordinated-turn"``, and ``[estimate] filter`` with ``[estimate.ukf]``.

    [[sensors]]   kind = "range-bearing" | "range" | "bearing", position = [px, py],
                  position_states = ["x", "y"] (default), R (m^2, rad^2), timing keys
    [model]       kind = "coordinated-turn", q = [qx, qy], q_turn   (state [x, vx, y, vy, omega])
    [estimate]    filter = "EKF" | "UKF" (required when a model is nonlinear)
    [estimate.ukf] alpha, beta, kappa (defaults 1, 2, 0; 0 < alpha <= 1, beta >= 0, and
                  0 < alpha^2 (n + kappa) = n + lambda <= chi2_n^-1(1 - eps): `_ukf_ranges`)

Every problem is one line naming the file, the key and the reason (`toml.Ctx.err`).
"""

from __future__ import annotations

import math
import sys
from typing import Any

from fusionlog.core.model import System
from fusionlog.core.models import CoordinatedTurn, SensorModel
from fusionlog.core.models.polar import POLAR_KINDS, PolarSensor

from . import toml
from .toml import Ctx

__all__ = [
    "FILTERS",
    "TURN_KEYS",
    "TURN_STATES",
    "check_nonlinear",
    "estimate_dict",
    "filter_section",
    "polar_dict",
    "polar_sensor",
    "turn_dict",
    "turn_section",
]

#: Values of [estimate] filter.
FILTERS: tuple[str, ...] = ("EKF", "UKF")
_UKF_KEYS = ("alpha", "beta", "kappa")
_UKF_DEFAULTS = (1.0, 2.0, 0.0)
#: [model] keys of kind = "coordinated-turn", and its state's default names.
TURN_KEYS = ("q", "q_turn")
TURN_STATES = ("x", "vx", "y", "vy", "omega")


def polar_sensor(
    ctx: Ctx, t: dict[str, Any], where: str, name: str, n: int, states: tuple[str, ...]
) -> SensorModel:
    """A range-bearing, range or bearing sensor's table."""
    cls = POLAR_KINDS[t["kind"]]
    position = toml.vector(ctx, t["position"], f"{where}.position", 2, "the sensor's x and y")
    pos_states = t.get("position_states", ["x", "y"])
    key = f"{where}.position_states"
    if (
        not isinstance(pos_states, list)
        or len(pos_states) != 2
        or not all(isinstance(p, str) for p in pos_states)
    ):
        raise ctx.err(
            key, f'expected two state names, e.g. ["x", "y"], got {toml.show(pos_states)}'
        )
    for p in pos_states:
        if p not in states:
            raise ctx.err(key, f"no state {p!r} (states: {', '.join(states)})")
    if pos_states[0] == pos_states[1]:
        raise ctx.err(key, f"the target's x and y are the same state {pos_states[0]!r}")
    m = len(cls.components)
    R = toml.matrix(ctx, t["R"], f"{where}.R", scalar=m == 1)
    if R.shape != (m, m):
        what = " and ".join(cls.components)
        raise ctx.err(
            f"{where}.R",
            f"shape {toml.shape(R)}, expected {m}x{m} (a {t['kind']} sensor measures {what})",
        )
    R = toml.covariance_checks(ctx, R, f"{where}.R", strict=True)
    idx = (states.index(pos_states[0]), states.index(pos_states[1]))
    # the timing keys are read by `sensors.sensor_from_table`, for every kind
    return cls(name, toml.readonly(position), idx, n, R, position_states=tuple(pos_states))


def polar_dict(s: SensorModel) -> dict[str, Any]:
    """A polar sensor's own keys (`polar_sensor`'s inverse)."""
    assert isinstance(s, PolarSensor)
    return {
        "position": toml.tolist(s.position),
        "position_states": list(s.position_states),
        "R": toml.tolist(s.R),
    }


def turn_section(
    ctx: Ctx, md: dict[str, Any], state_names: tuple[str, ...] | None, dt: float | None
) -> tuple[CoordinatedTurn, tuple[str, ...], float]:
    """[model] kind = "coordinated-turn": the model, the state names and dt."""
    for key in md:
        if key not in ("kind", *TURN_KEYS):
            raise ctx.err(
                f"model.{key}", "not allowed with kind = 'coordinated-turn' (it takes q, q_turn)"
            )
    for key in TURN_KEYS:
        if key not in md:
            raise ctx.err(
                f"model.{key}", "missing required key (kind = 'coordinated-turn' needs it)"
            )
    if dt is None:
        raise ctx.err("scenario.dt", "missing required key (kind = 'coordinated-turn' needs it)")
    q = toml.vector(ctx, md["q"], "model.q", 2, "[qx, qy]: one per axis")
    q_turn = toml.number(ctx, md["q_turn"], "model.q_turn")
    # Q must be invertible: the PCRB's recursion for nonlinear motion needs Q^-1.
    for where, v in (("model.q", float(q.min())), ("model.q_turn", q_turn)):
        if not v > 0:
            raise ctx.err(
                where, f"must be > 0 (the bound's recursion needs Q^-1), got {toml.fmt(v)}"
            )
    if state_names is None:
        state_names = TURN_STATES
    elif len(state_names) != 5:
        raise ctx.err(
            "scenario.state_names",
            "kind = 'coordinated-turn' has 5 states [x, vx, y, vy, omega], "
            f"got {len(state_names)} names",
        )
    return CoordinatedTurn((float(q[0]), float(q[1])), q_turn), state_names, dt


def turn_dict(motion: CoordinatedTurn) -> dict[str, Any]:
    """The [model] table of a coordinated turn (`turn_section`'s inverse)."""
    return {"kind": "coordinated-turn", "q": list(motion.q), "q_turn": motion.q_turn}


def filter_section(
    ctx: Ctx, doc: dict[str, Any], n: int, linear: bool
) -> tuple[str | None, tuple[float, float, float]]:
    """[estimate] filter and [estimate.ukf]: (filter or None, (alpha, beta, kappa))."""
    est = doc.get("estimate")
    est = est if isinstance(est, dict) else {}
    filt = None
    if "filter" in est:
        filt = toml.string(ctx, est["filter"], "estimate.filter")
        if filt not in FILTERS:
            raise ctx.err("estimate.filter", f"unknown filter {filt!r} (known: EKF, UKF)")
    elif not linear:
        raise ctx.err(
            "estimate.filter",
            'missing: a nonlinear sensor or motion needs filter = "EKF" or "UKF"',
        )
    ukf = _UKF_DEFAULTS
    if "ukf" in est:
        u = est["ukf"]
        if not isinstance(u, dict):
            raise ctx.err("estimate.ukf", f"expected a table, got {toml.tname(u)}")
        toml.check_keys(ctx, u, "estimate.ukf", _UKF_KEYS)
        ukf = tuple(
            toml.number(ctx, u[k], f"estimate.ukf.{k}") if k in u else d
            for k, d in zip(_UKF_KEYS, _UKF_DEFAULTS, strict=True)
        )
        alpha, _, kappa = ukf
        if not alpha > 0:
            raise ctx.err("estimate.ukf.alpha", f"must be > 0, got {toml.fmt(alpha)}")
        # alpha * alpha, not alpha**2: float ** raises OverflowError where * gives inf
        c = alpha * alpha * (n + kappa)
        if not c > 0 and n + kappa > 0:  # alpha so small that its square underflows
            raise ctx.err("estimate.ukf.alpha", f"too small: alpha^2 underflows to 0 (n = {n})")
        if not c > 0:
            raise ctx.err(
                "estimate.ukf.kappa",
                f"makes n + lambda = alpha^2 (n + kappa) = {toml.fmt(c)} "
                f"<= 0 (n = {n}): the sigma points need n + kappa > 0",
            )
        if not math.isfinite(c):
            raise ctx.err(
                "estimate.ukf.alpha",
                f"too large: n + lambda = alpha^2 (n + kappa) overflows (n = {n})",
            )
        _ukf_ranges(ctx, n, ukf)
    return filt, ukf  # type: ignore[return-value]


def _ukf_ranges(ctx: Ctx, n: int, ukf: tuple[float, float, float]) -> None:
    """The accepted ranges of the scaled unscented transform's parameters (Julier 2002, "The
    scaled unscented transformation"; Wan and van der Merwe 2000), each refused outside:

    - alpha in (0, 1]: it scales the sigma points' spread down from the unscaled transform's;
    - beta >= 0: beta = (kurtosis - 1) of the distribution whose fourth moment the points
      match (2 for a Gaussian), and no distribution has a kurtosis below 1;
    - kappa with 0 < n + lambda = alpha^2 (n + kappa) <= chi2_n^-1(1 - eps): the points lie
      sqrt(n + lambda) standard deviations from the mean, and beyond the radius that holds all
      but eps (2.2e-16) of the Gaussian's mass they sample a region a double cannot weigh
      against the rest (about 83 for n = 5; kappa = 1e300 put them 1e150 deviations out: CKF
      MSE 2207 against a bound of 23). The defaults (1, 2, 0) are inside for every n.
    """
    alpha, beta, kappa = ukf
    if not alpha <= 1.0:
        raise ctx.err("estimate.ukf.alpha", f"must be in (0, 1], got {toml.fmt(alpha)}")
    if not beta >= 0.0:
        raise ctx.err(
            "estimate.ukf.beta",
            f"must be >= 0 (beta = kurtosis - 1 of the distribution: 2 for a Gaussian), "
            f"got {toml.fmt(beta)}",
        )
    from scipy.special import gammainccinv  # the chi-square quantile, only with [estimate.ukf]

    top = 2.0 * float(gammainccinv(n / 2.0, sys.float_info.epsilon))
    c = alpha * alpha * (n + kappa)
    if c > top:
        raise ctx.err(
            "estimate.ukf.kappa",
            f"must be in ({-n}, {toml.fmt(top / (alpha * alpha) - n)}] with alpha = "
            f"{toml.fmt(alpha)} (n = {n}), got {toml.fmt(kappa)}: n + lambda = alpha^2 (n + "
            f"kappa) = {toml.fmt(c)} puts the sigma points {math.sqrt(c):.3g} standard "
            f"deviations out, beyond the radius holding all but 2.2e-16 of a Gaussian's mass "
            f"(n + lambda <= {toml.fmt(top)})",
        )


def estimate_dict(system: System) -> dict[str, Any]:
    """[estimate] filter and ukf of a system (empty when it has no filter set)."""
    if system.filter is None:
        return {}
    return {"filter": system.filter, "ukf": dict(zip(_UKF_KEYS, system.ukf, strict=True))}


def check_nonlinear(ctx: Ctx, system: System, has_correlations: bool) -> None:
    """What a system with a nonlinear model needs: a prior (the filters start from it) and
    independent sensor noises (the local filters' cross-covariances assume them)."""
    if system.linear:
        return
    if system.prior is None:
        raise ctx.err(
            "prior",
            "missing: the EKF and UKF start from [prior] (mean, cov) when a model is nonlinear",
        )
    if has_correlations:
        raise ctx.err(
            "correlations",
            "not supported with nonlinear sensors or motion (their noises must be independent)",
        )
