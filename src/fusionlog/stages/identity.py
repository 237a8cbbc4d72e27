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
import math
import os
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fusionlog.core.identity import (
    bayes_fusion,
    belief_array,
    dempster_combine_array,
    plausibility_array,
)
from fusionlog.core.simulate import chunk_runs
from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import VALUES, McapFile, McapWriter
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
    "IdentitySensor",
    "bayes_posteriors",
    "check_architectures",
    "ds_columns",
    "ds_combine",
    "identity_scenario_from_text",
    "is_identity_file",
    "is_identity_scenario_file",
    "load_identity_model",
    "load_identity_scenario",
    "run_estimate",
    "run_evaluate",
    "run_simulate",
    "simulate_identity",
]

KIND = "identity"
#: Identity architectures (DESIGN.md): Bayes' rule and Dempster's rule.
ARCHITECTURES: tuple[str, ...] = ("BAYES", "DS")
#: The implicit name of the whole frame.
UNKNOWN = "unknown"
#: Largest frame: DS keeps 2^N masses per run.
MAX_CLASSES = 12
#: Default bound on masses held at once by DS (runs x 2^N), as RUN_STEPS_PER_BLOCK for steps.
DS_MASSES_PER_BLOCK = 1 << 21
#: Tolerance of "sums to one" (prior, rows of the confusion matrices).
SUM_TOL = 1e-9
#: Two scores closer than this count as a tie in a decision.
TIE_TOL = 1e-12

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
class IdentitySensor:
    """A sensor's report alphabet, its confusion matrix and its DS reliability."""

    name: str
    reports: tuple[str, ...]  # as written: class names, set names or "unknown"
    subsets: tuple[int, ...]  # each report's subset of the frame as a bitmask (subset_index)
    confusion: np.ndarray  # (N classes, len(reports)): P(report | class), rows sum to one
    reliability: float  # DS: m(report) = reliability, m(frame) = 1 - reliability

    def mass_table(self, n_classes: int) -> np.ndarray:
        """(len(reports) + 1, 2^N): the DS mass function of each report; last row: no report."""
        size = 1 << n_classes
        table = np.zeros((len(self.reports) + 1, size))
        table[:, size - 1] = 1.0
        for j, b in enumerate(self.subsets):
            table[j, size - 1] -= self.reliability
            table[j, b] += self.reliability
        return table

    def likelihood(self) -> np.ndarray:
        """(len(reports) + 1, N): P(report | class) of each report; last row (no report): 1."""
        return np.vstack([self.confusion.T, np.ones(self.confusion.shape[0])])


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

    def to_dict(self) -> dict[str, Any]:
        """The resolved definitions as plain data (metadata, provenance)."""
        return {
            "classes": list(self.classes),
            "prior": [float(p) for p in self.prior],
            "sets": {k: list(v) for k, v in self.sets.items()},
            "sensors": [
                {
                    "name": s.name,
                    "reports": list(s.reports),
                    "subsets": [
                        [c for j, c in enumerate(self.classes) if b >> j & 1] for b in s.subsets
                    ],
                    "confusion": s.confusion.tolist(),
                    "reliability": s.reliability,
                }
                for s in self.sensors
            ],
            "architectures": list(self.architectures),
        }


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


def ds_columns(classes: Sequence[str]) -> list[str]:
    """Column names of ``/estimates/DS``."""
    return (
        [f"Bel({c})" for c in classes]
        + [f"Pl({c})" for c in classes]
        + ["conflict", "accumulated_conflict"]
    )


def _columns(classes: Sequence[str], archs: Sequence[str]) -> dict[str, list[str]]:
    cols = {"BAYES": [f"P({c})" for c in classes], "DS": ds_columns(classes)}
    return {a: cols[a] for a in archs}


def _dims(n: int) -> dict[str, int]:
    return {"BAYES": n, "DS": 2 * n + 2}


def _block(steps: int, runs: int, n_classes: int, requested: int | None) -> int:
    if requested is not None:
        return block_runs(steps, runs, requested)
    return max(1, min(block_runs(steps, runs), DS_MASSES_PER_BLOCK >> n_classes))


def _indices(values: np.ndarray, n: int, what: str, allow_nan: bool) -> np.ndarray:
    """Float indices -> int64, NaN -> n (the "no report" row); raises ValueError if invalid."""
    v = values
    nan = np.isnan(v)
    if nan.any() and not allow_nan:
        raise ValueError(f"{what}: NaN where a class index is expected")
    ok = nan | ((v >= 0) & (v < n) & (v == np.floor(v)))
    if not ok.all():
        bad = v[~ok][0]
        raise ValueError(f"{what}: value {bad!r} is not an index 0..{n - 1}")
    return np.where(nan, n, v).astype(np.int64)


