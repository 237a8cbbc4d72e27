"""Identity (classification) scenarios through the pipeline: simulate, estimate, evaluate.

Bayesian and Dempster-Shafer identity fusion of Challa & Koks (seed 004, Secs. 3-4): which
aircraft is it, a Learjet, a Falcon or a Caravan, from sensors that report a class, a named set
of classes ("fast" = {Learjet, Falcon}) or "unknown" (the whole frame)?

Scenario TOML (a file with an ``[identity]`` section is an identity scenario)::

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

Every problem is a ValidationError ``<file>: <key path>: <reason>`` on one line (as in
:mod:`fusionlog.scenario`, whose helpers this module uses).

Simulation: the true class of a run is drawn from the prior; at every step each sensor draws a
report from the row of its confusion matrix for that class, independently (the conditional
independence of eq. 36). Random numbers come from one stream per chunk of runs, as in
:mod:`fusionlog.core.simulate`, so the runs do not depend on the block size. Draw order per
chunk: one uniform per run (the class), then one per (run, step, sensor) (the reports), both
turned into indices by the inverse CDF.

MCAP (the DESIGN contract, schema ``fusionlog.Block`` for every topic, ``dim`` = columns):

=========================  ======  ========================================================
``/truth``                 1       index of the true class in ``classes``
``/sensors/<name>``        1       index of the report in the sensor's ``reports``; NaN = no
                                   report at that step (a real log may have gaps)
``/estimates/BAYES``       N       posterior probability of each class, in ``classes`` order
``/estimates/DS``          2N + 2  Bel({c}) of each class, then Pl({c}) of each class, then
                                   the conflict K of that step's combination, then the
                                   accumulated conflict 1 - prod_{t<=k} (1 - K_t)
=========================  ======  ========================================================

The sensors file's ``fusionlog.scenario`` record has ``kind = "identity"`` beside the TOML and
the resolved definitions (JSON, field ``identity``); the estimates file's provenance has the
column layout (field ``columns``). A run whose DS combination reaches total conflict (K = 1,
possible only with reliability 1) has NaN belief and plausibility from then on, per-step
conflict 1 at that step and NaN after, accumulated conflict 1.

Estimation (vectorised over the runs of a block, cumulative over time: the estimate at k uses
every report at t <= k):

* ``BAYES``: posterior_k(c) proportional to prior(c) prod_{t<=k} prod_s confusion_s[c, r_{s,t}]:
  eqs. (36)-(37) with the sensors' likelihoods, applied recursively (the posterior is the next
  prior, eqs. 38/41); log-likelihoods are summed, then :func:`bayes_fusion` normalises.
* ``DS``: report R of a sensor is the simple support function m(R) = reliability,
  m(frame) = 1 - reliability; every report is combined with Dempster's rule (eq. 47,
  :func:`dempster_combine_array`) into the running mass function over the 2^N subsets.
  Bel and Pl of each class come from :func:`belief_array` / :func:`plausibility_array`.

Identity (tested): the normalised singleton plausibility of the DS combination equals the Bayes
posterior with a uniform prior and the "likelihood" pl(c | R) = 1 if c in R else 1 - reliability
of each report (Dempster's rule multiplies contour functions: Pl_12({c}) = Pl_1({c}) Pl_2({c})
/ (1 - K)). In particular, with reliability 1 and singleton reports every report is a Bayesian
(categorical) mass function and DS is Bayes' rule with a uniform prior and 0/1 likelihoods:
Bel = Pl = the indicator of the reported class while all reports agree, total conflict as soon
as two differ.

Evaluation, per step k over the runs (metrics of the summary are means over the steps,
``final`` the values at k = K):

* decision: BAYES the class of largest posterior; DS the class of largest belief, ties in
  belief broken by plausibility. Remaining ties are split evenly (a run counts 1/|tied| as
  correct if its class is among the tied ones: the expected accuracy of a random tie-break).
  A DS run in total conflict decides nothing (counts as wrong).
* ``accuracy``: share of runs classified correctly.
* ``mean_p_true``: mean probability of the true class: BAYES posterior; DS the normalised
  plausibility Pl({c}) / sum_c' Pl({c'}) (the probability of the identity above).
* ``log_loss``: mean of -log of that probability (infinite if it is zero for some run: a
  reliable sensor ruled the true class out).
* DS: ``mean_belief_true``, ``mean_plausibility_true``, ``mean_conflict`` (per-step K),
  ``final.accumulated_conflict``, ``total_conflict`` (share of runs in total conflict at K).
* ``disagreement``: share of runs where the BAYES and DS decisions differ (ties as above:
  1 - sum_c w_BAYES(c) w_DS(c)).
* ``stderr``: Monte Carlo standard errors of the overall accuracy, log-loss and mean_p_true,
  from the spread of the per-run averages over the steps.

DS values are averaged over the runs where DS is defined (not in total conflict); accuracy and
disagreement over all runs.
"""

