"""Scenario and model definitions (pipeline/*.toml): parsing and validation.

A scenario file has the sections (DESIGN.md, "Scenario TOML")::

    [scenario]       name, description, steps (K: instants k = 0..K), runs (M), seed, dt,
                     state_names
    [model]          kind = "constant-velocity" with n0 (N0 = n0 * dt, eqs. 41-42),
                     or explicit F, Q and optionally G (default identity)
    [prior]          mean, cov of p(x_0 | z_-1); omit it for "no prior information"
    [truth]          initial_mean, initial_cov: where the true x_0 is drawn from
                     (optional; each defaults to the prior's)
    [[sensors]]      name, H, R (a scalar R for a one-row H; a one-row H may be a flat list)
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
import difflib
import math
import os
import re
import tomllib
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from fusionlog.core.model import Prior, Sensor, System, constant_velocity
from fusionlog.core.names import STATE_ARCHITECTURES, parse_arch
from fusionlog.errors import ValidationError

__all__ = [
    "Scenario",
    "load_scenario",
    "scenario_from_text",
    "load_model",
    "model_from_text",
    "system_to_dict",
    "system_from_dict",
    "scenario_with",
    "MODEL_KINDS",
]

#: Values of [model].kind.
MODEL_KINDS: tuple[str, ...] = ("constant-velocity",)

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
_SCENARIO_REQUIRED = ("name", "steps", "runs", "seed", "dt")
_MODEL_KEYS = ("kind", "n0", "F", "Q", "G")
_PRIOR_KEYS = ("mean", "cov")
_TRUTH_KEYS = ("initial_mean", "initial_cov")
_SENSOR_KEYS = ("name", "H", "R")
_CORRELATION_KEYS = ("sensors", "cov")
_ESTIMATE_KEYS = ("architectures",)
_EVALUATE_KEYS = ("confidence", "sample_runs", "plane_view")

#: Names that end up in MCAP topics, Rerun entity paths and folder names.
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")
_NAME_RULE = "letters, digits, '_', '.', '-', not starting with '.' or '-'"

#: Relative tolerance of the symmetry check: max|A - A^T| <= _SYM_RTOL * max|A|.
_SYM_RTOL = 1e-12
#: Eigenvalues within _DEF_RTOL * n * max|eig| of zero count as zero in definiteness checks.
_DEF_RTOL = 1e-12

_DEFAULT_CONFIDENCE = 0.95
_DEFAULT_SAMPLE_RUNS = 3


@dataclass(frozen=True, eq=False)
class Scenario:
    """A validated scenario: the system, the Monte Carlo budget and the pipeline defaults."""

    name: str
    description: str
    steps: int  # K: instants k = 0..K
    runs: int  # M
    seed: int
    dt: float
    state_names: tuple[str, ...]
    system: System
    architectures: tuple[str, ...]
    confidence: float = _DEFAULT_CONFIDENCE
    sample_runs: int = _DEFAULT_SAMPLE_RUNS
    plane_view: bool = False  # a 2-D view of the state plane (n = 2): estimates and ellipses
    source: str = ""  # the TOML text as loaded (overrides are not written back into it)
    path: str | None = None

    @property
    def times(self) -> np.ndarray:
        """t_k = k dt for k = 0..K."""
        return np.arange(self.steps + 1) * self.dt


# --------------------------------------------------------------------------------------------
# Public API


def load_scenario(
    path: str | os.PathLike[str],
    *,
    runs: int | None = None,
    steps: int | None = None,
    seed: int | None = None,
) -> Scenario:
    """Read and validate a scenario file; `runs`, `steps`, `seed` override it (CLI options)."""
    file = os.fspath(path)
    text = _read_text(file)
    scenario = _scenario_from_doc(_parse_toml(text, file), file, text, file)
    return scenario_with(scenario, runs=runs, steps=steps, seed=seed)


def scenario_from_text(text: str, source: str = "<string>") -> Scenario:
    """Validate a scenario given as TOML text; `source` names it in error messages."""
    return _scenario_from_doc(_parse_toml(text, source), source, text, None)


def load_model(path: str | os.PathLike[str]) -> System:
    """Read a model file (a scenario file without the need for [scenario]) into a System."""
    file = os.fspath(path)
    return model_from_text(_read_text(file), file)


def model_from_text(text: str, source: str = "<string>") -> System:
    """Validate a model given as TOML text."""
    return _model_from_doc(_parse_toml(text, source), source)


_S = TypeVar("_S")


def scenario_with(
    scenario: _S,
    *,
    runs: int | None = None,
    steps: int | None = None,
    seed: int | None = None,
) -> _S:
    """A copy with the given Monte Carlo settings replaced (None keeps the scenario's value);
    any scenario dataclass with `path`, `runs`, `steps` and `seed` (state or identity)."""
    path = scenario.path  # type: ignore[attr-defined]
    ctx = _Ctx(path if path is not None else "<scenario>")
    changes: dict[str, int] = {}
    if runs is not None:
        changes["runs"] = _check_int(ctx, runs, "--runs", minimum=1)
    if steps is not None:
        changes["steps"] = _check_int(ctx, steps, "--steps", minimum=0)
    if seed is not None:
        changes["seed"] = _check_int(ctx, seed, "--seed", minimum=0)
    return dataclasses.replace(scenario, **changes) if changes else scenario  # type: ignore


def system_to_dict(system: System) -> dict[str, Any]:
    """The resolved system as JSON-able plain data (for MCAP metadata).

    The layout is that of a model file with explicit matrices, so the dict can be written out
    as TOML and loaded with `load_model`; `system_from_dict` is its inverse.
    """
    names = [s.name for s in system.sensors]
    d: dict[str, Any] = {
        "scenario": {"dt": float(system.dt), "state_names": list(system.state_names)},
        "model": {"F": _tolist(system.F), "Q": _tolist(system.Q)},
    }
    if system.G is not None:
        d["model"]["G"] = _tolist(system.G)
    if system.prior is not None:
        d["prior"] = {"mean": _tolist(system.prior.mean), "cov": _tolist(system.prior.cov)}
    if system.initial is not None:
        d["truth"] = {
            "initial_mean": _tolist(system.initial.mean),
            "initial_cov": _tolist(system.initial.cov),
        }
    d["sensors"] = [{"name": s.name, "H": _tolist(s.H), "R": _tolist(s.R)} for s in system.sensors]
    d["correlations"] = [
        {"sensors": [names[i], names[j]], "cov": _tolist(c)}
        for (i, j), c in sorted(system.cross_R.items())
    ]
    return d


def system_from_dict(d: dict[str, Any], source: str = "<system dict>") -> System:
    """Rebuild (and re-validate) a System from `system_to_dict` output."""
    if not isinstance(d, dict):
        raise _Ctx(source).err("(top level)", f"expected a table, got {_tname(d)}")
    return _model_from_doc(d, source)


# --------------------------------------------------------------------------------------------
# Reading


class _Ctx:
    """Where errors are reported: the file (or source) name."""

    def __init__(self, file: str) -> None:
        self.file = file

    def err(self, where: str, reason: str) -> ValidationError:
        msg = f"{self.file}: {where}: {reason}"
        return ValidationError(" ".join(msg.split("\n")).replace("\r", " "))


def _read_text(file: str) -> str:
    try:
        with open(file, "rb") as fh:
            data = fh.read()
    except OSError as e:
        raise ValidationError(f"{file}: cannot read: {e.strerror or e}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValidationError(f"{file}: byte {e.start}: not UTF-8 text") from None


_TOML_POS = re.compile(r"\s*\(at (line \d+, column \d+|end of document)\)\s*$")


def _parse_toml(text: str, file: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        msg = str(e)
        m = _TOML_POS.search(msg)
        where = m.group(1) if m else "TOML"
        reason = msg[: m.start()] if m else msg
        raise _Ctx(file).err(where, f"invalid TOML: {reason}") from None


# --------------------------------------------------------------------------------------------
# Documents


def _scenario_from_doc(doc: dict[str, Any], file: str, source: str, path: str | None) -> Scenario:
    ctx = _Ctx(file)
    _check_keys(ctx, doc, "(top level)", _TOP_KEYS, what="section")
    sc = _table(ctx, doc, "scenario", required=True)
    _check_keys(ctx, sc, "scenario", _SCENARIO_KEYS, required=_SCENARIO_REQUIRED)

    name = _name(ctx, sc["name"], "scenario.name")
    description = _str(ctx, sc.get("description", ""), "scenario.description")
    steps = _check_int(ctx, sc["steps"], "scenario.steps", minimum=0)
    runs = _check_int(ctx, sc["runs"], "scenario.runs", minimum=1)
    seed = _check_int(ctx, sc["seed"], "scenario.seed", minimum=0)

    system = _system(ctx, doc, sc, need_truth=True)
    architectures = _architectures(ctx, doc, system)
    confidence, sample_runs, plane_view = _evaluate(ctx, doc)
    if plane_view and system.n != 2:
        raise ctx.err("evaluate.plane_view", f"needs a 2-D state, this one has {system.n}")
    return Scenario(
        name=name,
        description=description,
        steps=steps,
        runs=runs,
        seed=seed,
        dt=system.dt,
        state_names=system.state_names,
        system=system,
        architectures=architectures,
        confidence=confidence,
        sample_runs=sample_runs,
        plane_view=plane_view,
        source=source,
        path=path,
    )


def _model_from_doc(doc: dict[str, Any], file: str) -> System:
    ctx = _Ctx(file)
    _check_keys(ctx, doc, "(top level)", _TOP_KEYS, what="section")
    sc = _table(ctx, doc, "scenario", required=False) or {}
    _check_keys(ctx, sc, "scenario", _SCENARIO_KEYS)
    # A full scenario file is a valid model file: check what it says, use only the system.
    if "name" in sc:
        _name(ctx, sc["name"], "scenario.name")
    if "description" in sc:
        _str(ctx, sc["description"], "scenario.description")
    for key, minimum in (("steps", 0), ("runs", 1), ("seed", 0)):
        if key in sc:
            _check_int(ctx, sc[key], f"scenario.{key}", minimum=minimum)
    system = _system(ctx, doc, sc, need_truth=False)
    _architectures(ctx, doc, system)
    _evaluate(ctx, doc)
    return system


def _system(ctx: _Ctx, doc: dict[str, Any], sc: dict[str, Any], *, need_truth: bool) -> System:
    state_names = None
    if "state_names" in sc:
        state_names = _names_list(ctx, sc["state_names"], "scenario.state_names")
    dt = None
    if "dt" in sc:
        dt = _float(ctx, sc["dt"], "scenario.dt")
        if not dt > 0:
            raise ctx.err("scenario.dt", f"must be > 0, got {_fmt(dt)}")

    F, Q, G, state_names, dt = _model(ctx, doc, state_names, dt)
    n = F.shape[0]

    prior = None
    pr = _table(ctx, doc, "prior", required=False)
    if pr is not None:
        _check_keys(ctx, pr, "prior", _PRIOR_KEYS, required=_PRIOR_KEYS)
        prior = Prior(
            _vector(ctx, pr["mean"], "prior.mean", n),
            # Positive definite: a filter's covariance must be invertible (information form,
            # Millman's formula); a perfectly known component belongs in [truth], not here.
            _covariance(ctx, pr["cov"], "prior.cov", n, strict=True),
        )
    elif abs(np.linalg.det(F)) <= 1e-12 * max(1.0, float(np.abs(F).max()) ** n):
        raise ctx.err(
            "model.F",
            "must be invertible when there is no [prior]: the filters start in information "
            "form and predict through F^-1",
        )

    initial = None
    tr = _table(ctx, doc, "truth", required=False)
    if tr is not None:
        _check_keys(ctx, tr, "truth", _TRUTH_KEYS)
        if prior is None:
            for key in _TRUTH_KEYS:
                if key not in tr:
                    raise ctx.err(
                        f"truth.{key}", "missing required key (there is no [prior] to default to)"
                    )
        mean = (
            _vector(ctx, tr["initial_mean"], "truth.initial_mean", n)
            if "initial_mean" in tr
            else prior.mean
        )
        cov = (
            _covariance(ctx, tr["initial_cov"], "truth.initial_cov", n, strict=False)
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
    )


def _model(
    ctx: _Ctx, doc: dict[str, Any], state_names: tuple[str, ...] | None, dt: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple[str, ...], float]:
    md = _table(ctx, doc, "model", required=True)
    _check_keys(ctx, md, "model", _MODEL_KEYS)
    if "kind" in md:
        kind = _str(ctx, md["kind"], "model.kind")
        if kind not in MODEL_KINDS:
            raise ctx.err("model.kind", f"unknown kind {kind!r} (known: {', '.join(MODEL_KINDS)})")
        for key in ("F", "Q", "G"):
            if key in md:
                raise ctx.err(
                    f"model.{key}",
                    f"not allowed with kind = {kind!r} (give either kind and n0, or F, Q, G)",
                )
        if "n0" not in md:
            raise ctx.err("model.n0", f"missing required key (kind = {kind!r} needs it)")
        n0 = _float(ctx, md["n0"], "model.n0")
        if n0 < 0:
            raise ctx.err("model.n0", f"must be >= 0, got {_fmt(n0)}")
        if dt is None:
            raise ctx.err("scenario.dt", f"missing required key (kind = {kind!r} needs it)")
        if state_names is None:
            state_names = ("position", "velocity")
        elif len(state_names) != 2:
            raise ctx.err(
                "scenario.state_names",
                f"kind = {kind!r} has 2 states (position, velocity), got {len(state_names)} names",
            )
        F, Q = constant_velocity(dt, n0 * dt)
        return _ro(F), _ro(Q), None, state_names, dt

    if "n0" in md:
        raise ctx.err("model.n0", "only used with kind = 'constant-velocity'")
    for key in ("F", "Q"):
        if key not in md:
            raise ctx.err(
                f"model.{key}", "missing required key (give kind = 'constant-velocity' or F and Q)"
            )
    F = _matrix(ctx, md["F"], "model.F", scalar=True)
    if F.shape[0] != F.shape[1]:
        raise ctx.err("model.F", f"must be square, got {_shape(F)}")
    n = F.shape[0]
    if state_names is None:
        state_names = tuple(f"x{i + 1}" for i in range(n))
    elif len(state_names) != n:
        raise ctx.err(
            "model.F",
            f"shape {_shape(F)} does not match the {len(state_names)} "
            f"scenario.state_names (expected {len(state_names)}x{len(state_names)})",
        )
    G = None
    q = n
    if "G" in md:
        G = _matrix(ctx, md["G"], "model.G", scalar=True, row=n == 1)
        if G.shape[0] != n:
            raise ctx.err("model.G", f"shape {_shape(G)}, expected {n} rows (n, as F)")
        q = G.shape[1]
        G = _ro(G)
    Q = _matrix(ctx, md["Q"], "model.Q", scalar=True)
    if Q.shape != (q, q):
        why = f"q x q, q = {q} columns of G" if G is not None else "n x n, as F"
        raise ctx.err("model.Q", f"shape {_shape(Q)}, expected {q}x{q} ({why})")
    Q = _covariance_checks(ctx, Q, "model.Q", strict=False)
    return _ro(F), Q, G, state_names, 1.0 if dt is None else dt


def _sensors(ctx: _Ctx, doc: dict[str, Any], n: int) -> tuple[Sensor, ...]:
    if "sensors" not in doc:
        raise ctx.err("sensors", "missing: give at least one [[sensors]] table (name, H, R)")
    items = doc["sensors"]
    if isinstance(items, dict):
        raise ctx.err("sensors", "expected an array of tables ([[sensors]]), got one table")
    if not isinstance(items, list) or not all(isinstance(t, dict) for t in items):
        raise ctx.err("sensors", f"expected an array of tables ([[sensors]]), got {_tname(items)}")
    if not items:
        raise ctx.err("sensors", "empty: give at least one sensor")
    sensors: list[Sensor] = []
    seen: dict[str, int] = {}
    for j, t in enumerate(items):
        where = f"sensors[{j}]"
        _check_keys(ctx, t, where, _SENSOR_KEYS, required=_SENSOR_KEYS)
        name = _name(ctx, t["name"], f"{where}.name")
        if name in seen:
            raise ctx.err(
                f"{where}.name", f"duplicate sensor name {name!r} (also sensors[{seen[name]}])"
            )
        seen[name] = j
        H = _matrix(ctx, t["H"], f"{where}.H", scalar=n == 1, row=True)
        if H.shape[1] != n:
            raise ctx.err(f"{where}.H", f"shape {_shape(H)}, expected {H.shape[0]}x{n} (m x n)")
        m = H.shape[0]
        R = _matrix(ctx, t["R"], f"{where}.R", scalar=m == 1)
        if R.shape != (m, m):
            raise ctx.err(
                f"{where}.R", f"shape {_shape(R)}, expected {m}x{m} (H has {m} row{'s' * (m > 1)})"
            )
        R = _covariance_checks(ctx, R, f"{where}.R", strict=True)
        sensors.append(Sensor(name, _ro(H), R))
    return tuple(sensors)


def _correlations(
    ctx: _Ctx, doc: dict[str, Any], sensors: tuple[Sensor, ...]
) -> dict[tuple[int, int], np.ndarray]:
    items = doc.get("correlations", [])
    if isinstance(items, dict):
        raise ctx.err(
            "correlations", "expected an array of tables ([[correlations]]), got one table"
        )
    if not isinstance(items, list) or not all(isinstance(t, dict) for t in items):
        raise ctx.err(
            "correlations", f"expected an array of tables ([[correlations]]), got {_tname(items)}"
        )
    names = [s.name for s in sensors]
    cross: dict[tuple[int, int], np.ndarray] = {}
    first: dict[tuple[int, int], int] = {}
    for k, t in enumerate(items):
        where = f"correlations[{k}]"
        _check_keys(ctx, t, where, _CORRELATION_KEYS, required=_CORRELATION_KEYS)
        pair = t["sensors"]
        if (
            not isinstance(pair, list)
            or len(pair) != 2
            or not all(isinstance(p, str) for p in pair)
        ):
            raise ctx.err(
                f"{where}.sensors", f'expected two sensor names, e.g. ["a", "b"], got {_show(pair)}'
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
        C = _matrix(ctx, t["cov"], f"{where}.cov", scalar=True, row=ma == 1)
        if C.shape != (ma, mb):
            raise ctx.err(
                f"{where}.cov",
                f"shape {_shape(C)}, expected {ma}x{mb} (rows: {a!r} has {ma}, "
                f"columns: {b!r} has {mb})",
            )
        if i > j:
            C = C.T
        Ra, Rb = sensors[key[0]].R, sensors[key[1]].R
        joint = np.block([[Ra, C], [C.T, Rb]])
        lo = _min_eig_excess(joint, strict=True)
        if lo is not None:
            raise ctx.err(
                f"{where}.cov",
                f"makes the joint noise covariance of {a!r} and {b!r} not positive definite "
                f"(smallest eigenvalue {_fmt(lo)})",
            )
        first[key] = k
        cross[key] = _ro(np.array(C))
    if len(cross) > 1:
        # Pairs are checked above; several correlations can still conflict with each other.
        probe = System(F=np.zeros((1, 1)), Q=np.zeros((1, 1)), sensors=sensors, cross_R=cross)
        lo = _min_eig_excess(probe.R, strict=True)
        if lo is not None:
            raise ctx.err(
                "correlations",
                "the full measurement noise covariance R of all sensors (eq. 31) is not "
                f"positive definite (smallest eigenvalue {_fmt(lo)})",
            )
    return cross


def _architectures(ctx: _Ctx, doc: dict[str, Any], system: System) -> tuple[str, ...]:
    est = _table(ctx, doc, "estimate", required=False)
    if est is None:
        return STATE_ARCHITECTURES
    _check_keys(ctx, est, "estimate", _ESTIMATE_KEYS)
    if "architectures" not in est:
        return STATE_ARCHITECTURES
    archs = est["architectures"]
    if not isinstance(archs, list):
        raise ctx.err("estimate.architectures", f"expected a list of names, got {_tname(archs)}")
    if not archs:
        raise ctx.err("estimate.architectures", "empty: name at least one architecture")
    names = tuple(s.name for s in system.sensors)
    seen: set[str] = set()
    for i, a in enumerate(archs):
        where = f"estimate.architectures[{i}]"
        a = _str(ctx, a, where)
        try:
            parse_arch(a, names)
        except ValueError as e:
            raise ctx.err(where, str(e)) from None
        if a in seen:
            raise ctx.err(where, f"duplicate architecture {a!r}")
        seen.add(a)
    return tuple(archs)


def _evaluate(ctx: _Ctx, doc: dict[str, Any]) -> tuple[float, int, bool]:
    ev = _table(ctx, doc, "evaluate", required=False) or {}
    _check_keys(ctx, ev, "evaluate", _EVALUATE_KEYS)
    confidence = _DEFAULT_CONFIDENCE
    if "confidence" in ev:
        confidence = _float(ctx, ev["confidence"], "evaluate.confidence")
        if not 0.0 < confidence < 1.0:
            raise ctx.err("evaluate.confidence", f"must be in (0, 1), got {_fmt(confidence)}")
    sample_runs = _DEFAULT_SAMPLE_RUNS
    if "sample_runs" in ev:
        sample_runs = _check_int(ctx, ev["sample_runs"], "evaluate.sample_runs", minimum=0)
    plane_view = ev.get("plane_view", False)
    if not isinstance(plane_view, bool):
        raise ctx.err("evaluate.plane_view", f"expected true or false, got {_tname(plane_view)}")
    return confidence, sample_runs, plane_view


# --------------------------------------------------------------------------------------------
# Values


def _tname(v: Any) -> str:
    if isinstance(v, bool):
        return f"boolean {str(v).lower()}"
    if isinstance(v, int):
        return f"integer {v}"
    if isinstance(v, float):
        return f"float {_fmt(v)}"
    if isinstance(v, str):
        return f"string {_show(v)}"
    if isinstance(v, list):
        return "an array"
    if isinstance(v, dict):
        return "a table"
    return type(v).__name__


def _show(v: Any, limit: int = 60) -> str:
    s = repr(v)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _fmt(x: float) -> str:
    return f"{x:.6g}"


def _shape(A: np.ndarray) -> str:
    return "x".join(str(d) for d in A.shape)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _ro(A: np.ndarray) -> np.ndarray:
    A = np.array(A, dtype=float)
    A.flags.writeable = False
    return A


def _tolist(A: np.ndarray) -> list:
    return np.asarray(A, dtype=float).tolist()


def _check_keys(
    ctx: _Ctx,
    table: dict[str, Any],
    where: str,
    allowed: tuple[str, ...],
    *,
    required: tuple[str, ...] = (),
    what: str = "key",
) -> None:
    for key in table:
        if key not in allowed:
            hint = difflib.get_close_matches(key, allowed, n=1)
            mean = f"; did you mean {hint[0]!r}?" if hint else ""
            raise ctx.err(where, f"unknown {what} {key!r} (allowed: {', '.join(allowed)}){mean}")
    for key in required:
        if key not in table:
            at = key if where == "(top level)" else f"{where}.{key}"
            raise ctx.err(at, "missing required key")


def _table(ctx: _Ctx, doc: dict[str, Any], key: str, *, required: bool) -> dict[str, Any] | None:
    if key not in doc:
        if required:
            raise ctx.err(key, f"missing required section [{key}]")
        return None
    t = doc[key]
    if not isinstance(t, dict):
        raise ctx.err(key, f"expected a table ([{key}]), got {_tname(t)}")
    return t


def _str(ctx: _Ctx, v: Any, where: str) -> str:
    if not isinstance(v, str):
        raise ctx.err(where, f"expected a string, got {_tname(v)}")
    return v


def _name(ctx: _Ctx, v: Any, where: str) -> str:
    s = _str(ctx, v, where)
    if not _NAME_RE.match(s):
        raise ctx.err(where, f"invalid name {_show(s)} (use {_NAME_RULE})")
    return s


def _names_list(ctx: _Ctx, v: Any, where: str) -> tuple[str, ...]:
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a list of names, got {_tname(v)}")
    if not v:
        raise ctx.err(where, "empty: name every state")
    out = tuple(_name(ctx, s, f"{where}[{i}]") for i, s in enumerate(v))
    for i, s in enumerate(out):
        if s in out[:i]:
            raise ctx.err(f"{where}[{i}]", f"duplicate name {s!r}")
    return out


def _check_int(ctx: _Ctx, v: Any, where: str, *, minimum: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int | np.integer):
        integral = isinstance(v, float) and v.is_integer() and abs(v) < 2**63
        hint = f" (write {int(v)})" if integral else ""
        raise ctx.err(where, f"expected an integer, got {_tname(v)}{hint}")
    v = int(v)
    if v < minimum:
        raise ctx.err(where, f"must be >= {minimum}, got {v}")
    return v


def _float(ctx: _Ctx, v: Any, where: str) -> float:
    if not _is_number(v) and not isinstance(v, np.floating | np.integer):
        raise ctx.err(where, f"expected a number, got {_tname(v)}")
    x = float(v)
    if not math.isfinite(x):
        raise ctx.err(where, f"not finite ({x})")
    return x


def _matrix(
    ctx: _Ctx, v: Any, where: str, *, scalar: bool = False, row: bool = False
) -> np.ndarray:
    """A 2-D float matrix from a list of rows; a number is 1x1 if `scalar`, a flat list one row
    if `row`. Elements must be finite numbers."""
    example = "a list of rows, e.g. [[1.0, 0.0], [0.0, 1.0]]"
    if _is_number(v):
        if not scalar:
            raise ctx.err(where, f"expected a matrix ({example}), got a number")
        return np.array([[_float(ctx, v, where)]])
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a matrix ({example}), got {_tname(v)}")
    if not v:
        raise ctx.err(where, "empty matrix")
    if all(_is_number(x) for x in v):
        if not row:
            raise ctx.err(where, f"expected a matrix ({example}), got a flat list")
        return np.array([[_float(ctx, x, f"{where}[{j}]") for j, x in enumerate(v)]])
    rows: list[list[float]] = []
    for i, r in enumerate(v):
        if not isinstance(r, list):
            raise ctx.err(f"{where}[{i}]", f"expected a row (a list of numbers), got {_tname(r)}")
        if not r:
            raise ctx.err(f"{where}[{i}]", "empty row")
        if len(r) != len(v[0]):
            raise ctx.err(
                where, f"rows have different lengths (row 0 has {len(v[0])}, row {i} has {len(r)})"
            )
        rows.append([_float(ctx, x, f"{where}[{i}][{j}]") for j, x in enumerate(r)])
    return np.array(rows, dtype=float)


def _vector(ctx: _Ctx, v: Any, where: str, n: int) -> np.ndarray:
    if _is_number(v) and n == 1:
        return _ro(np.array([_float(ctx, v, where)]))
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a list of {n} numbers, got {_tname(v)}")
    x = np.array([_float(ctx, e, f"{where}[{i}]") for i, e in enumerate(v)])
    if x.shape != (n,):
        raise ctx.err(where, f"length {x.size}, expected {n} (the number of states)")
    return _ro(x)


def _covariance(ctx: _Ctx, v: Any, where: str, n: int, *, strict: bool) -> np.ndarray:
    A = _matrix(ctx, v, where, scalar=n == 1)
    if A.shape != (n, n):
        raise ctx.err(where, f"shape {_shape(A)}, expected {n}x{n} (n x n)")
    return _covariance_checks(ctx, A, where, strict=strict)


def _covariance_checks(ctx: _Ctx, A: np.ndarray, where: str, *, strict: bool) -> np.ndarray:
    """Symmetry (relative tolerance) and positive (semi)definiteness; returns the symmetrised,
    read-only matrix."""
    label = where.rsplit(".", 1)[-1]
    asym = float(np.max(np.abs(A - A.T)))
    if asym > _SYM_RTOL * float(np.max(np.abs(A))):
        raise ctx.err(where, f"not symmetric (max |{label} - {label}^T| = {asym:.3g})")
    A = 0.5 * (A + A.T)
    lo = _min_eig_excess(A, strict=strict)
    if lo is not None:
        kind = "positive definite" if strict else "positive semidefinite"
        raise ctx.err(where, f"not {kind} (smallest eigenvalue {_fmt(lo)})")
    return _ro(A)


def _min_eig_excess(A: np.ndarray, *, strict: bool) -> float | None:
    """The smallest eigenvalue if it violates definiteness, else None. Eigenvalues within
    _DEF_RTOL * n * max|eig| of zero count as zero."""
    w = np.linalg.eigvalsh(0.5 * (A + A.T))
    tol = _DEF_RTOL * A.shape[0] * float(np.max(np.abs(w)))
    lo = float(w[0])
    bad = lo <= tol if strict else lo < -tol
    return lo if bad else None
