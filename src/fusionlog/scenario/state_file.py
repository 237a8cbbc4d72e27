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
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from fusionlog.core.late_policy import system_refusal
from fusionlog.core.model import Prior, System
from fusionlog.core.models import SensorModel
from fusionlog.core.names import STATE_ARCHITECTURES, known_arch, parse_arch_of
from fusionlog.core.timing import Schedule, SensorTiming, instant_counts

from . import estimate_keys, toml, trajectory
from . import nonlinear_syntax as nonlinear
from . import sensors as sensor_tables
from .latency import LATE_POLICIES, late_section, latency_dict
from .model_section import (
    MODEL_KINDS,
    check_schedule,
    model_section,
)
from .scenario_base import DEFAULT_CONFIDENCE, DEFAULT_SAMPLE_RUNS, Scenario, header
from .toml import Ctx

__all__ = [
    "NonlinearScenario",
    "StateScenario",
    "architectures_section",
    "correlations_section",
    "evaluate_section",
    "prior_section",
    "MODEL_KINDS",
    "model_from_doc",
    "state_from_doc",
    "system_from_dict",
    "system_to_dict",
]


@dataclass(frozen=True, eq=False)
class StateScenario(Scenario):
    """A state scenario: a linear Gaussian system (`core.model.System`) and the fusion
    architectures of the Ajgl-Simandl-Dunik paper; its sensors' timing decides the instants."""

    kind = "state"
    system: System

    @cached_property
    def schedule(self) -> Schedule:
        """The instants of the horizon and which sensor measures when (`core.timing`): t_k =
        k dt unless the sensors' periods and offsets make them irregular."""
        return self.system.schedule(self.steps)

    @property
    def instants(self) -> int:
        """K + 1 on the regular grid (every sensor's period and offset whole dt), counted
        without the schedule: a replay's scenario keeps its own instants' times, so a schedule
        built only to count them would be held beside them, 8 bytes an instant (issue 34)."""
        if "schedule" not in self.__dict__:
            timings = tuple(s.timing for s in self.system.sensors)
            if instant_counts(self.system.dt, self.steps, timings) is None:
                return self.steps + 1
        return len(self.schedule.times)

    def check_horizon(self, ctx: Ctx, steps_key: str) -> None:
        """The sensors' timing on the new horizon: the instants' count and memory."""
        check_schedule(ctx, self.system, self.steps, steps_key, len(self.architectures))


@dataclass(frozen=True, eq=False)
class NonlinearScenario(StateScenario):
    """A state scenario with a nonlinear sensor or motion model (DESIGN.md, "Nonlinear sensors
    and motion"): EKF or UKF local filters, no exact analysis, the PCRB beside the Monte Carlo
    values."""


def state_scenario(h: Any, system: System, **fields: Any) -> StateScenario:
    """The state scenario of `system`: a NonlinearScenario when its model is nonlinear."""
    cls = StateScenario if system.linear else NonlinearScenario
    return cls.of(h, system, **fields)


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
_PRIOR_KEYS = ("mean", "cov")
_TRUTH_KEYS = ("initial_mean", "initial_cov")
_CORRELATION_KEYS = ("sensors", "cov")
_EVALUATE_KEYS = ("confidence", "sample_runs", "plane_view", "full_resolution", *trajectory.KEYS)


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
    if system.motion_model is not None:
        d["model"] = nonlinear.turn_dict(system.motion_model)
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
        sensor_tables.sensor_to_dict(s) | _timing_dict(s.timing) for s in system.sensors
    ]
    d["correlations"] = [
        {"sensors": [names[i], names[j]], "cov": toml.tolist(c)}
        for (i, j), c in sorted(system.cross_R.items())
    ]
    if system.filter is not None:
        d["estimate"] = nonlinear.estimate_dict(system)
    if system.ci_criterion != "trace":
        d.setdefault("estimate", {})["ci_criterion"] = system.ci_criterion
    if system.late != LATE_POLICIES[0]:
        d.setdefault("estimate", {})["late"] = system.late
    return d


def _timing_dict(t: SensorTiming) -> dict[str, float]:
    """The timing keys that differ from their defaults."""
    d = {"offset": t.offset, "dropout": t.dropout}
    d = {k: float(v) for k, v in d.items() if v != 0.0} | latency_dict(t.latency)
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


