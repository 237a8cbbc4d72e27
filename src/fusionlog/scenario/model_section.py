"""The [model] section of a state scenario (and of a replay or model file), and the sensors'
timing keys: which discrete model a scenario has, and whether it can be discretised for any
interval (irregular instants, `core.timing`).

    [model]   kind = "constant-velocity" with n0 (N0 = n0 * dt, eqs. 41-42) and optionally
              axes (N independent axes, state per axis [p, v]);
              kind = "continuous" with A, Qc (F = expm(A dt), Q by Van Loan's method);
              or explicit F, Q and optionally G (default identity), for dt only.
    [[sensors]] period, offset (s), dropout (probability), latency (s, `.latency`): see
    `core.timing`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fusionlog.core.model import System, constant_velocity
from fusionlog.core.timing import (
    MAX_PERIOD_S,
    MIN_PERIOD_S,
    SensorTiming,
    constant_velocity_continuous,
    instant_counts,
    van_loan,
)

from . import toml
from .scenario_base import MAX_INDEX, memory_shortfall
from .toml import Ctx

__all__ = [
    "MODEL_KEYS",
    "MODEL_KINDS",
    "TIMING_KEYS",
    "Model",
    "bytes_per_instant",
    "check_schedule",
    "model_section",
    "sensor_timing",
]

#: Values of [model].kind.
MODEL_KINDS: tuple[str, ...] = ("constant-velocity", "continuous")
MODEL_KEYS = ("kind", "n0", "axes", "A", "Qc", "F", "Q", "G")
TIMING_KEYS = ("period", "offset", "dropout", "latency")

#: F, Q, G, state names, dt, and the continuous model (A, Qc) or None.
Model = tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple[str, ...], float, Any]


def model_section(
    ctx: Ctx, doc: dict[str, Any], state_names: tuple[str, ...] | None, dt: float | None
) -> Model:
    """The [model] section: F, Q (at dt), G, the state names, dt and the continuous model."""
    md = toml.table(ctx, doc, "model", required=True)
    toml.check_keys(ctx, md, "model", MODEL_KEYS)
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
    F, state_names = _square(ctx, md, "F", state_names)
    n = F.shape[0]
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
    A, state_names = _square(ctx, md, "A", state_names)
    n = A.shape[0]
    Qc = toml.covariance(ctx, md["Qc"], "model.Qc", n, strict=False)
    with np.errstate(all="ignore"):
        F, Q = van_loan(A, Qc, dt)
    if not (np.isfinite(F).all() and np.isfinite(Q).all()):
        raise ctx.err("model.A", f"expm(A dt) overflows for dt = {toml.fmt(dt)}")
    A = toml.readonly(np.array(A))
    return toml.readonly(F), toml.readonly(Q), None, state_names, dt, (A, Qc)


def _square(
    ctx: Ctx, md: dict[str, Any], key: str, state_names: tuple[str, ...] | None
) -> tuple[np.ndarray, tuple[str, ...]]:
    """[model].<key> (F or A): a square matrix, and the state names it has room for
    (x1, x2, ... when the scenario names none)."""
    M = toml.matrix(ctx, md[key], f"model.{key}", scalar=True)
    if M.shape[0] != M.shape[1]:
        raise ctx.err(f"model.{key}", f"must be square, got {toml.shape(M)}")
    n = M.shape[0]
    if state_names is None:
        return M, tuple(f"x{i + 1}" for i in range(n))
    if len(state_names) != n:
        raise ctx.err(
            f"model.{key}",
            f"shape {toml.shape(M)} does not match the {len(state_names)} "
            f"scenario.state_names (expected {len(state_names)}x{len(state_names)})",
        )
    return M, state_names


def sensor_timing(ctx: Ctx, t: dict[str, Any], where: str, dt: float) -> SensorTiming:
    """A sensor's period, offset (s) and dropout probability; the horizon is checked later,
    when the instants are known (`check_schedule`). Periods and offsets other than 0 lie in
    [1 ns, 10^9 s] (`core.timing`); without a period the period is dt, so 0 <= offset < dt."""
    period = None
    if "period" in t:
        period = toml.number(ctx, t["period"], f"{where}.period")
        _in_range(ctx, period, f"{where}.period")
    offset = toml.number(ctx, t.get("offset", 0.0), f"{where}.offset")
    if offset != 0:
        _in_range(ctx, offset, f"{where}.offset")
    if not offset < (dt if period is None else period):
        what = (
            f"period ({toml.fmt(period)} s)"
            if period is not None
            else (f"the period, which is dt = {toml.fmt(dt)} s without a period key")
        )
        raise ctx.err(f"{where}.offset", f"must be < {what}, got {toml.fmt(offset)}")
    dropout = toml.number(ctx, t.get("dropout", 0.0), f"{where}.dropout")
    if not 0.0 <= dropout < 1.0:
        raise ctx.err(f"{where}.dropout", f"must be in [0, 1), got {toml.fmt(dropout)}")
    from .latency import sensor_latency

    return SensorTiming(period, offset, dropout, sensor_latency(ctx, t, where))


def _in_range(ctx: Ctx, value: float, key: str) -> None:
    if key.endswith(".period") and not value > 0:
        raise ctx.err(key, f"must be > 0, got {toml.fmt(value)}")
    if value < 0:
        raise ctx.err(key, f"must be >= 0, got {toml.fmt(value)}")
    if not MIN_PERIOD_S <= value <= MAX_PERIOD_S:
        raise ctx.err(
            key,
            f"{toml.fmt(value)} s is outside [1e-09, 1e+09] s (one nanosecond, the resolution "
            "of a log's time, to about 31.7 years)",
        )


def bytes_per_instant(system: System, architectures: int) -> int:
    """Memory one run holds per instant (truth and measurements in float64, and the plans'
    per-step maps of the estimate stage): the budget of `scenario_base.memory_shortfall`."""
    s = system
    return 8 * (s.n + s.m) * 4 + 8 * s.n * (s.n + s.m) * architectures


def check_schedule(
    ctx: Ctx, system: System, steps: int, steps_key: str, architectures: int = 1
) -> None:
    """The sensors' timing on a horizon of `steps` dt: the instants fit in memory and a log's
    uint32 step index (counted before anything is built), every sensor measures at least
    once, and irregular instants have a model that can be discretised for any interval."""
    if ctx.recorded:  # a record's schedule was checked when it ran (`Ctx`)
        return
    timings = tuple(s.timing for s in system.sensors)
    counts = instant_counts(system.dt, steps, timings)
    horizon = toml.fmt(steps * system.dt)
    if counts is None:
        key, instants, what = steps_key, steps + 1, f"{steps + 1} instants need"
    else:
        j = max(range(len(counts)), key=counts.__getitem__)
        period = timings[j].period if timings[j].period is not None else system.dt
        key = f"sensors[{j}].period"
        instants = 1 + sum(counts)
        what = (
            f"up to {instants} instants (sensor {system.sensors[j].name!r} measures every "
            f"{toml.fmt(period)} s over {horizon} s)"
        )
        if counts[j] > MAX_INDEX:
            raise ctx.err(key, f"{what}: more than a uint32 step index holds")
        what += " need"
    # the schedule's own arrays (times, the sensors' sampling times, which sensor measures)
    per_instant = bytes_per_instant(system, architectures) + 24 + len(timings)
    why = memory_shortfall(instants, per_instant)
    if why is not None:
        raise ctx.err(key, f"{what} {why}")
    sched = system.schedule(steps)
    for j, sen in enumerate(system.sensors):
        if not sched.measures[:, j].any():
            raise ctx.err(
                f"sensors[{j}].offset",
                f"sensor {sen.name!r} never measures within [0, {horizon}] s "
                f"(offset {toml.fmt(sen.timing.offset)} s, {steps_key} = {steps})",
            )
    if not sched.regular and system.continuous is None and system.motion_model is None:
        raise ctx.err(
            "model.F",
            "explicit F, Q hold for dt only, but the sensors' periods and offsets are not "
            "multiples of dt (irregular instants): give kind = 'constant-velocity' (n0, axes) "
            "or kind = 'continuous' (A, Qc)",
        )
    if len(sched.times) > MAX_INDEX:
        raise ctx.err(steps_key, f"{len(sched.times)} instants exceed a uint32 step index")
