"""Strict JSON out (DESIGN.md: "All JSON written is strict JSON (no NaN/Infinity)").

RFC 8259 has no NaN or Infinity, and other languages' parsers reject Python's ``NaN`` /
``Infinity`` extensions. Yet some metrics are legitimately non-finite: an identity log-loss is
+inf when a reliable sensor ruled the true class out, a metric with no defined step is NaN.
Every JSON document we write therefore goes through :func:`dumps`, which

* replaces each non-finite float by ``null`` and, when the document is an object, records what
  it was in a top-level note ``"non_finite": {"architectures.DS.log_loss": "Infinity", ...}``
  (key paths as :func:`join_path` spells them: object keys joined by ".", list items "[i]";
  values "Infinity", "-Infinity" or "NaN");
* serialises with ``allow_nan=False``, so a non-finite value that slipped past the replacement
  raises instead of producing non-JSON.

:func:`resolve_non_finite` is the inverse for readers (``compare``, the summary table): it puts
the noted values back where the note says and drops the note.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

__all__ = [
    "MAX_DEPTH",
    "NON_FINITE",
    "TOKENS",
    "dumps",
    "join_path",
    "resolve_non_finite",
    "to_strict_json",
    "token_of",
]

#: The top-level key of the note listing the non-finite values replaced by null.
NON_FINITE = "non_finite"

#: How a non-finite value is named in the note, and the float each name stands for.
TOKENS: dict[str, float] = {"Infinity": math.inf, "-Infinity": -math.inf, "NaN": math.nan}

#: Deepest nesting walked. A summary is 4 levels deep; the bound turns a pathological document
#: (a 100,000-deep array) into a ValueError instead of a RecursionError.
MAX_DEPTH = 64


def join_path(prefix: str, key: str | int) -> str:
    """``architectures`` + ``DS`` -> ``architectures.DS``; ``mse_per_state`` + 1 ->
    ``mse_per_state[1]``. The spelling of key paths in notes, errors and diff lines."""
    if isinstance(key, int):
        return f"{prefix}[{key}]"
    return f"{prefix}.{key}" if prefix else str(key)


def token_of(v: float) -> str:
    """The note's name of a non-finite float: "Infinity", "-Infinity" or "NaN"."""
    if math.isnan(v):
        return "NaN"
    return "Infinity" if v > 0 else "-Infinity"


def _too_deep(path: str) -> ValueError:
    return ValueError(f"{path or 'the document'}: nested more than {MAX_DEPTH} levels deep")


def to_strict_json(obj: Any) -> tuple[Any, dict[str, str]]:
    """(a copy of `obj` with every non-finite float replaced by None, {key path: token}).

    Mappings (keys made str, as json does) and lists/tuples are copied; other values are kept
    as they are. Raises ValueError for nesting deeper than MAX_DEPTH.
    """
    notes: dict[str, str] = {}

    def walk(v: Any, path: str, depth: int) -> Any:
        if isinstance(v, float):
            if math.isfinite(v):
                return v
            notes[path] = token_of(v)
            return None
        if depth >= MAX_DEPTH and isinstance(v, Mapping | list | tuple):
            raise _too_deep(path)
        if isinstance(v, Mapping):
            return {str(k): walk(x, join_path(path, str(k)), depth + 1) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [walk(x, join_path(path, i), depth + 1) for i, x in enumerate(v)]
        return v

    return walk(obj, "", 0), notes


def dumps(obj: Any, **kwargs: Any) -> str:
    """Strict JSON text of `obj` (keyword arguments as for json.dumps, except allow_nan).

    Non-finite floats become null; if `obj` is a mapping, they are listed in its top-level
    ``non_finite`` note (merged with a note it already has, placed last). A non-finite value
    in a document that is not an object has no place for a note and is just null.
    """
    clean, notes = to_strict_json(obj)
    if notes and isinstance(clean, dict):
        old = clean.pop(NON_FINITE, None)
        clean[NON_FINITE] = {**(old if isinstance(old, dict) else {}), **notes}
    return json.dumps(clean, allow_nan=False, **kwargs)


def resolve_non_finite(doc: Any, *, check: bool = True) -> Any:
    """`doc` with the values its ``non_finite`` note lists put back as floats, note removed.

    With ``check`` a malformed note raises ValueError naming the entry: not an object, a value
    other than "Infinity"/"-Infinity"/"NaN", or a key path that is not a null in `doc`.
    Without it, such entries are ignored (for display). Anything but a mapping with a note is
    returned as it is.
    """
    if not isinstance(doc, Mapping) or NON_FINITE not in doc:
        return doc
    note = doc[NON_FINITE]
    if not isinstance(note, Mapping):
        if check:
            raise ValueError(f"{NON_FINITE}: must be an object of key path -> 'Infinity', ...")
        note = {}
    wanted: dict[str, float] = {}
    for key, token in note.items():
        if isinstance(token, str) and token in TOKENS:
            wanted[str(key)] = TOKENS[token]
        elif check:
            raise ValueError(
                f"{join_path(NON_FINITE, str(key))}: {token!r} is not one of "
                f"{', '.join(map(repr, TOKENS))}"
            )
    used: set[str] = set()

    def walk(v: Any, path: str, depth: int) -> Any:
        if v is None and path in wanted:
            used.add(path)
            return wanted[path]
        if depth >= MAX_DEPTH and isinstance(v, Mapping | list | tuple):
            raise _too_deep(path)
        if isinstance(v, Mapping):
            return {k: walk(x, join_path(path, str(k)), depth + 1) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [walk(x, join_path(path, i), depth + 1) for i, x in enumerate(v)]
        return v

    out = {k: walk(v, join_path("", str(k)), 1) for k, v in doc.items() if k != NON_FINITE}
    if check and (unused := [k for k in wanted if k not in used]):
        raise ValueError(f"{join_path(NON_FINITE, unused[0])}: names no null value in the file")
    return out