# --------------------------------------------------------------------------------------------
# Core math (numpy only; no I/O)
# --------------------------------------------------------------------------------------------


def _inverse_cdf(probs: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Index j with cdf_{j-1} <= u < cdf_j, for rows probs (..., J) and uniforms u (...)."""
    cdf = np.cumsum(probs, axis=-1)[..., :-1]
    return (u[..., None] >= cdf).sum(axis=-1)


def _identity_chunk(sc: IdentityScenario, steps: int, seed: int, chunk: int):
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(chunk,)))
    R, S = chunk_runs(steps), len(sc.sensors)
    # Draw order is part of the reproducibility contract: classes, then reports.
    u0 = rng.random(R)
    u = rng.random((R, steps + 1, S))
    truth = _inverse_cdf(np.asarray(sc.prior), u0)
    reports = np.empty((R, steps + 1, S), dtype=np.int64)
    for s, sensor in enumerate(sc.sensors):
        rows = sensor.confusion[truth][:, None, :]  # (R, 1, reports)
        reports[:, :, s] = _inverse_cdf(rows, u[:, :, s])
    return truth, reports


def simulate_identity(
    sc: IdentityScenario, steps: int, seed: int, run_offset: int, runs: int
) -> tuple[np.ndarray, np.ndarray]:
    """True classes (runs,) and report indices (runs, K+1, S) for runs [run_offset, +runs)."""
    size = chunk_runs(steps)
    first, last = run_offset // size, (run_offset + runs - 1) // size
    ts, rs = [], []
    for c in range(first, last + 1):
        t, r = _identity_chunk(sc, steps, seed, c)
        lo, hi = max(run_offset - c * size, 0), min(run_offset + runs - c * size, size)
        ts.append(t[lo:hi])
        rs.append(r[lo:hi])
    return np.concatenate(ts), np.concatenate(rs)


def bayes_posteriors(
    reports: np.ndarray,
    sensors: Sequence[IdentitySensor],
    prior: np.ndarray,
    run_offset: int = 0,
) -> np.ndarray:
    """Cumulative Bayes posteriors (B, K+1, N) from report indices (B, K+1, S).

    A report index equal to the sensor's number of reports means "no report" (likelihood 1).
    posterior_k ∝ prior · prod_{t<=k} prod_s P(r_{s,t} | class): eqs. (36)-(37) recursively;
    log-likelihoods are summed over sensors and time and scaled so that the largest class has
    likelihood 1, then :func:`bayes_fusion` applies the prior and normalises.
    Raises ValueError if the reports of some run have zero likelihood for every class (only
    possible under a model other than the one that simulated them); `run_offset` numbers the
    runs in that message.
    """
    B, K1, S = reports.shape
    n = np.asarray(prior).shape[-1]
    loglik = np.zeros((B, K1, n))
    with np.errstate(divide="ignore"):
        for s, sensor in enumerate(sensors):
            loglik += np.log(sensor.likelihood())[reports[..., s]]
    cum = np.cumsum(loglik, axis=1)
    top = cum.max(axis=-1, keepdims=True)
    if np.isneginf(top).any():
        b, k = (int(i) for i in np.argwhere(np.isneginf(top[..., 0]))[0])
        raise ValueError(
            f"run {run_offset + b}, step {k}: the reports have zero likelihood for every class "
            "under the model's confusion matrices"
        )
    lik = np.exp(cum - top)
    return bayes_fusion(lik[..., None, :], prior)


def ds_combine(
    reports: np.ndarray, sensors: Sequence[IdentitySensor], n_classes: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cumulative Dempster-Shafer combination of every report (eq. 47).

    reports: (B, K+1, S) report indices (the sensor's number of reports = no report). Starts
    from the vacuous mass function; at step k combines the running masses with each sensor's
    report mass (m(R) = reliability, m(frame) = 1 - reliability) by Dempster's rule.
    Returns Bel({c}) and Pl({c}) (B, K+1, N), the conflict K of step k's combination (B, K+1)
    and the accumulated conflict 1 - prod_{t<=k}(1 - K_t) (B, K+1). A run in total conflict
    (K = 1) has NaN Bel and Pl from then on, conflict 1 at that step and NaN after, and
    accumulated conflict 1.
    """
    B, K1, S = reports.shape
    size = 1 << n_classes
    tables = [s.mass_table(n_classes) for s in sensors]
    vacuous = np.zeros(size)
    vacuous[-1] = 1.0
    m = np.tile(vacuous, (B, 1))
    dead = np.zeros(B, dtype=bool)
    acc = np.zeros(B)
    bel = np.full((B, K1, n_classes), np.nan)
    pl = np.full((B, K1, n_classes), np.nan)
    conflict = np.full((B, K1), np.nan)
    accumulated = np.ones((B, K1))
    for k in range(K1):
        inputs = [tables[s][reports[:, k, s]] for s in range(S)]
        res = dempster_combine_array(m, *inputs, on_total_conflict="nan")
        newly = ~dead & ~np.isfinite(res.masses).all(axis=-1)
        live = ~dead & ~newly
        m = np.where(live[:, None], res.masses, vacuous)  # dead runs: a placeholder
        conflict[live, k] = res.conflict[live]
        conflict[newly, k] = 1.0
        acc = np.where(live, 1.0 - (1.0 - acc) * (1.0 - res.conflict), 1.0)
        accumulated[:, k] = acc
        dead |= newly
        if live.any():
            ml = m[live]
            for c in range(n_classes):
                bel[live, k, c] = belief_array(ml, 1 << c)
                pl[live, k, c] = plausibility_array(ml, 1 << c)
    return bel, pl, conflict, accumulated


def decision_weights(score: np.ndarray, tiebreak: np.ndarray | None = None) -> np.ndarray:
    """Weights (..., N) of the decided classes: 1/|T| on the tied maxima T of `score`, ties
    broken by `tiebreak` if given; all zero where `score` is not finite (no decision)."""
    ok = np.isfinite(score).all(axis=-1, keepdims=True)
    s = np.where(ok, score, 0.0)
    tied = s >= s.max(axis=-1, keepdims=True) - TIE_TOL
    if tiebreak is not None:
        t = np.where(tied & ok, tiebreak, -np.inf)
        tied &= t >= t.max(axis=-1, keepdims=True) - TIE_TOL
    w = tied / tied.sum(axis=-1, keepdims=True)
    return np.where(ok, w, 0.0)


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
    with Outputs([out], force=force) as outs, McapWriter(outs.open(out)) as w:
        w.add_metadata(SCENARIO_META, _metadata(scenario))
        w.add_metadata(PROVENANCE_META, provenance(command, scenario.seed))
        offsets = range(0, M, B)
        for off in progress(offsets, len(offsets), "simulate"):
            runs = min(B, M - off)
            truth, reports = simulate_identity(scenario, K, scenario.seed, off, runs)
            t = truth.astype(float)[:, None]
            r = reports.astype(float)
            for k in range(K + 1):
                w.write_values("/truth", k, float(times[k]), off, t)
                for s, topic in enumerate(topics):
                    w.write_values(topic, k, float(times[k]), off, r[:, k, s : s + 1])
            messages += (K + 1) * (1 + len(topics))
        w.close()
        outs.commit()
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
    columns = _columns(model.classes, archs)
    meta_prov = provenance(
        command,
        recorded.seed if recorded is not None else None,
        sensors_sha256=sha256_of(Path(sensors_path)),
        sensors_file=Path(sensors_path).name,
        model_source=model_source,
        model=json.dumps(model.to_dict()),
        architectures=json.dumps(archs),
        columns=json.dumps(columns),
    )
    outs = Outputs([out], force=force, inputs=[Path(sensors_path)])
    with outs, McapWriter(outs.open(out)) as w:
        if SCENARIO_META in mf.metadata:
            w.add_metadata(SCENARIO_META, mf.metadata[SCENARIO_META])
        w.add_metadata(PROVENANCE_META, meta_prov)
        blocks = mf.iter_run_blocks(topics, B)
        for off, _runs, data in progress(blocks, -(-M // B), "estimate"):
            try:
                reports = np.stack(
                    [
                        _indices(data[t][..., 0], len(s.reports), f"{t}", allow_nan=True)
                        for t, s in zip(topics, model.sensors, strict=True)
                    ],
                    axis=-1,
                )
            except ValueError as e:
                raise FusionlogError(f"{sensors_path}: runs from {off}: {e}") from None
            out_vals: dict[str, np.ndarray] = {}
            try:
                if "BAYES" in archs:
                    out_vals["BAYES"] = bayes_posteriors(reports, model.sensors, model.prior, off)
                if "DS" in archs:
                    bel, pl, kk, ka = ds_combine(reports, model.sensors, n)
                    out_vals["DS"] = np.concatenate([bel, pl, kk[..., None], ka[..., None]], -1)
            except ValueError as e:
                raise _library_error(sensors_path, e) from None
            for a in archs:
                topic = f"/estimates/{a}"
                vals = out_vals[a]
                for k in range(K + 1):
                    w.write_values(topic, k, float(times[k]), off, vals[:, k])
        w.close()
        outs.commit()
    return EstimateResult(Path(out), archs, M, K)


# --------------------------------------------------------------------------------------------
# evaluate
# --------------------------------------------------------------------------------------------


class _Sums:
    """Per-step sums over runs (and per-run averages for standard errors) of one metric."""

    def __init__(self, steps: int) -> None:
        self.sum = np.zeros(steps)
        self.count = np.zeros(steps)
        self.run_sum = 0.0
        self.run_sq = 0.0
        self.runs = 0

    def add(self, values: np.ndarray) -> None:
        """values (B, K+1), NaN where undefined (left out)."""
        ok = ~np.isnan(values)
        self.sum += np.where(ok, values, 0.0).sum(axis=0)
        self.count += ok.sum(axis=0)
        has = ok.any(axis=1)
        if has.any():
            with np.errstate(invalid="ignore"):
                per_run = np.where(ok, values, 0.0).sum(axis=1)[has] / ok.sum(axis=1)[has]
            self.run_sum += float(per_run.sum())
            self.run_sq += float((per_run * per_run).sum())
            self.runs += int(has.sum())

    def series(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 0, self.sum / np.maximum(self.count, 1), np.nan)

    def overall(self) -> float:
        s = self.series()
        s = s[~np.isnan(s)]
        return float(s.mean()) if s.size else math.nan

    def final(self) -> float:
        return float(self.series()[-1])

    def stderr(self) -> float:
        n = self.runs
        if n < 2 or not math.isfinite(self.run_sq):
            return math.nan
        mean = self.run_sum / n
        var = max(self.run_sq / n - mean * mean, 0.0) * n / (n - 1)
        return math.sqrt(var / n)


class _PerClass:
    """Per step and class c: mean over the runs whose truth is c of a score of class c."""

    def __init__(self, steps: int, n: int) -> None:
        self.sum = np.zeros((steps, n))
        self.count = np.zeros((steps, n))

    def add(self, truth: np.ndarray, scores: np.ndarray) -> None:
        own = np.take_along_axis(scores, truth[:, None, None], axis=-1)[..., 0]  # (B, K+1)
        ok = ~np.isnan(own)
        onehot = truth[:, None] == np.arange(scores.shape[-1])[None, :]  # (B, N)
        self.sum += np.einsum("bk,bn->kn", np.where(ok, own, 0.0), onehot)
        self.count += np.einsum("bk,bn->kn", ok.astype(float), onehot)

    def series(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 0, self.sum / np.maximum(self.count, 1), np.nan)


def _true(values: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """values (B, K+1, N) at each run's true class: (B, K+1)."""
    return np.take_along_axis(values, truth[:, None, None], axis=-1)[..., 0]


def _neg_log(p: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return -np.log(p)


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
    dims = _dims(n)
    archs = [a for a in ARCHITECTURES if f"/estimates/{a}" in est.topics]
    if not archs:
        have = ", ".join(sorted(est.topics)) or "none"
        raise FusionlogError(
            f"{estimates_path}: no /estimates/BAYES or /estimates/DS topics (topics: {have})"
        )
    topics = [f"/estimates/{a}" for a in archs]
    for a, t in zip(archs, topics, strict=True):
        if est.kind_of(t) != VALUES or est.dim_of(t) != dims[a]:
            raise FusionlogError(
                f"{estimates_path}: topic {t} is not an identity estimate "
                f"(fusionlog.Block with {dims[a]} values per run for {n} classes)"
            )
    K, M = sens.steps() - 1, sens.runs()
    times = sens.times()
    B = _block(K, M, n, block)
    metrics: dict[str, dict[str, _Sums]] = {}
    for a in archs:
        names = ["accuracy", "p_true", "log_loss"]
        if a == "DS":
            names += ["belief_true", "plausibility_true", "conflict", "accumulated_conflict"]
        metrics[a] = {k: _Sums(K + 1) for k in names}
    per_class = {
        (a, kind): _PerClass(K + 1, n)
        for a in archs
        for kind in (("probability",) if a == "BAYES" else ("belief", "plausibility"))
    }
    disagreement = _Sums(K + 1) if len(archs) == 2 else None
    total_conflict = 0
    n_samples = min(sc.sample_runs, M)
    samples: dict[int, tuple[int, dict[str, dict[str, np.ndarray]]]] = {}
    blocks = zip(sens.iter_run_blocks(["/truth"], B), est.iter_run_blocks(topics, B), strict=True)
    for (off, runs, tdata), (_, _, edata) in progress(blocks, -(-M // B), "evaluate"):
        try:
            truth = _indices(tdata["/truth"][:, 0, 0], n, "/truth", allow_nan=False)
        except ValueError as e:
            raise FusionlogError(f"{sensors_path}: runs from {off}: {e}") from None
        if (tdata["/truth"][..., 0] != tdata["/truth"][:, :1, 0]).any():
            raise FusionlogError(f"{sensors_path}: runs from {off}: the true class changes")
        weights: dict[str, np.ndarray] = {}
        for a, t in zip(archs, topics, strict=True):
            v = edata[t]
            mt = metrics[a]
            if a == "BAYES":
                p = v
                weights[a] = decision_weights(p)
                per_class[(a, "probability")].add(truth, p)
            else:
                bel, pl = v[..., :n], v[..., n : 2 * n]
                with np.errstate(invalid="ignore", divide="ignore"):
                    p = pl / pl.sum(axis=-1, keepdims=True)
                weights[a] = decision_weights(bel, tiebreak=pl)
                mt["belief_true"].add(_true(bel, truth))
                mt["plausibility_true"].add(_true(pl, truth))
                mt["conflict"].add(v[..., 2 * n])
                mt["accumulated_conflict"].add(v[..., 2 * n + 1])
                per_class[(a, "belief")].add(truth, bel)
                per_class[(a, "plausibility")].add(truth, pl)
                total_conflict += int(np.isnan(bel[:, -1]).any(axis=-1).sum())
            p_true = _true(p, truth)
            mt["accuracy"].add(_true(weights[a], truth))
            mt["p_true"].add(p_true)
            mt["log_loss"].add(_neg_log(p_true))
            for r in range(off, min(off + runs, n_samples)):
                entry = samples.setdefault(r, (int(truth[r - off]), {}))[1]
                if a == "BAYES":
                    entry[a] = {"probability": v[r - off]}
                else:
                    entry[a] = {"belief": bel[r - off], "plausibility": pl[r - off]}
        if disagreement is not None:
            disagreement.add(1.0 - (weights["BAYES"] * weights["DS"]).sum(axis=-1))

    arch_summary: dict[str, Any] = {}
    series: dict[str, dict[str, np.ndarray]] = {}
    for a in archs:
        mt = metrics[a]
        entry: dict[str, Any] = {
            "accuracy": mt["accuracy"].overall(),
            "log_loss": mt["log_loss"].overall(),
            "mean_p_true": mt["p_true"].overall(),
        }
        final: dict[str, Any] = {
            "accuracy": mt["accuracy"].final(),
            "log_loss": mt["log_loss"].final(),
            "mean_p_true": mt["p_true"].final(),
        }
        if a == "DS":
            entry["mean_belief_true"] = mt["belief_true"].overall()
            entry["mean_plausibility_true"] = mt["plausibility_true"].overall()
            entry["mean_conflict"] = mt["conflict"].overall()
            final["mean_belief_true"] = mt["belief_true"].final()
            final["mean_plausibility_true"] = mt["plausibility_true"].final()
            final["accumulated_conflict"] = mt["accumulated_conflict"].final()
            entry["total_conflict"] = total_conflict / M
        entry["final"] = final
        entry["stderr"] = {
            "accuracy": mt["accuracy"].stderr(),
            "log_loss": mt["log_loss"].stderr(),
            "mean_p_true": mt["p_true"].stderr(),
        }
        arch_summary[a] = entry
        series[a] = {k: s.series() for k, s in mt.items()}
        for (aa, kind), pc in per_class.items():
            if aa == a:
                series[a][kind] = pc.series()
    summary: dict[str, Any] = {
        "kind": KIND,
        "scenario": sc.name,
        "seed": sc.seed,
        "runs": M,
        "steps": K,
        "state_names": list(sc.classes),
        "architectures": arch_summary,
    }
    if disagreement is not None:
        summary["disagreement"] = disagreement.overall()
        summary["final_disagreement"] = disagreement.final()
    definitions = {
        "columns": json.dumps(_columns(sc.classes, archs)),
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
            series=series,
            disagreement=disagreement.series() if disagreement is not None else None,
            summary=summary,
            sample_runs=samples,
            properties={"scenario": sc.source, "provenance": prov, "identity": definitions},
            force=force,
        )
    except ValueError as e:  # pragma: no cover - inputs are built above
        raise FusionlogError(f"{out}: {e}") from None
    if summary_path is not None:
        write_json_atomic(summary_path, summary, force)
    return EvaluateResult(out, summary_path, summary)
