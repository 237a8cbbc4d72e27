"""The identity kind's scenario files: parsing and validation.

Identity fusion (Challa & Koks, seed 004): which aircraft is it, from sensors that report a
class, a named set of classes or "unknown"? A file with an ``[identity]`` section (or
``[[identity_sensors]]``) is an identity scenario::

    [scenario]          name, description, steps (K: reports at k = 0..K), runs (M), seed, dt
    [identity]          classes = ["Learjet", "Falcon", "Caravan"]  (the frame of discernment)
                        prior = [0.5, 0.4, 0.1]  (optional, default uniform): the distribution
                            the true class of each run is drawn from AND the fusion node's
                            prior for BAYES (DS starts from the vacuous mass m(frame) = 1)
                        sets = { fast = ["Learjet", "Falcon"] }  (optional): named subsets a
                            sensor may report; "unknown" (the whole frame) is always there
    [[identity_sensors]] name; reports = ["fast", "Caravan", "unknown"] (each a class, a set or
                        "unknown"); confusion = one row per class, one column per report:
                        P(report | true class), each row summing to one; reliability in (0, 1]
    [estimate]          architectures = ["BAYES", "DS"] (the default)
    [evaluate]          sample_runs = 3 (runs drawn one by one in the recording)

The resolved definitions are a :class:`fusionlog.core.identity.IdentitySystem`, the kind's
system. Every problem is a ValidationError ``<file>: <key path>: <reason>`` on one line.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fusionlog.core.identity.model import (
    ARCHITECTURES,
    MAX_CLASSES,
    SUM_TOL,
    UNKNOWN,
    IdentitySensor,
    IdentitySystem,
)
from fusionlog.errors import FusionlogError

from . import toml
from .scenario_base import DEFAULT_SAMPLE_RUNS, Scenario, header
from .toml import Ctx

__all__ = [
    "IdentityScenario",
    "check_identity_architectures",
    "identity_from_doc",
    "is_identity_doc",
]

_TOP_KEYS = ("scenario", "identity", "identity_sensors", "estimate", "evaluate")
_SCENARIO_KEYS = ("name", "description", "steps", "runs", "seed", "dt")
_IDENTITY_KEYS = ("classes", "prior", "sets")
_SENSOR_KEYS = ("name", "reports", "confusion", "reliability")
_EVALUATE_KEYS = ("sample_runs",)


@dataclass(frozen=True, eq=False)
class IdentityScenario(Scenario):
    """An identity scenario: classes, prior and sensors reporting a class or a named set
    (`core.identity.IdentitySystem`), fused by Bayes' and Dempster's rules (seed 004)."""

    kind = "identity"
    system: IdentitySystem


def is_identity_doc(doc: Mapping[str, Any] | None) -> bool:
    """Whether a parsed TOML document is an identity scenario: the one place the kind of a
    scenario file is decided."""
    return isinstance(doc, Mapping) and ("identity" in doc or "identity_sensors" in doc)


def identity_from_doc(
    doc: dict[str, Any],
    file: str,
    source: str,
    path: str | None,
    *,
    model: bool = False,
    recorded: bool = False,
) -> IdentityScenario:
    """An identity scenario from a parsed TOML document; with ``model`` (``estimate --model``)
    [scenario] and its keys are optional: classes, prior, sets and sensors are what is used."""
    ctx = Ctx(file, recorded)
    if not is_identity_doc(doc):
        raise ctx.err("identity", "missing required section [identity]: not an identity scenario")
    toml.check_keys(ctx, doc, "(top level)", _TOP_KEYS, what="section")
    sc = toml.table(ctx, doc, "scenario", required=not model) or {}
    toml.check_keys(ctx, sc, "scenario", _SCENARIO_KEYS)
    h = header(ctx, sc, model=model)

    idt = toml.table(ctx, doc, "identity", required=True)
    toml.check_keys(ctx, idt, "identity", _IDENTITY_KEYS, required=("classes",))
    classes = _classes(ctx, idt["classes"])
    n = len(classes)
    prior = _prior(ctx, idt["prior"], n) if "prior" in idt else np.full(n, 1.0 / n)
    sets = _sets(ctx, idt.get("sets", {}), classes)
    sensors = _sensors(ctx, doc, classes, sets)
    archs = _architectures(ctx, doc)
    ev = toml.table(ctx, doc, "evaluate", required=False) or {}
    toml.check_keys(ctx, ev, "evaluate", _EVALUATE_KEYS)
    sample_runs = DEFAULT_SAMPLE_RUNS
    if "sample_runs" in ev:
        sample_runs = toml.integer(ctx, ev["sample_runs"], "evaluate.sample_runs", minimum=0)
    return IdentityScenario.of(
        h,
        IdentitySystem(classes=classes, prior=prior, sets=sets, sensors=sensors),
        dt=1.0 if h.dt is None else h.dt,
        state_names=classes,
        architectures=archs,
        sample_runs=sample_runs,
        source=source,
        path=path,
    )


def _classes(ctx: Ctx, v: Any) -> tuple[str, ...]:
    where = "identity.classes"
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a list of class names, got {toml.tname(v)}")
    if len(v) < 2:
        raise ctx.err(where, f"needs at least two classes, got {len(v)}")
    if len(v) > MAX_CLASSES:
        raise ctx.err(where, f"{len(v)} classes, at most {MAX_CLASSES} (DS keeps 2^N masses)")
    out: list[str] = []
    for i, c in enumerate(v):
        c = toml.name(ctx, c, f"{where}[{i}]")
        if c == UNKNOWN:
            raise ctx.err(f"{where}[{i}]", f"{UNKNOWN!r} is reserved for the whole frame")
        if c in out:
            raise ctx.err(f"{where}[{i}]", f"duplicate class {c!r}")
        out.append(c)
    return tuple(out)


def _probabilities(ctx: Ctx, v: Any, where: str, n: int, what: str) -> np.ndarray:
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a list of {n} probabilities, got {toml.tname(v)}")
    p = np.array([toml.number(ctx, x, f"{where}[{i}]") for i, x in enumerate(v)])
    if p.shape != (n,):
        raise ctx.err(where, f"length {p.size}, expected {n} ({what})")
    if (p < 0).any():
        i = int(np.flatnonzero(p < 0)[0])
        raise ctx.err(f"{where}[{i}]", f"must be >= 0, got {toml.fmt(p[i])}")
    if abs(p.sum() - 1.0) > SUM_TOL:
        raise ctx.err(where, f"sums to {p.sum():.12g}, not 1")
    return p


def _prior(ctx: Ctx, v: Any, n: int) -> np.ndarray:
    p = _probabilities(ctx, v, "identity.prior", n, "one per class")
    p.flags.writeable = False
    return p


def _sets(ctx: Ctx, v: Any, classes: tuple[str, ...]) -> dict[str, tuple[str, ...]]:
    if not isinstance(v, dict):
        raise ctx.err("identity.sets", f"expected a table of named sets, got {toml.tname(v)}")
    out: dict[str, tuple[str, ...]] = {}
    for key, members in v.items():
        where = f"identity.sets.{key}"
        name = toml.name(ctx, key, where)
        if name == UNKNOWN:
            raise ctx.err(where, f"{UNKNOWN!r} is implicit (the whole frame); choose another name")
        if name in classes:
            raise ctx.err(where, f"{name!r} is already a class name")
        if not isinstance(members, list):
            raise ctx.err(where, f"expected a list of class names, got {toml.tname(members)}")
        if not members:
            raise ctx.err(where, "empty set")
        seen: list[str] = []
        for i, c in enumerate(members):
            c = toml.string(ctx, c, f"{where}[{i}]")
            if c not in classes:
                raise ctx.err(f"{where}[{i}]", toml.unknown_msg("class", c, classes))
            if c in seen:
                raise ctx.err(f"{where}[{i}]", f"duplicate class {c!r}")
            seen.append(c)
        out[name] = tuple(seen)
    return out


def _sensors(
    ctx: Ctx, doc: dict[str, Any], classes: tuple[str, ...], sets: dict[str, tuple[str, ...]]
) -> tuple[IdentitySensor, ...]:
    n = len(classes)
    bit = {c: 1 << j for j, c in enumerate(classes)}
    named = {c: bit[c] for c in classes}
    for s, members in sets.items():
        named[s] = sum(bit[c] for c in members)
    named[UNKNOWN] = (1 << n) - 1
    out: list[IdentitySensor] = []
    for where, t, name in toml.named_tables(ctx, doc, "identity_sensors", _SENSOR_KEYS, ""):
        reports = t["reports"]
        if not isinstance(reports, list):
            raise ctx.err(
                f"{where}.reports", f"expected a list of report names, got {toml.tname(reports)}"
            )
        if not reports:
            raise ctx.err(f"{where}.reports", "empty: name at least one report")
        rep: list[str] = []
        for i, r in enumerate(reports):
            r = toml.string(ctx, r, f"{where}.reports[{i}]")
            if r not in named:
                raise ctx.err(
                    f"{where}.reports[{i}]", toml.unknown_msg("class or set", r, list(named))
                )
            if r in rep:
                raise ctx.err(f"{where}.reports[{i}]", f"duplicate report {r!r}")
            rep.append(r)
        C = toml.matrix(ctx, t["confusion"], f"{where}.confusion")
        if C.shape != (n, len(rep)):
            raise ctx.err(
                f"{where}.confusion",
                f"shape {C.shape[0]}x{C.shape[1]}, expected {n}x{len(rep)} "
                f"(one row per class, one column per report)",
            )
        for i in range(n):
            row = C[i]
            if (row < 0).any():
                c = int(np.flatnonzero(row < 0)[0])
                raise ctx.err(
                    f"{where}.confusion[{i}][{c}]", f"must be >= 0, got {toml.fmt(row[c])}"
                )
            if abs(row.sum() - 1.0) > SUM_TOL:
                raise ctx.err(
                    f"{where}.confusion[{i}]",
                    f"row sums to {row.sum():.12g}, not 1 (P(report | {classes[i]}) over the "
                    "reports)",
                )
        C.flags.writeable = False
        rel = toml.number(ctx, t["reliability"], f"{where}.reliability")
        if not 0.0 < rel <= 1.0:
            raise ctx.err(f"{where}.reliability", f"must be in (0, 1], got {toml.fmt(rel)}")
        out.append(IdentitySensor(name, tuple(rep), tuple(named[r] for r in rep), C, rel))
    return tuple(out)


def _architectures(ctx: Ctx, doc: dict[str, Any]) -> tuple[str, ...]:
    def check(a: str) -> None:
        if a not in ARCHITECTURES:
            raise ValueError(_arch_msg(a))

    return toml.architectures(ctx, doc, ARCHITECTURES, check)


def _arch_msg(a: str) -> str:
    return (
        f"unknown architecture {a!r} for an identity scenario (known: {', '.join(ARCHITECTURES)})"
    )


def check_identity_architectures(names: Sequence[str], where: str = "--arch") -> list[str]:
    """Validate identity architecture names (e.g. from --arch); duplicates are dropped."""
    for a in names:
        if a not in ARCHITECTURES:
            raise FusionlogError(f"{where}: {_arch_msg(a)}")
    return list(dict.fromkeys(names))
