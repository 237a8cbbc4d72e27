"""Scenario definitions (pipeline/*.toml, DESIGN.md "Scenario TOML"): loading and validation.

A parsed document is sniffed once (:func:`doc_kind`: ``identity``, ``replay`` or ``state``)
and handed to its kind's parser; each kind is a class of its own (:mod:`.scenario_base`:
``StateScenario``, ``NonlinearScenario``, ``ReplayScenario``, ``IdentityScenario``) that owns
its checks. The parsers sit side by side in :mod:`.state_file`, :mod:`.replay_file` and
:mod:`.identity_file`, on the shared helpers of :mod:`.toml`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from fusionlog.errors import FusionlogError

from . import toml
from .identity_file import (
    IdentityScenario,
    check_identity_architectures,
    identity_from_doc,
    is_identity_doc,
)
from .replay_file import Replay, ReplayScenario, Stream, is_replay_doc, replay_from_doc
from .scenario_base import KINDS, Scenario, check_budget, scenario_with
from .state_file import (
    MODEL_KINDS,
    NonlinearScenario,
    StateScenario,
    model_from_doc,
    state_from_doc,
    system_from_dict,
    system_to_dict,
)

__all__ = [
    "KINDS",
    "IdentityScenario",
    "NonlinearScenario",
    "Replay",
    "ReplayScenario",
    "Stream",
    "MODEL_KINDS",
    "Scenario",
    "StateScenario",
    "check_budget",
    "check_identity_architectures",
    "doc_kind",
    "is_replay_text",
    "kind_of_text",
    "load_model",
    "load_scenario",
    "model_from_text",
    "scenario_from_doc",
    "scenario_from_metadata",
    "scenario_from_text",
    "scenario_with",
    "system_from_dict",
    "system_to_dict",
]


#: A document's kind to its parser (doc, file, text, path) -> Scenario.
_PARSERS = {"identity": identity_from_doc, "replay": replay_from_doc, "state": state_from_doc}


def doc_kind(doc: Mapping[str, Any]) -> str:
    """What a parsed scenario or model document is: ``identity`` (it has [identity] or
    [[identity_sensors]]), ``replay`` (a sensor names a recorded `source`) or ``state``: the one
    place a document is sniffed."""
    if is_identity_doc(doc):
        return "identity"
    return "replay" if is_replay_doc(doc) else "state"


def _recorded_kind(kind: str) -> str:
    """The kind the files record of a document kind (a replay is a state scenario)."""
    return "identity" if kind == "identity" else "state"


def _from_text(text: str, file: str, path: str | None) -> Scenario:
    return scenario_from_doc(toml.parse_toml(text, file), file, text, path)


def scenario_from_doc(
    doc: dict[str, Any], file: str, text: str = "", path: str | None = None
) -> Scenario:
    """Validate a scenario of either kind from a parsed TOML document: the one validation path
    of files, texts and documents edited after parsing (a sweep's grid points). `file` names
    it in errors, `text` is the TOML as written (recorded in outputs), `path` its file."""
    return _PARSERS[doc_kind(doc)](doc, file, text, path)


def load_scenario(
    path: str | os.PathLike[str],
    *,
    runs: int | None = None,
    steps: int | None = None,
    seed: int | None = None,
) -> Scenario:
    """Read and validate a scenario file of either kind; `runs`, `steps`, `seed` override it.
    A replay file has none of them (one recorded run on its measurement times): an override
    is refused rather than silently ignored."""
    file = os.fspath(path)
    scenario = _from_text(toml.read_text(file), file, file)
    given = [
        f for f, v in (("--runs", runs), ("--steps", steps), ("--seed", seed)) if v is not None
    ]
    scenario.check_overrides(file, given)  # a replay's: refused, never ignored
    return scenario_with(scenario, runs=runs, steps=steps, seed=seed)


def scenario_from_text(text: str, source: str = "<string>") -> Scenario:
    """Validate a scenario given as TOML text; `source` names it in error messages."""
    return _from_text(text, source, None)


def kind_of_text(text: str, source: str = "<string>") -> str:
    """The kind of a scenario or model file's text (``state`` unless it has [identity])."""
    return _recorded_kind(doc_kind(toml.parse_toml(text, source)))


def is_replay_text(text: str, source: str = "<string>") -> bool:
    """Whether a scenario's TOML text (as a file's ``fusionlog.scenario`` record keeps it) is
    a replay file (its sensors name a `source`): one recorded run, no seed."""
    return doc_kind(toml.parse_toml(text, source)) == "replay"


def load_model(
    path: str | os.PathLike[str], kind: str | None = None, dt: float | None = None
) -> Any:
    """The filter model of ``estimate --model``: a state System, or for the identity kind an
    identity Scenario (classes, prior, sensors). ``kind`` defaults to the file's own; ``dt``
    (the recorded scenario's) stands for a missing ``scenario.dt`` of a state model."""
    file = os.fspath(path)
    return model_from_text(toml.read_text(file), file, kind, dt)


def _a(word: str) -> str:
    return f"{'an' if word[:1] in 'aeiou' else 'a'} {word}"


def model_from_text(
    text: str, source: str = "<string>", kind: str | None = None, dt: float | None = None
) -> Any:
    """Validate a model given as TOML text (see :func:`load_model`)."""
    doc = toml.parse_toml(text, source)
    own = doc_kind(doc)
    if own == "replay":  # its sensors' R may come from the recorded messages alone
        raise FusionlogError(
            f"{source}: a replay file, not a filter model (give --model a scenario or model "
            "file; `fusionlog run` replays the recorded data with this file's model)"
        )
    head = doc.get("scenario", {})
    if dt is not None and isinstance(head, dict) and "dt" not in head:
        # a model file need not repeat [scenario] (docs/reference/scenario.md): n0 * dt is
        # the recorded dt's
        doc = {**doc, "scenario": {**head, "dt": dt}}
    if kind is not None and own != kind:
        what = "no [identity] section" if own == "state" else "it has [identity]"
        raise FusionlogError(
            f"{source}: {_a(own)} model ({what}), but the sensors file holds {_a(kind)} scenario"
        )
    if own == "identity":
        return identity_from_doc(doc, source, text, source, model=True)
    return model_from_doc(doc, source)


def scenario_from_metadata(meta: Mapping[str, str], source: str) -> Scenario:
    """The scenario recorded in a sensors file's ``fusionlog.scenario`` record, with the runs,
    steps and seed it was run with. Its kind is the record's ``kind`` (files written before the
    field existed are state files unless their TOML has [identity])."""
    try:
        text = meta["toml"]
        doc = toml.parse_toml(text, source)
        own = doc_kind(doc)
        kind = meta.get("kind") or _recorded_kind(own)
        if kind not in KINDS:
            raise ValueError(f"unknown kind {kind!r}")
        # validated when it ran: rebuilt as recorded, without the value checks (`toml.Ctx`)
        sc = _PARSERS[own](doc, source, text, None, recorded=True)
        if own == "replay":
            sc = _with_recorded_R(sc, meta, source)
        if sc.kind != kind:
            raise ValueError(f"kind {kind!r} but the TOML is a {sc.kind} scenario")
        runs, steps, seed = (int(meta[k]) for k in ("runs", "steps", "seed"))
        return scenario_with(sc, runs=runs, steps=steps, seed=seed, recorded=True)
    except (KeyError, ValueError, TypeError) as e:
        raise FusionlogError(f"{source}: unreadable ({e})") from e


def _with_recorded_R(sc: Scenario, meta: Mapping[str, str], source: str) -> Scenario:
    """A replay's sensor given by its messages' covariances alone has no R in the file; the
    import recorded the nominal R it took (their mean) in the resolved system: use it."""
    import dataclasses
    import json

    import numpy as np

    if all(np.isfinite(s.R).all() for s in sc.system.sensors) or "system" not in meta:
        return sc
    recorded = system_from_dict(json.loads(meta["system"]), source)
    by_name = {s.name: s.R for s in recorded.sensors}
    sensors = tuple(
        s if np.isfinite(s.R).all() else dataclasses.replace(s, R=by_name[s.name])
        for s in sc.system.sensors
    )
    return dataclasses.replace(sc, system=dataclasses.replace(sc.system, sensors=sensors))