from __future__ import annotations

import difflib
import json
import os
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fusionlog.core.identity.fusion import columns, dims, estimate, report_indices
from fusionlog.core.identity.metrics import IdentityMetrics
from fusionlog.core.identity.model import (
    ARCHITECTURES,
    MAX_CLASSES,
    SUM_TOL,
    UNKNOWN,
    IdentitySensor,
    IdentitySystem,
)
from fusionlog.core.identity.simulate import simulate
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap_io import VALUES, McapFile, McapWriter
from fusionlog.scenario import (
    _check_int,
    _check_keys,
    _Ctx,
    _float,
    _fmt,
    _matrix,
    _name,
    _parse_toml,
    _read_text,
    _show,
    _str,
    _table,
    _tname,
    scenario_with,
)

from .common import (
    PROVENANCE_META,
    SCENARIO_META,
    block_runs,
    open_evaluation_inputs,
    progress,
    provenance,
    sha256_of,
)
from .simulate import SimulateResult

if TYPE_CHECKING:
    from .estimate import EstimateResult
    from .evaluate import EvaluateResult

__all__ = [
    "ARCHITECTURES",
    "KIND",
    "IdentityScenario",
    "check_architectures",
    "identity_scenario_from_text",
    "is_identity_file",
    "is_identity_scenario_file",
    "load_identity_model",
    "load_identity_scenario",
    "run_estimate",
    "run_evaluate",
    "run_simulate",
]

KIND = "identity"
#: Default bound on masses held at once by DS (runs x 2^N), as RUN_STEPS_PER_BLOCK for steps.
DS_MASSES_PER_BLOCK = 1 << 21

_TOP_KEYS = ("scenario", "identity", "identity_sensors", "estimate", "evaluate")
_SCENARIO_KEYS = ("name", "description", "steps", "runs", "seed", "dt")
_SCENARIO_REQUIRED = ("name", "steps", "runs", "seed", "dt")
_IDENTITY_KEYS = ("classes", "prior", "sets")
_SENSOR_KEYS = ("name", "reports", "confusion", "reliability")
_ESTIMATE_KEYS = ("architectures",)
_EVALUATE_KEYS = ("sample_runs",)
_DEFAULT_SAMPLE_RUNS = 3


# --------------------------------------------------------------------------------------------
# Scenario
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class IdentityScenario:
    """A validated identity scenario (or, from ``--model``, the fusion node's model)."""

    name: str
    description: str
    steps: int
    runs: int
    seed: int
    dt: float
    classes: tuple[str, ...]
    prior: np.ndarray
    sets: dict[str, tuple[str, ...]]
    sensors: tuple[IdentitySensor, ...]
    architectures: tuple[str, ...] = ARCHITECTURES
    sample_runs: int = _DEFAULT_SAMPLE_RUNS
    source: str = ""
    path: str | None = None
    kind: str = KIND

    @property
    def state_names(self) -> tuple[str, ...]:
        """The classes: the summary's ``state_names``."""
        return self.classes

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.steps + 1) * self.dt

    @cached_property
    def system(self) -> IdentitySystem:
        """The classes, prior, sets and sensors: what simulation and fusion use."""
        return IdentitySystem(self.classes, self.prior, self.sets, self.sensors)

    def to_dict(self) -> dict[str, Any]:
        """The resolved definitions as plain data (metadata, provenance)."""
        return {**self.system.to_dict(), "architectures": list(self.architectures)}


