"""The state kind's scenario and model files (pipeline/*.toml): parsing and validation.

A scenario file has the sections (DESIGN.md, "Scenario TOML")::

    [scenario]       name, description, steps (K: instants k = 0..K), runs (M), seed, dt,
                     state_names
    [model]          kind = "constant-velocity" with n0 (N0 = n0 * dt, eqs. 41-42) and
                     optionally axes (N independent axes, state per axis [p, v]);
                     kind = "continuous" with A, Qc (F = expm(A dt), Q by Van Loan);
                     or explicit F, Q and optionally G (default identity)
    [prior]          mean, cov of p(x_0 | z_-1); omit it for "no prior information"
    [truth]          initial_mean, initial_cov: where the true x_0 is drawn from
                     (optional; each defaults to the prior's)
    [[sensors]]      name, H, R (a scalar R for a one-row H; a one-row H may be a flat list);
                     optionally period, offset (s) and dropout (probability), core.timing
    [[correlations]] sensors = ["a", "b"], cov = E[v_a v_b^T] (m_a x m_b)
    [estimate]       architectures (default: all of names.STATE_ARCHITECTURES)
    [evaluate]       confidence (two-sided chi-square band, default 0.95),
                     sample_runs (default 3), plane_view (2-D state plane view, default false)

A model file (``fusionlog estimate --model MODEL.toml``) has the same sections, but [scenario] is
optional and none of its keys is required there (``dt`` is required for the constant-velocity
kind, whose matrices depend on it), and neither [prior] nor [truth] is required.

Every problem is reported as a ValidationError with a one-line message
``<file>: <key path>: <reason>``; key paths index arrays from 0 (``sensors[1].R`` is the
second sensor's R). Matrices of the resolved System are float64, symmetrised where they are
covariances, and read-only.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fusionlog.core.model import Prior, Sensor, System, constant_velocity
from fusionlog.core.names import STATE_ARCHITECTURES, parse_arch
from fusionlog.core.timing import SensorTiming, constant_velocity_continuous, van_loan

from . import toml
from .base import DEFAULT_CONFIDENCE, DEFAULT_SAMPLE_RUNS, MAX_INDEX, Scenario, header
from .toml import Ctx

__all__ = [
    "MODEL_KINDS",
    "model_from_doc",
    "state_from_doc",
    "system_from_dict",
    "system_to_dict",
]

#: Values of [model].kind.
MODEL_KINDS: tuple[str, ...] = ("constant-velocity", "continuous")

_TOP_KEYS = (
    "scenario",
    "model",
    "prior",
    "truth",
    "sensors",
    "correlations",
    "estimate",
    "evaluate",
)
_SCENARIO_KEYS = ("name", "description", "steps", "runs", "seed", "dt", "state_names")
_MODEL_KEYS = ("kind", "n0", "axes", "A", "Qc", "F", "Q", "G")
_PRIOR_KEYS = ("mean", "cov")
_TRUTH_KEYS = ("initial_mean", "initial_cov")
_SENSOR_KEYS = ("name", "H", "R")
_TIMING_KEYS = ("period", "offset", "dropout")
_CORRELATION_KEYS = ("sensors", "cov")
_EVALUATE_KEYS = ("confidence", "sample_runs", "plane_view")


def system_to_dict(system: System) -> dict[str, Any]:
    """The resolved system as JSON-able plain data (for MCAP metadata).

    The layout is that of a model file with explicit matrices (plus, for a model given in
    continuous time, a ``continuous`` table with A and Qc, used on irregular instants);
    `system_from_dict` is its inverse.
    """
    names = [s.name for s in system.sensors]
    d: dict[str, Any] = {
        "scenario": {"dt": float(system.dt), "state_names": list(system.state_names)},
        "model": {"F": toml.tolist(system.F), "Q": toml.tolist(system.Q)},
    }
    if system.G is not None:
        d["model"]["G"] = toml.tolist(system.G)
    if system.prior is not None:
        d["prior"] = {"mean": toml.tolist(system.prior.mean), "cov": toml.tolist(system.prior.cov)}
    if system.initial is not None:
        d["truth"] = {
            "initial_mean": toml.tolist(system.initial.mean),
            "initial_cov": toml.tolist(system.initial.cov),
        }
    if system.continuous is not None:
        # F and Q stay as they are (bit for bit); the continuous model rides beside them for
        # instants other than k dt, outside the model-file sections.
        A, Qc = system.continuous
        d["continuous"] = {"A": toml.tolist(A), "Qc": toml.tolist(Qc)}
    d["sensors"] = [
        {"name": s.name, "H": toml.tolist(s.H), "R": toml.tolist(s.R)} | _timing_dict(s.timing)
        for s in system.sensors
    ]
    d["correlations"] = [
        {"sensors": [names[i], names[j]], "cov": toml.tolist(c)}
        for (i, j), c in sorted(system.cross_R.items())
    ]
    return d


def _timing_dict(t: SensorTiming) -> dict[str, float]:
    """The timing keys that differ from their defaults."""
    d = {"offset": t.offset, "dropout": t.dropout}
    d = {k: float(v) for k, v in d.items() if v != 0.0}
    return d if t.period is None else {"period": float(t.period)} | d


def system_from_dict(d: dict[str, Any], source: str = "<system dict>") -> System:
    """Rebuild (and re-validate) a System from `system_to_dict` output."""
    if not isinstance(d, dict):
        raise Ctx(source).err("(top level)", f"expected a table, got {toml.tname(d)}")
    d = dict(d)
    cont = d.pop("continuous", None)
    system = model_from_doc(d, source)
    if cont is None:
        return system
    ctx = Ctx(source)
    if not isinstance(cont, dict) or set(cont) != {"A", "Qc"}:
        raise ctx.err("continuous", "expected a table with A and Qc")
    A = toml.matrix(ctx, cont["A"], "continuous.A", scalar=True)
    if A.shape != (system.n, system.n):
        raise ctx.err("continuous.A", f"shape {toml.shape(A)}, expected {system.n}x{system.n}")
    Qc = toml.covariance(ctx, cont["Qc"], "continuous.Qc", system.n, strict=False)
    return dataclasses.replace(system, continuous=(toml.readonly(A), Qc))


# --------------------------------------------------------------------------------------------
# Documents


def state_from_doc(doc: dict[str, Any], file: str, source: str, path: str | None) -> Scenario:
    """A state scenario from a parsed TOML document; `file` names it in errors, `source` is the
    text as written (recorded in the sensors file)."""
    ctx = Ctx(file)
    toml.check_keys(ctx, doc, "(top level)", _TOP_KEYS, what="section")
    sc = toml.table(ctx, doc, "scenario", required=True)
    toml.check_keys(ctx, sc, "scenario", _SCENARIO_KEYS)
    h = header(ctx, sc, model=False)

    system = _system(ctx, doc, sc, need_truth=True)
    check_schedule(ctx, system, h.steps, "scenario.steps")
    architectures = _architectures(ctx, doc, system)
    confidence, sample_runs, plane_view = _evaluate(ctx, doc)
    if plane_view and system.n != 2:
        raise ctx.err("evaluate.plane_view", f"needs a 2-D state, this one has {system.n}")
    return Scenario.of(
        "state",
        h,
        system,
        dt=system.dt,
        state_names=system.state_names,
        architectures=architectures,
        confidence=confidence,
        sample_runs=sample_runs,
        plane_view=plane_view,
        source=source,
        path=path,
    )


def model_from_doc(doc: dict[str, Any], file: str) -> System:
    """The filter model of a model file (``estimate --model``): a scenario file in which
    [scenario] and its keys are optional; only the system is used."""
    ctx = Ctx(file)
    toml.check_keys(ctx, doc, "(top level)", _TOP_KEYS, what="section")
    sc = toml.table(ctx, doc, "scenario", required=False) or {}
    toml.check_keys(ctx, sc, "scenario", _SCENARIO_KEYS)
    # A full scenario file is a valid model file: check what it says, use only the system.
    header(ctx, sc, model=True)
    system = _system(ctx, doc, sc, need_truth=False)
    _architectures(ctx, doc, system)
    _evaluate(ctx, doc)
    return system


def _system(ctx: Ctx, doc: dict[str, Any], sc: dict[str, Any], *, need_truth: bool) -> System:
    state_names = None
    if "state_names" in sc:
        state_names = toml.names_list(ctx, sc["state_names"], "scenario.state_names")
    dt = None
    if "dt" in sc:
        dt = toml.number(ctx, sc["dt"], "scenario.dt")
        if not dt > 0:
            raise ctx.err("scenario.dt", f"must be > 0, got {toml.fmt(dt)}")

    F, Q, G, state_names, dt, continuous = _model(ctx, doc, state_names, dt)
    n = F.shape[0]

    prior = None
    pr = toml.table(ctx, doc, "prior", required=False)
    if pr is not None:
        toml.check_keys(ctx, pr, "prior", _PRIOR_KEYS, required=_PRIOR_KEYS)
        prior = Prior(
            toml.vector(ctx, pr["mean"], "prior.mean", n),
            # Positive definite: a filter's covariance must be invertible (information form,
            # Millman's formula); a perfectly known component belongs in [truth], not here.
            toml.covariance(ctx, pr["cov"], "prior.cov", n, strict=True),
        )
    elif abs(np.linalg.det(F)) <= 1e-12 * max(1.0, float(np.abs(F).max()) ** n):
        raise ctx.err(
            "model.F",
            "must be invertible when there is no [prior]: the filters start in information "
            "form and predict through F^-1",
        )

    initial = None
    tr = toml.table(ctx, doc, "truth", required=False)
    if tr is not None:
        toml.check_keys(ctx, tr, "truth", _TRUTH_KEYS)
        if prior is None:
            for key in _TRUTH_KEYS:
                if key not in tr:
                    raise ctx.err(
                        f"truth.{key}", "missing required key (there is no [prior] to default to)"
                    )
        mean = (
            toml.vector(ctx, tr["initial_mean"], "truth.initial_mean", n)
            if "initial_mean" in tr
            else prior.mean
        )
        cov = (
            toml.covariance(ctx, tr["initial_cov"], "truth.initial_cov", n, strict=False)
            if "initial_cov" in tr
            else prior.cov
        )
        initial = Prior(mean, cov)
    if need_truth and prior is None and initial is None:
        raise ctx.err(
            "prior",
            "missing: give [prior] (mean, cov) or, for no prior information, "
            "[truth] (initial_mean, initial_cov) to draw the true x_0 from",
        )

    sensors = _sensors(ctx, doc, n)
    cross_R = _correlations(ctx, doc, sensors)

    return System(
        F=F,
        Q=Q,
        G=G,
        sensors=sensors,
        prior=prior,
        cross_R=cross_R,
        initial=initial,
        dt=dt,
        state_names=state_names,
        continuous=continuous,
    )


def _model(
    ctx: Ctx, doc: dict[str, Any], state_names: tuple[str, ...] | None, dt: float | None
) -> Model:
    md = toml.table(ctx, doc, "model", required=True)
    toml.check_keys(ctx, md, "model", _MODEL_KEYS)
    if "kind" in md:
        kind = toml.string(ctx, md["kind"], "model.kind")
        if kind not in MODEL_KINDS:
            raise ctx.err("model.kind", f"unknown kind {kind!r} (known: {', '.join(MODEL_KINDS)})")
        own = {"constant-velocity": ("n0", "axes"), "continuous": ("A", "Qc")}[kind]
        for key in ("F", "Q", "G", "n0", "axes", "A", "Qc"):
            if key in md and key not in own:
                raise ctx.err(
                    f"model.{key}",
                    f"not allowed with kind = {kind!r} (it takes {', '.join(own)})",
                )
        if dt is None:
            raise ctx.err("scenario.dt", f"missing required key (kind = {kind!r} needs it)")
        if kind == "constant-velocity":
            return _constant_velocity(ctx, md, state_names, dt)
        return _continuous(ctx, md, state_names, dt)

    for key in ("n0", "axes", "A", "Qc"):
        if key in md:
            raise ctx.err(
                f"model.{key}", "only used with kind = 'constant-velocity' or 'continuous'"
            )
    for key in ("F", "Q"):
        if key not in md:
            raise ctx.err(
                f"model.{key}", "missing required key (give kind = 'constant-velocity' or F and Q)"
            )
    F = toml.matrix(ctx, md["F"], "model.F", scalar=True)
    if F.shape[0] != F.shape[1]:
        raise ctx.err("model.F", f"must be square, got {toml.shape(F)}")
    n = F.shape[0]
    if state_names is None:
        state_names = tuple(f"x{i + 1}" for i in range(n))
    elif len(state_names) != n:
        raise ctx.err(
            "model.F",
            f"shape {toml.shape(F)} does not match the {len(state_names)} "
            f"scenario.state_names (expected {len(state_names)}x{len(state_names)})",
        )
    G = None
    q = n
    if "G" in md:
        G = toml.matrix(ctx, md["G"], "model.G", scalar=True, row=n == 1)
        if G.shape[0] != n:
            raise ctx.err("model.G", f"shape {toml.shape(G)}, expected {n} rows (n, as F)")
        q = G.shape[1]
        G = toml.readonly(G)
    Q = toml.matrix(ctx, md["Q"], "model.Q", scalar=True)
    if Q.shape != (q, q):
        why = f"q x q, q = {q} columns of G" if G is not None else "n x n, as F"
        raise ctx.err("model.Q", f"shape {toml.shape(Q)}, expected {q}x{q} ({why})")
    Q = toml.covariance_checks(ctx, Q, "model.Q", strict=False)
    return toml.readonly(F), Q, G, state_names, 1.0 if dt is None else dt, None


Model = tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple[str, ...], float, Any]


def _constant_velocity(
    ctx: Ctx, md: dict[str, Any], state_names: tuple[str, ...] | None, dt: float
) -> Model:
    """Eqs. (41)-(42) with N0 = n0 dt, on `axes` independent axes (state per axis [p, v])."""
    if "n0" not in md:
        raise ctx.err("model.n0", "missing required key (kind = 'constant-velocity' needs it)")
    n0 = toml.number(ctx, md["n0"], "model.n0")
    if n0 < 0:
        raise ctx.err("model.n0", f"must be >= 0, got {toml.fmt(n0)}")
    axes = toml.integer(ctx, md.get("axes", 1), "model.axes", minimum=1)
    if axes > 64:
        raise ctx.err("model.axes", f"must be <= 64, got {axes}")
    if state_names is None:
        if axes == 1:
            state_names = ("position", "velocity")
        else:
            names = "xyz"[:axes] if axes <= 3 else [f"p{i + 1}" for i in range(axes)]
            state_names = tuple(x for a in names for x in (a, f"v{a}"))
    elif len(state_names) != 2 * axes:
        raise ctx.err(
            "scenario.state_names",
            f"kind = 'constant-velocity' with {axes} ax{'es' if axes > 1 else 'is'} has "
            f"{2 * axes} states ([p, v] per axis), got {len(state_names)} names",
        )
    F1, Q1 = constant_velocity(dt, n0 * dt)
    F, Q = np.kron(np.eye(axes), F1), np.kron(np.eye(axes), Q1)
    continuous = constant_velocity_continuous(axes, n0 * dt)
    return toml.readonly(F), toml.readonly(Q), None, state_names, dt, continuous


def _continuous(
    ctx: Ctx, md: dict[str, Any], state_names: tuple[str, ...] | None, dt: float
) -> Model:
    """dx = A x dt + dw, E[dw dw'] = Qc dt: F = expm(A dt) and Q by Van Loan's method."""
    for key in ("A", "Qc"):
        if key not in md:
            raise ctx.err(f"model.{key}", "missing required key (kind = 'continuous' needs it)")
    A = toml.matrix(ctx, md["A"], "model.A", scalar=True)
    if A.shape[0] != A.shape[1]:
        raise ctx.err("model.A", f"must be square, got {toml.shape(A)}")
    n = A.shape[0]
    if state_names is None:
        state_names = tuple(f"x{i + 1}" for i in range(n))
    elif len(state_names) != n:
        raise ctx.err(
            "model.A",
            f"shape {toml.shape(A)} does not match the {len(state_names)} scenario.state_names",
        )
    Qc = toml.covariance(ctx, md["Qc"], "model.Qc", n, strict=False)
    with np.errstate(all="ignore"):
        F, Q = van_loan(A, Qc, dt)
    if not (np.isfinite(F).all() and np.isfinite(Q).all()):
        raise ctx.err("model.A", f"expm(A dt) overflows for dt = {toml.fmt(dt)}")
    A = toml.readonly(np.array(A))
    return toml.readonly(F), toml.readonly(Q), None, state_names, dt, (A, Qc)


def _timing(ctx: Ctx, t: dict[str, Any], where: str) -> SensorTiming:
    """A sensor's period, offset (s) and dropout probability; the horizon is checked later,
    when the instants are known (`check_schedule`)."""
    period = None
    if "period" in t:
        period = toml.number(ctx, t["period"], f"{where}.period")
        if not period > 0:
            raise ctx.err(f"{where}.period", f"must be > 0, got {toml.fmt(period)}")
    offset = toml.number(ctx, t.get("offset", 0.0), f"{where}.offset")
    if offset < 0:
        raise ctx.err(f"{where}.offset", f"must be >= 0, got {toml.fmt(offset)}")
    if period is not None and not offset < period:
        raise ctx.err(
            f"{where}.offset",
            f"must be < period ({toml.fmt(period)} s), got {toml.fmt(offset)}",
        )
    dropout = toml.number(ctx, t.get("dropout", 0.0), f"{where}.dropout")
    if not 0.0 <= dropout < 1.0:
        raise ctx.err(f"{where}.dropout", f"must be in [0, 1), got {toml.fmt(dropout)}")
    return SensorTiming(period, offset, dropout)


def check_schedule(ctx: Ctx, system: System, steps: int, steps_key: str) -> None:
    """The sensors' timing on a horizon of `steps` dt: every sensor measures at least once,
    irregular instants have a model that can be discretised for any interval, and the
    instants fit a log's uint32 step index."""
    sched = system.schedule(steps)
    horizon = toml.fmt(steps * system.dt)
    for j, sen in enumerate(system.sensors):
        if not sched.measures[:, j].any():
            raise ctx.err(
                f"sensors[{j}].offset",
                f"sensor {sen.name!r} never measures within [0, {horizon}] s "
                f"(offset {toml.fmt(sen.timing.offset)} s, {steps_key} = {steps})",
            )
    if not sched.regular and system.continuous is None:
        raise ctx.err(
            "model.F",
            "explicit F, Q hold for dt only, but the sensors' periods and offsets are not "
            "multiples of dt (irregular instants): give kind = 'constant-velocity' (n0, axes) "
            "or kind = 'continuous' (A, Qc)",
        )
    if len(sched.times) > MAX_INDEX:
        raise ctx.err(steps_key, f"{len(sched.times)} instants exceed a uint32 step index")


def _sensors(ctx: Ctx, doc: dict[str, Any], n: int) -> tuple[Sensor, ...]:
    sensors: list[Sensor] = []
    tables = toml.named_tables(ctx, doc, "sensors", _SENSOR_KEYS, " (name, H, R)", _TIMING_KEYS)
    for where, t, name in tables:
        H = toml.matrix(ctx, t["H"], f"{where}.H", scalar=n == 1, row=True)
        if H.shape[1] != n:
            raise ctx.err(f"{where}.H", f"shape {toml.shape(H)}, expected {H.shape[0]}x{n} (m x n)")
        m = H.shape[0]
        R = toml.matrix(ctx, t["R"], f"{where}.R", scalar=m == 1)
        if R.shape != (m, m):
            raise ctx.err(
                f"{where}.R",
                f"shape {toml.shape(R)}, expected {m}x{m} (H has {m} row{'s' * (m > 1)})",
            )
        R = toml.covariance_checks(ctx, R, f"{where}.R", strict=True)
        sensors.append(Sensor(name, toml.readonly(H), R, _timing(ctx, t, where)))
    return tuple(sensors)


def _correlations(
    ctx: Ctx, doc: dict[str, Any], sensors: tuple[Sensor, ...]
) -> dict[tuple[int, int], np.ndarray]:
    items = doc.get("correlations", [])
    if isinstance(items, dict):
        raise ctx.err(
            "correlations", "expected an array of tables ([[correlations]]), got one table"
        )
    if not isinstance(items, list) or not all(isinstance(t, dict) for t in items):
        raise ctx.err(
            "correlations",
            f"expected an array of tables ([[correlations]]), got {toml.tname(items)}",
        )
    names = [s.name for s in sensors]
    cross: dict[tuple[int, int], np.ndarray] = {}
    first: dict[tuple[int, int], int] = {}
    for k, t in enumerate(items):
        where = f"correlations[{k}]"
        toml.check_keys(ctx, t, where, _CORRELATION_KEYS, required=_CORRELATION_KEYS)
        pair = t["sensors"]
        if (
            not isinstance(pair, list)
            or len(pair) != 2
            or not all(isinstance(p, str) for p in pair)
        ):
            raise ctx.err(
                f"{where}.sensors",
                f'expected two sensor names, e.g. ["a", "b"], got {toml.show(pair)}',
            )
        a, b = pair
        for p in (a, b):
            if p not in names:
                raise ctx.err(
                    f"{where}.sensors", f"unknown sensor {p!r} (sensors: {', '.join(names)})"
                )
        if a == b:
            raise ctx.err(
                f"{where}.sensors",
                f"a sensor cannot be correlated with itself ({a!r}); its noise covariance is "
                f"sensors[{names.index(a)}].R",
            )
        i, j = names.index(a), names.index(b)
        key = (min(i, j), max(i, j))
        if key in first:
            raise ctx.err(
                f"{where}.sensors",
                f"pair ({a!r}, {b!r}) already correlated in correlations[{first[key]}]",
            )
        ma, mb = sensors[i].dim, sensors[j].dim
        C = toml.matrix(ctx, t["cov"], f"{where}.cov", scalar=True, row=ma == 1)
        if C.shape != (ma, mb):
            raise ctx.err(
                f"{where}.cov",
                f"shape {toml.shape(C)}, expected {ma}x{mb} (rows: {a!r} has {ma}, "
                f"columns: {b!r} has {mb})",
            )
        if i > j:
            C = C.T
        Ra, Rb = sensors[key[0]].R, sensors[key[1]].R
        joint = np.block([[Ra, C], [C.T, Rb]])
        lo = toml.min_eig_excess(joint, strict=True)
        if lo is not None:
            raise ctx.err(
                f"{where}.cov",
                f"makes the joint noise covariance of {a!r} and {b!r} not positive definite "
                f"(smallest eigenvalue {toml.fmt(lo)})",
            )
        first[key] = k
        cross[key] = toml.readonly(np.array(C))
    if len(cross) > 1:
        # Pairs are checked above; several correlations can still conflict with each other.
        probe = System(F=np.zeros((1, 1)), Q=np.zeros((1, 1)), sensors=sensors, cross_R=cross)
        lo = toml.min_eig_excess(probe.R, strict=True)
        if lo is not None:
            raise ctx.err(
                "correlations",
                "the full measurement noise covariance R of all sensors (eq. 31) is not "
                f"positive definite (smallest eigenvalue {toml.fmt(lo)})",
            )
    return cross


def _architectures(ctx: Ctx, doc: dict[str, Any], system: System) -> tuple[str, ...]:
    names = tuple(s.name for s in system.sensors)
    return toml.architectures(ctx, doc, STATE_ARCHITECTURES, lambda a: parse_arch(a, names))


def _evaluate(ctx: Ctx, doc: dict[str, Any]) -> tuple[float, int, bool]:
    ev = toml.table(ctx, doc, "evaluate", required=False) or {}
    toml.check_keys(ctx, ev, "evaluate", _EVALUATE_KEYS)
    confidence = DEFAULT_CONFIDENCE
    if "confidence" in ev:
        confidence = toml.number(ctx, ev["confidence"], "evaluate.confidence")
        if not 0.0 < confidence < 1.0:
            raise ctx.err("evaluate.confidence", f"must be in (0, 1), got {toml.fmt(confidence)}")
    sample_runs = DEFAULT_SAMPLE_RUNS
    if "sample_runs" in ev:
        sample_runs = toml.integer(ctx, ev["sample_runs"], "evaluate.sample_runs", minimum=0)
    plane_view = ev.get("plane_view", False)
    if not isinstance(plane_view, bool):
        raise ctx.err(
            "evaluate.plane_view", f"expected true or false, got {toml.tname(plane_view)}"
        )
    return confidence, sample_runs, plane_view