def state_from_doc(
    doc: dict[str, Any], file: str, source: str, path: str | None, *, recorded: bool = False
) -> StateScenario:
    """A state scenario from a parsed TOML document; `file` names it in errors, `source` is the
    text as written (recorded in the sensors file); `recorded`: that record (`Ctx`)."""
    ctx = Ctx(file, recorded)
    toml.check_keys(ctx, doc, "(top level)", _TOP_KEYS, what="section")
    sc = toml.table(ctx, doc, "scenario", required=True)
    toml.check_keys(ctx, sc, "scenario", _SCENARIO_KEYS)
    h = header(ctx, sc, model=False)

    system = _system(ctx, doc, sc, need_truth=True)
    architectures = architectures_section(ctx, doc, system)
    check_schedule(ctx, system, h.steps, "scenario.steps", len(architectures))
    confidence, sample_runs, plane_view = evaluate_section(ctx, doc)
    if plane_view and system.n != 2:
        raise ctx.err("evaluate.plane_view", f"needs a 2-D state, this one has {system.n}")
    return state_scenario(
        h,
        system,
        dt=system.dt,
        state_names=system.state_names,
        architectures=architectures,
        confidence=confidence,
        sample_runs=sample_runs,
        plane_view=plane_view,
        full_resolution=full_resolution_of(ctx, doc),
        source=source,
        path=path,
        trajectory=trajectory.trajectory_section(ctx, doc, system.state_names),
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
    architectures_section(ctx, doc, system)
    evaluate_section(ctx, doc)
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

    md = doc.get("model")
    motion = None
    if isinstance(md, dict) and md.get("kind") == "coordinated-turn":
        motion, state_names, dt = nonlinear.turn_section(ctx, md, state_names, dt)
        # F, Q: its linearisation at the zero state (constant velocity) and Q over dt; the
        # filters and the simulation ask the motion model itself
        F, Q = motion.jacobian(np.zeros(motion.n), dt).copy(), motion.Q(dt)
        G, continuous = None, None
    else:
        F, Q, G, state_names, dt, continuous = model_section(ctx, doc, state_names, dt)
    n = F.shape[0]

    prior = prior_section(ctx, doc, F)

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

    sensors = _sensors(ctx, doc, n, tuple(state_names), dt)
    cross_R = correlations_section(ctx, doc, sensors)
    linear = motion is None and all(s.linear for s in sensors)
    filt, ukf = nonlinear.filter_section(ctx, doc, n, linear)
    criterion = estimate_keys.ci_criterion(ctx, doc)

    system = System(
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
        motion_model=motion,
        filter=filt,
        ukf=ukf,
        ci_criterion=criterion,
        late=late_section(ctx, doc),
    )
    nonlinear.check_nonlinear(ctx, system, bool(cross_R))
    if (why := system_refusal(system)) is not None:
        raise ctx.err(*why)
    check_determined(ctx, system)
    return system


def check_determined(ctx: Ctx, system: System) -> None:
    """Without a prior every state must be determined by the sensors through the model (a
    replay with a state nothing measures gave every metric NaN, exit 0, and no word why)."""
    if system.prior is None and system.linear and (lost := system.undetermined_states()):
        names = ", ".join(system.state_names[i] for i in lost)
        raise ctx.err(
            "prior",
            f"missing, and no sensor ever determines {names} through the model (unobservable): "
            "without a prior no filter would ever have a covariance and every metric would be "
            "NaN; give [prior] (mean, cov) or a sensor that measures them",
        )


def prior_section(ctx: Ctx, doc: dict[str, Any], F: np.ndarray) -> Prior | None:
    """[prior] mean, cov; None ("no prior information": F must then be invertible)."""
    n = F.shape[0]
    pr = toml.table(ctx, doc, "prior", required=False)
    if pr is not None:
        toml.check_keys(ctx, pr, "prior", _PRIOR_KEYS, required=_PRIOR_KEYS)
        return Prior(
            toml.vector(ctx, pr["mean"], "prior.mean", n),
            # Positive definite: a filter's covariance must be invertible (information form,
            # Millman's formula); a perfectly known component belongs in [truth], not here.
            toml.covariance(ctx, pr["cov"], "prior.cov", n, strict=True),
        )
    if abs(np.linalg.det(F)) <= 1e-12 * max(1.0, float(np.abs(F).max()) ** n):
        raise ctx.err(
            "model.F",
            "must be invertible when there is no [prior]: the filters start in information "
            "form and predict through F^-1",
        )
    return None


def _sensors(
    ctx: Ctx, doc: dict[str, Any], n: int, states: tuple[str, ...], dt: float
) -> tuple[SensorModel, ...]:
    """The sensor models of the [[sensors]] tables, each parsed by its kind's syntax."""
    allowed = sensor_tables.allowed_keys()
    tables = toml.named_tables(ctx, doc, "sensors", ("name",), " (name, H, R)", allowed[1:])
    return tuple(
        sensor_tables.sensor_from_table(ctx, t, where, nm, n, states, dt) for where, t, nm in tables
    )


def correlations_section(
    ctx: Ctx, doc: dict[str, Any], sensors: tuple[SensorModel, ...]
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
        why = None if ctx.recorded else toml.not_definite(joint, strict=True)
        if why is not None:
            raise ctx.err(
                f"{where}.cov",
                f"makes the joint noise covariance of {a!r} and {b!r} not positive definite {why}",
            )
        first[key] = k
        cross[key] = toml.readonly(np.array(C))
    if len(cross) > 1 and not ctx.recorded:
        # Pairs are checked above; several correlations can still conflict with each other.
        probe = System(F=np.zeros((1, 1)), Q=np.zeros((1, 1)), sensors=sensors, cross_R=cross)
        why = toml.not_definite(probe.R, strict=True)
        if why is not None:
            raise ctx.err(
                "correlations",
                "the full measurement noise covariance R of all sensors (eq. 31) is not "
                f"positive definite {why}",
            )
    return cross


def architectures_section(ctx: Ctx, doc: dict[str, Any], system: System) -> tuple[str, ...]:
    def check(a: str) -> tuple[str, str | None]:
        return parse_arch_of(a, system)

    # late sensors: by default the architectures that take them
    default = tuple(a for a in STATE_ARCHITECTURES if known_arch(a, system))
    return toml.architectures(ctx, doc, default, check, ("filter", "ukf", "ci_criterion", "late"))


def evaluate_section(ctx: Ctx, doc: dict[str, Any]) -> tuple[float, int, bool]:
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


def full_resolution_of(ctx: Ctx, doc: dict[str, Any]) -> bool:
    """``[evaluate] full_resolution``: the recording's series at every instant of a long log
    (default false: a few 10^4 points per series, `core.decimate`)."""
    value = (toml.table(ctx, doc, "evaluate", required=False) or {}).get("full_resolution", False)
    if not isinstance(value, bool):
        raise ctx.err(
            "evaluate.full_resolution", f"expected true or false, got {toml.tname(value)}"
        )
    return value