def _peek_toml(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return None


def _is_identity_doc(doc: Mapping[str, Any] | None) -> bool:
    return isinstance(doc, Mapping) and ("identity" in doc or "identity_sensors" in doc)


def is_identity_scenario_file(path: str | os.PathLike[str]) -> bool:
    """Whether a scenario file is an identity scenario (has [identity] or [[identity_sensors]]).

    An unreadable or invalid file is not: the state loader then reports the problem.
    """
    return _is_identity_doc(_peek_toml(path))


def load_identity_scenario(
    path: str | os.PathLike[str],
    *,
    runs: int | None = None,
    steps: int | None = None,
    seed: int | None = None,
) -> IdentityScenario:
    """Read and validate an identity scenario file; `runs`, `steps`, `seed` override it."""
    file = os.fspath(path)
    text = _read_text(file)
    sc = _from_doc(_parse_toml(text, file), file, text, file, model=False)
    return identity_with(sc, runs=runs, steps=steps, seed=seed)


def identity_scenario_from_text(text: str, source: str = "<string>") -> IdentityScenario:
    """Validate an identity scenario given as TOML text; `source` names it in errors."""
    return _from_doc(_parse_toml(text, source), source, text, None, model=False)


def load_identity_model(path: str | os.PathLike[str]) -> IdentityScenario:
    """The fusion node's model for ``estimate --model``: an identity scenario file in which
    [scenario] and its keys are optional (classes, prior, sets and sensors are what is used)."""
    file = os.fspath(path)
    text = _read_text(file)
    return _from_doc(_parse_toml(text, file), file, text, file, model=True)


def identity_with(
    sc: IdentityScenario,
    *,
    runs: int | None = None,
    steps: int | None = None,
    seed: int | None = None,
) -> IdentityScenario:
    """A copy with the Monte Carlo settings replaced (None keeps the scenario's value)."""
    return scenario_with(sc, runs=runs, steps=steps, seed=seed)


def _from_doc(
    doc: dict[str, Any], file: str, source: str, path: str | None, *, model: bool
) -> IdentityScenario:
    ctx = _Ctx(file)
    if not _is_identity_doc(doc):
        raise ctx.err("identity", "missing required section [identity]: not an identity scenario")
    _check_keys(ctx, doc, "(top level)", _TOP_KEYS, what="section")
    sc = _table(ctx, doc, "scenario", required=not model) or {}
    _check_keys(ctx, sc, "scenario", _SCENARIO_KEYS, required=() if model else _SCENARIO_REQUIRED)
    name = _name(ctx, sc["name"], "scenario.name") if "name" in sc else "model"
    description = _str(ctx, sc.get("description", ""), "scenario.description")
    ints = {}
    for key, minimum, default in (("steps", 0, 0), ("runs", 1, 1), ("seed", 0, 0)):
        ints[key] = (
            _check_int(ctx, sc[key], f"scenario.{key}", minimum=minimum) if key in sc else default
        )
    dt = 1.0
    if "dt" in sc:
        dt = _float(ctx, sc["dt"], "scenario.dt")
        if not dt > 0:
            raise ctx.err("scenario.dt", f"must be > 0, got {_fmt(dt)}")

    idt = _table(ctx, doc, "identity", required=True)
    _check_keys(ctx, idt, "identity", _IDENTITY_KEYS, required=("classes",))
    classes = _classes(ctx, idt["classes"])
    n = len(classes)
    prior = _prior(ctx, idt["prior"], n) if "prior" in idt else np.full(n, 1.0 / n)
    sets = _sets(ctx, idt.get("sets", {}), classes)
    sensors = _sensors(ctx, doc, classes, sets)
    archs = _architectures(ctx, doc)
    ev = _table(ctx, doc, "evaluate", required=False) or {}
    _check_keys(ctx, ev, "evaluate", _EVALUATE_KEYS)
    sample_runs = _DEFAULT_SAMPLE_RUNS
    if "sample_runs" in ev:
        sample_runs = _check_int(ctx, ev["sample_runs"], "evaluate.sample_runs", minimum=0)
    return IdentityScenario(
        name=name,
        description=description,
        steps=ints["steps"],
        runs=ints["runs"],
        seed=ints["seed"],
        dt=dt,
        classes=classes,
        prior=prior,
        sets=sets,
        sensors=sensors,
        architectures=archs,
        sample_runs=sample_runs,
        source=source,
        path=path,
    )


def _classes(ctx: _Ctx, v: Any) -> tuple[str, ...]:
    where = "identity.classes"
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a list of class names, got {_tname(v)}")
    if len(v) < 2:
        raise ctx.err(where, f"needs at least two classes, got {len(v)}")
    if len(v) > MAX_CLASSES:
        raise ctx.err(where, f"{len(v)} classes, at most {MAX_CLASSES} (DS keeps 2^N masses)")
    out: list[str] = []
    for i, c in enumerate(v):
        c = _name(ctx, c, f"{where}[{i}]")
        if c == UNKNOWN:
            raise ctx.err(f"{where}[{i}]", f"{UNKNOWN!r} is reserved for the whole frame")
        if c in out:
            raise ctx.err(f"{where}[{i}]", f"duplicate class {c!r}")
        out.append(c)
    return tuple(out)


def _probabilities(ctx: _Ctx, v: Any, where: str, n: int, what: str) -> np.ndarray:
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a list of {n} probabilities, got {_tname(v)}")
    p = np.array([_float(ctx, x, f"{where}[{i}]") for i, x in enumerate(v)])
    if p.shape != (n,):
        raise ctx.err(where, f"length {p.size}, expected {n} ({what})")
    if (p < 0).any():
        i = int(np.flatnonzero(p < 0)[0])
        raise ctx.err(f"{where}[{i}]", f"must be >= 0, got {_fmt(p[i])}")
    if abs(p.sum() - 1.0) > SUM_TOL:
        raise ctx.err(where, f"sums to {p.sum():.12g}, not 1")
    return p


def _prior(ctx: _Ctx, v: Any, n: int) -> np.ndarray:
    p = _probabilities(ctx, v, "identity.prior", n, "one per class")
    p.flags.writeable = False
    return p


def _sets(ctx: _Ctx, v: Any, classes: tuple[str, ...]) -> dict[str, tuple[str, ...]]:
    if not isinstance(v, dict):
        raise ctx.err("identity.sets", f"expected a table of named sets, got {_tname(v)}")
    out: dict[str, tuple[str, ...]] = {}
    for key, members in v.items():
        where = f"identity.sets.{key}"
        name = _name(ctx, key, where)
        if name == UNKNOWN:
            raise ctx.err(where, f"{UNKNOWN!r} is implicit (the whole frame); choose another name")
        if name in classes:
            raise ctx.err(where, f"{name!r} is already a class name")
        if not isinstance(members, list):
            raise ctx.err(where, f"expected a list of class names, got {_tname(members)}")
        if not members:
            raise ctx.err(where, "empty set")
        seen: list[str] = []
        for i, c in enumerate(members):
            c = _str(ctx, c, f"{where}[{i}]")
            if c not in classes:
                raise ctx.err(f"{where}[{i}]", _unknown_msg("class", c, classes))
            if c in seen:
                raise ctx.err(f"{where}[{i}]", f"duplicate class {c!r}")
            seen.append(c)
        out[name] = tuple(seen)
    return out


def _unknown_msg(what: str, name: str, known: Sequence[str]) -> str:
    hint = difflib.get_close_matches(name, list(known), n=1)
    mean = f"; did you mean {hint[0]!r}?" if hint else ""
    return f"unknown {what} {_show(name)} (known: {', '.join(known)}){mean}"


def _sensors(
    ctx: _Ctx, doc: dict[str, Any], classes: tuple[str, ...], sets: dict[str, tuple[str, ...]]
) -> tuple[IdentitySensor, ...]:
    key = "identity_sensors"
    if key not in doc:
        raise ctx.err(key, "missing: give at least one [[identity_sensors]] table")
    items = doc[key]
    if isinstance(items, dict):
        raise ctx.err(key, "expected an array of tables ([[identity_sensors]]), got one table")
    if not isinstance(items, list) or not all(isinstance(t, dict) for t in items):
        raise ctx.err(
            key, f"expected an array of tables ([[identity_sensors]]), got {_tname(items)}"
        )
    if not items:
        raise ctx.err(key, "empty: give at least one sensor")
    n = len(classes)
    bit = {c: 1 << j for j, c in enumerate(classes)}
    named = {c: bit[c] for c in classes}
    for s, members in sets.items():
        named[s] = sum(bit[c] for c in members)
    named[UNKNOWN] = (1 << n) - 1
    out: list[IdentitySensor] = []
    seen: dict[str, int] = {}
    for j, t in enumerate(items):
        where = f"{key}[{j}]"
        _check_keys(ctx, t, where, _SENSOR_KEYS, required=_SENSOR_KEYS)
        name = _name(ctx, t["name"], f"{where}.name")
        if name in seen:
            raise ctx.err(
                f"{where}.name", f"duplicate sensor name {name!r} (also {key}[{seen[name]}])"
            )
        seen[name] = j
        reports = t["reports"]
        if not isinstance(reports, list):
            raise ctx.err(
                f"{where}.reports", f"expected a list of report names, got {_tname(reports)}"
            )
        if not reports:
            raise ctx.err(f"{where}.reports", "empty: name at least one report")
        rep: list[str] = []
        for i, r in enumerate(reports):
            r = _str(ctx, r, f"{where}.reports[{i}]")
            if r not in named:
                raise ctx.err(f"{where}.reports[{i}]", _unknown_msg("class or set", r, list(named)))
            if r in rep:
                raise ctx.err(f"{where}.reports[{i}]", f"duplicate report {r!r}")
            rep.append(r)
        C = _matrix(ctx, t["confusion"], f"{where}.confusion")
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
                raise ctx.err(f"{where}.confusion[{i}][{c}]", f"must be >= 0, got {_fmt(row[c])}")
            if abs(row.sum() - 1.0) > SUM_TOL:
                raise ctx.err(
                    f"{where}.confusion[{i}]",
                    f"row sums to {row.sum():.12g}, not 1 (P(report | {classes[i]}) over the "
                    "reports)",
                )
        C.flags.writeable = False
        rel = _float(ctx, t["reliability"], f"{where}.reliability")
        if not 0.0 < rel <= 1.0:
            raise ctx.err(f"{where}.reliability", f"must be in (0, 1], got {_fmt(rel)}")
        out.append(IdentitySensor(name, tuple(rep), tuple(named[r] for r in rep), C, rel))
    return tuple(out)


def _architectures(ctx: _Ctx, doc: dict[str, Any]) -> tuple[str, ...]:
    est = _table(ctx, doc, "estimate", required=False)
    if est is None:
        return ARCHITECTURES
    _check_keys(ctx, est, "estimate", _ESTIMATE_KEYS)
    if "architectures" not in est:
        return ARCHITECTURES
    archs = est["architectures"]
    if not isinstance(archs, list):
        raise ctx.err("estimate.architectures", f"expected a list of names, got {_tname(archs)}")
    if not archs:
        raise ctx.err("estimate.architectures", "empty: name at least one architecture")
    out: list[str] = []
    for i, a in enumerate(archs):
        where = f"estimate.architectures[{i}]"
        a = _str(ctx, a, where)
        if a not in ARCHITECTURES:
            raise ctx.err(where, _arch_msg(a))
        if a in out:
            raise ctx.err(where, f"duplicate architecture {a!r}")
        out.append(a)
    return tuple(out)


def _arch_msg(a: str) -> str:
    return (
        f"unknown architecture {a!r} for an identity scenario (known: {', '.join(ARCHITECTURES)})"
    )


def check_architectures(names: Sequence[str], where: str = "--arch") -> list[str]:
    """Validate identity architecture names (e.g. from --arch); duplicates are dropped."""
    for a in names:
        if a not in ARCHITECTURES:
            raise FusionlogError(f"{where}: {_arch_msg(a)}")
    return list(dict.fromkeys(names))


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def _metadata(sc: IdentityScenario) -> dict[str, str]:
    return {
        "kind": KIND,
        "toml": sc.source,
        "name": sc.name,
        "steps": str(sc.steps),
        "runs": str(sc.runs),
        "seed": str(sc.seed),
        "dt": repr(sc.dt),
        "identity": json.dumps(sc.to_dict()),
    }


def is_identity_file(path: str | os.PathLike[str]) -> bool:
    """Whether an MCAP file's ``fusionlog.scenario`` record is an identity scenario."""
    meta = McapFile(path).metadata.get(SCENARIO_META)
    if meta is None:
        return False
    if meta.get("kind") == KIND:
        return True
    try:
        return _is_identity_doc(tomllib.loads(meta.get("toml", "")))
    except tomllib.TOMLDecodeError:
        return False


def _scenario_of(mf: McapFile) -> IdentityScenario | None:
    meta = mf.metadata.get(SCENARIO_META)
    if meta is None:
        return None
    try:
        sc = identity_scenario_from_text(
            meta["toml"], source=f"{mf.path} (metadata {SCENARIO_META})"
        )
        return identity_with(
            sc, runs=int(meta["runs"]), steps=int(meta["steps"]), seed=int(meta["seed"])
        )
    except (KeyError, ValueError) as e:
        raise FusionlogError(f"{mf.path}: metadata {SCENARIO_META} is unreadable ({e})") from e


def _block(steps: int, runs: int, n_classes: int, requested: int | None) -> int:
    if requested is not None:
        return block_runs(steps, runs, requested)
    return max(1, min(block_runs(steps, runs), DS_MASSES_PER_BLOCK >> n_classes))


# --------------------------------------------------------------------------------------------
# simulate
# --------------------------------------------------------------------------------------------


def run_simulate(
    scenario: IdentityScenario,
    out: Path,
    *,
    force: bool = False,
    block: int | None = None,
    command: str = "fusionlog simulate",
) -> SimulateResult:
    """Simulate `scenario` block by block of runs: /truth (class index) and /sensors/<name>."""
    K, M = scenario.steps, scenario.runs
    B = block_runs(K, M, block)
    times = scenario.times
    topics = [f"/sensors/{s.name}" for s in scenario.sensors]
    messages = 0
    with McapWriter(out, force=force) as w:
        w.add_metadata(SCENARIO_META, _metadata(scenario))
        w.add_metadata(PROVENANCE_META, provenance(command, scenario.seed))
        offsets = range(0, M, B)
        for off in progress(offsets, len(offsets), "simulate"):
            runs = min(B, M - off)
            truth, reports = simulate(scenario.system, K, scenario.seed, off, runs)
            t = truth.astype(float)[:, None]
            r = reports.astype(float)
            for k in range(K + 1):
                w.write_values("/truth", k, float(times[k]), off, t)
                for s, topic in enumerate(topics):
                    w.write_values(topic, k, float(times[k]), off, r[:, k, s : s + 1])
            messages += (K + 1) * (1 + len(topics))
    return SimulateResult(Path(out), M, K, messages)


# --------------------------------------------------------------------------------------------
# estimate
# --------------------------------------------------------------------------------------------


def _check_topics(mf: McapFile, model: IdentityScenario) -> list[str]:
    topics = []
    for s in model.sensors:
        t = f"/sensors/{s.name}"
        if t not in mf.topics:
            have = ", ".join(sorted(mf.topics)) or "none"
            raise FusionlogError(
                f"{mf.path}: no topic {t} for identity sensor {s.name!r} (topics: {have})"
            )
        if mf.kind_of(t) != VALUES or mf.dim_of(t) != 1:
            raise FusionlogError(
                f"{mf.path}: topic {t} is not a stream of report indices (fusionlog.Block, dim 1)"
            )
        topics.append(t)
    return topics


def _resolve_model(
    mf: McapFile, model_path: Path | None
) -> tuple[IdentityScenario | None, IdentityScenario, str]:
    recorded = _scenario_of(mf)
    if model_path is None:
        if recorded is None:
            raise FusionlogError(
                f"{mf.path}: no {SCENARIO_META} metadata to take the model from; "
                "pass --model MODEL.toml"
            )
        return recorded, recorded, "scenario"
    model = load_identity_model(model_path)
    if recorded is not None:
        if model.classes != recorded.classes:
            raise FusionlogError(
                f"{model_path}: identity.classes {list(model.classes)} differ from the "
                f"recorded scenario's {list(recorded.classes)}"
            )
        rec = {s.name: s for s in recorded.sensors}
        for j, s in enumerate(model.sensors):
            if s.name in rec and s.reports != rec[s.name].reports:
                raise FusionlogError(
                    f"{model_path}: identity_sensors[{j}].reports {list(s.reports)} differ from "
                    f"the recorded sensor's {list(rec[s.name].reports)} (the log holds indices "
                    "into them)"
                )
    return recorded, model, str(model_path)


def _library_error(path: Path | str, e: ValueError) -> FusionlogError:
    return FusionlogError(f"{path}: identity fusion failed: {e}")


def run_estimate(
    sensors_path: Path,
    out: Path,
    *,
    archs: list[str] | None = None,
    model_path: Path | None = None,
    force: bool = False,
    block: int | None = None,
    command: str = "fusionlog estimate",
) -> EstimateResult:
    """Fuse every run's reports with BAYES and/or DS; write /estimates/<ARCH> (see module doc)."""
    from .estimate import EstimateResult  # imported here: it pulls in scipy

    mf = McapFile(sensors_path)
    recorded, model, model_source = _resolve_model(mf, model_path)
    topics = _check_topics(mf, model)
    if not archs:
        archs = list(recorded.architectures if recorded is not None else model.architectures)
    archs = check_architectures(archs, "--arch")
    if out.exists() and not force:
        raise FusionlogError(f"{out}: exists; use --force to overwrite")
    K, M, n = mf.steps() - 1, mf.runs(), len(model.classes)
    times = mf.times()
    B = _block(K, M, n, block)
    cols = columns(model.classes, archs)
    meta_prov = provenance(
        command,
        recorded.seed if recorded is not None else None,
        sensors_sha256=sha256_of(Path(sensors_path)),
        sensors_file=Path(sensors_path).name,
        model_source=model_source,
        model=json.dumps(model.to_dict()),
        architectures=json.dumps(archs),
        columns=json.dumps(cols),
    )
    with McapWriter(out, force=force) as w:
        if SCENARIO_META in mf.metadata:
            w.add_metadata(SCENARIO_META, mf.metadata[SCENARIO_META])
        w.add_metadata(PROVENANCE_META, meta_prov)
        blocks = mf.iter_run_blocks(topics, B)
        for off, _runs, data in progress(blocks, -(-M // B), "estimate"):
            try:
                reports = np.stack(
                    [
                        report_indices(data[t][..., 0], len(s.reports), f"{t}", allow_nan=True)
                        for t, s in zip(topics, model.sensors, strict=True)
                    ],
                    axis=-1,
                )
            except ValueError as e:
                raise FusionlogError(f"{sensors_path}: runs from {off}: {e}") from None
            try:
                out_vals = {a: estimate(model.system, reports, a, off) for a in archs}
            except ValueError as e:
                raise _library_error(sensors_path, e) from None
            for a in archs:
                topic = f"/estimates/{a}"
                vals = out_vals[a]
                for k in range(K + 1):
                    w.write_values(topic, k, float(times[k]), off, vals[:, k])
    return EstimateResult(Path(out), archs, M, K)


# --------------------------------------------------------------------------------------------
# evaluate
# --------------------------------------------------------------------------------------------


def run_evaluate(
    sensors_path: Path,
    estimates_path: Path,
    out: Path,
    *,
    summary_path: Path | None = None,
    force: bool = False,
    block: int | None = None,
) -> EvaluateResult:
    """Identity metrics of every architecture of `estimates_path` into a recording (and JSON)."""
    from fusionlog.io.rrd_identity import write_identity_recording  # rerun: slow to import

    from .evaluate import EvaluateResult, write_json_atomic

    outputs = [out] + ([summary_path] if summary_path else [])
    sens, est, prov = open_evaluation_inputs(sensors_path, estimates_path, outputs, force)
    sc = _scenario_of(sens)
    if sc is None:
        raise FusionlogError(f"{sensors_path}: no {SCENARIO_META} metadata (not a simulation)")
    n = len(sc.classes)
    sizes = dims(n)
    archs = [a for a in ARCHITECTURES if f"/estimates/{a}" in est.topics]
    if not archs:
        have = ", ".join(sorted(est.topics)) or "none"
        raise FusionlogError(
            f"{estimates_path}: no /estimates/BAYES or /estimates/DS topics (topics: {have})"
        )
    topics = [f"/estimates/{a}" for a in archs]
    for a, t in zip(archs, topics, strict=True):
        if est.kind_of(t) != VALUES or est.dim_of(t) != sizes[a]:
            raise FusionlogError(
                f"{estimates_path}: topic {t} is not an identity estimate "
                f"(fusionlog.Block with {sizes[a]} values per run for {n} classes)"
            )
    K, M = sens.steps() - 1, sens.runs()
    times = sens.times()
    B = _block(K, M, n, block)
    metrics = IdentityMetrics(K + 1, sc.classes, archs, sample_runs=min(sc.sample_runs, M))
    blocks = zip(sens.iter_run_blocks(["/truth"], B), est.iter_run_blocks(topics, B), strict=True)
    for (off, _runs, tdata), (_, _, edata) in progress(blocks, -(-M // B), "evaluate"):
        try:
            truth = report_indices(tdata["/truth"][:, 0, 0], n, "/truth", allow_nan=False)
        except ValueError as e:
            raise FusionlogError(f"{sensors_path}: runs from {off}: {e}") from None
        if (tdata["/truth"][..., 0] != tdata["/truth"][:, :1, 0]).any():
            raise FusionlogError(f"{sensors_path}: runs from {off}: the true class changes")
        metrics.add(truth, {a: edata[t] for a, t in zip(archs, topics, strict=True)}, off)
    res = metrics.finish()
    summary: dict[str, Any] = {
        "kind": KIND,
        "scenario": sc.name,
        "seed": sc.seed,
        "runs": M,
        "steps": K,
        "state_names": list(sc.classes),
        "architectures": res.architectures,
    }
    if res.disagreement is not None:
        summary["disagreement"] = res.disagreement_overall
        summary["final_disagreement"] = res.disagreement_final
    definitions = {
        "columns": json.dumps(columns(sc.classes, archs)),
        "decision": "BAYES: largest posterior; DS: largest belief, ties by plausibility; "
        "remaining ties split evenly",
        "p_true": "BAYES: posterior; DS: normalised plausibility Pl({c}) / sum Pl",
        "per_class": "identity/<kind>/<class>/<ARCH>: mean over the runs whose truth is <class>",
    }
    try:
        write_identity_recording(
            out,
            scenario_name=sc.name,
            seed=sc.seed,
            times=times,
            classes=sc.classes,
            series=res.series,
            disagreement=res.disagreement,
            summary=summary,
            sample_runs=res.samples,
            properties={"scenario": sc.source, "provenance": prov, "identity": definitions},
            force=force,
        )
    except ValueError as e:  # pragma: no cover - inputs are built above
        raise FusionlogError(f"{out}: {e}") from None
    if summary_path is not None:
        write_json_atomic(summary_path, summary, force)
    return EvaluateResult(out, summary_path, summary)
