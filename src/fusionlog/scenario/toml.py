"""Reading TOML definitions: the helpers every scenario parser (state, identity, replay) shares.

Each helper checks one value and raises a one-line ValidationError
``<file>: <key path>: <reason>`` through :class:`Ctx`; key paths index arrays from 0
(``sensors[1].R`` is the second sensor's R). Matrices come back as float64; ``readonly`` makes
them read-only, ``covariance_checks`` symmetrises them.
"""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from typing import Any

import numpy as np

from fusionlog.core.linalg import definite
from fusionlog.errors import ValidationError
from fusionlog.inputs import check_input

#: Names that end up in MCAP topics, Rerun entity paths and folder names.
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")
_NAME_RULE = "letters, digits, '_', '.', '-', not starting with '.' or '-'"

#: Relative tolerance of the symmetry check: max|A - A^T| <= SYM_RTOL * max|A|.
SYM_RTOL = 1e-12


class Ctx:
    """Where errors are reported: the file (or source) name. `recorded`: the document is the
    record of a scenario that was validated when it was run (a sensors file's
    ``fusionlog.scenario``): it is rebuilt as written, its structure and types still checked
    (a damaged or foreign record is refused), but not the value checks it passed then
    (definiteness of its covariances, the schedule's budget), which cannot fail for it."""

    def __init__(self, file: str, recorded: bool = False) -> None:
        self.file = file
        self.recorded = recorded

    def err(self, where: str, reason: str) -> ValidationError:
        msg = f"{self.file}: {where}: {reason}"
        return ValidationError(" ".join(msg.split("\n")).replace("\r", " "))


def read_text(file: str) -> str:
    check_input(file)  # a FIFO or a device would block or never end
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


def parse_toml(text: str, file: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        msg = str(e)
        m = _TOML_POS.search(msg)
        where = m.group(1) if m else "TOML"
        reason = msg[: m.start()] if m else msg
        raise Ctx(file).err(where, f"invalid TOML: {reason}") from None


def tname(v: Any) -> str:
    if isinstance(v, bool):
        return f"boolean {str(v).lower()}"
    if isinstance(v, int):
        return f"integer {v}"
    if isinstance(v, float):
        return f"float {fmt(v)}"
    if isinstance(v, str):
        return f"string {show(v)}"
    if isinstance(v, list):
        return "an array"
    if isinstance(v, dict):
        return "a table"
    return type(v).__name__


def show(v: Any, limit: int = 60) -> str:
    s = repr(v)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def fmt(x: float) -> str:
    return f"{x:.6g}"


def shape(A: np.ndarray) -> str:
    return "x".join(str(d) for d in A.shape)


def is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def readonly(A: np.ndarray) -> np.ndarray:
    A = np.array(A, dtype=float)
    A.flags.writeable = False
    return A


def tolist(A: np.ndarray) -> list:
    return np.asarray(A, dtype=float).tolist()


def check_keys(
    ctx: Ctx,
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


def table(ctx: Ctx, doc: dict[str, Any], key: str, *, required: bool) -> dict[str, Any] | None:
    if key not in doc:
        if required:
            raise ctx.err(key, f"missing required section [{key}]")
        return None
    t = doc[key]
    if not isinstance(t, dict):
        raise ctx.err(key, f"expected a table ([{key}]), got {tname(t)}")
    return t


def string(ctx: Ctx, v: Any, where: str) -> str:
    if not isinstance(v, str):
        raise ctx.err(where, f"expected a string, got {tname(v)}")
    return v


def name(ctx: Ctx, v: Any, where: str) -> str:
    s = string(ctx, v, where)
    if not _NAME_RE.match(s):
        raise ctx.err(where, f"invalid name {show(s)} (use {_NAME_RULE})")
    return s


def names_list(ctx: Ctx, v: Any, where: str) -> tuple[str, ...]:
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a list of names, got {tname(v)}")
    if not v:
        raise ctx.err(where, "empty: name every state")
    out = tuple(name(ctx, s, f"{where}[{i}]") for i, s in enumerate(v))
    for i, s in enumerate(out):
        if s in out[:i]:
            raise ctx.err(f"{where}[{i}]", f"duplicate name {s!r}")
    return out


def integer(ctx: Ctx, v: Any, where: str, *, minimum: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int | np.integer):
        integral = isinstance(v, float) and v.is_integer() and abs(v) < 2**63
        hint = f" (write {int(v)})" if integral else ""
        raise ctx.err(where, f"expected an integer, got {tname(v)}{hint}")
    v = int(v)
    if v < minimum:
        raise ctx.err(where, f"must be >= {minimum}, got {v}")
    return v


def number(ctx: Ctx, v: Any, where: str) -> float:
    if not is_number(v) and not isinstance(v, np.floating | np.integer):
        raise ctx.err(where, f"expected a number, got {tname(v)}")
    x = float(v)
    if not math.isfinite(x):
        raise ctx.err(where, f"not finite ({x})")
    return x


def matrix(ctx: Ctx, v: Any, where: str, *, scalar: bool = False, row: bool = False) -> np.ndarray:
    """A 2-D float matrix from a list of rows; a number is 1x1 if `scalar`, a flat list one row
    if `row`. Elements must be finite numbers."""
    example = "a list of rows, e.g. [[1.0, 0.0], [0.0, 1.0]]"
    if is_number(v):
        if not scalar:
            raise ctx.err(where, f"expected a matrix ({example}), got a number")
        return np.array([[number(ctx, v, where)]])
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a matrix ({example}), got {tname(v)}")
    if not v:
        raise ctx.err(where, "empty matrix")
    if all(is_number(x) for x in v):
        if not row:
            raise ctx.err(where, f"expected a matrix ({example}), got a flat list")
        return np.array([[number(ctx, x, f"{where}[{j}]") for j, x in enumerate(v)]])
    rows: list[list[float]] = []
    for i, r in enumerate(v):
        if not isinstance(r, list):
            raise ctx.err(f"{where}[{i}]", f"expected a row (a list of numbers), got {tname(r)}")
        if not r:
            raise ctx.err(f"{where}[{i}]", "empty row")
        if len(r) != len(v[0]):
            raise ctx.err(
                where, f"rows have different lengths (row 0 has {len(v[0])}, row {i} has {len(r)})"
            )
        rows.append([number(ctx, x, f"{where}[{i}][{j}]") for j, x in enumerate(r)])
    return np.array(rows, dtype=float)


def vector(ctx: Ctx, v: Any, where: str, n: int, why: str = "the number of states") -> np.ndarray:
    if is_number(v) and n == 1:
        return readonly(np.array([number(ctx, v, where)]))
    if not isinstance(v, list):
        raise ctx.err(where, f"expected a list of {n} numbers, got {tname(v)}")
    x = np.array([number(ctx, e, f"{where}[{i}]") for i, e in enumerate(v)])
    if x.shape != (n,):
        raise ctx.err(where, f"length {x.size}, expected {n} ({why})")
    return readonly(x)


def covariance(ctx: Ctx, v: Any, where: str, n: int, *, strict: bool) -> np.ndarray:
    A = matrix(ctx, v, where, scalar=n == 1)
    if A.shape != (n, n):
        raise ctx.err(where, f"shape {shape(A)}, expected {n}x{n} (n x n)")
    return covariance_checks(ctx, A, where, strict=strict)


def covariance_checks(ctx: Ctx, A: np.ndarray, where: str, *, strict: bool) -> np.ndarray:
    """Symmetry (relative tolerance) and positive (semi)definiteness; returns the symmetrised,
    read-only matrix."""
    label = where.rsplit(".", 1)[-1]
    asym = float(np.max(np.abs(A - A.T)))
    if asym > SYM_RTOL * float(np.max(np.abs(A))):
        raise ctx.err(where, f"not symmetric (max |{label} - {label}^T| = {asym:.3g})")
    A = 0.5 * A + 0.5 * A.T  # not (A + A^T) / 2: entries near 1e308 would overflow
    why = None if ctx.recorded else not_definite(A, strict=strict)
    if why is not None:
        kind = "positive definite" if strict else "positive semidefinite"
        raise ctx.err(where, f"not {kind} {why}")
    return readonly(A)


def not_definite(A: np.ndarray, *, strict: bool) -> str | None:
    """None when A is positive (semi)definite to working precision (`core.linalg.definite`,
    which does not depend on units), else why not: "(smallest eigenvalue ...)"."""
    if definite(A, strict=strict):
        return None
    lo = float(np.linalg.eigvalsh(0.5 * A + 0.5 * A.T)[0])
    if lo > 0:  # singular only on the scale of its own variances
        return f"(smallest eigenvalue {fmt(lo)}: singular to working precision for its variances)"
    return f"(smallest eigenvalue {fmt(lo)})"


def unknown_msg(what: str, name: str, known: list[str] | tuple[str, ...]) -> str:
    """'unknown <what> <name> (known: ...); did you mean ...?'"""
    hint = difflib.get_close_matches(name, list(known), n=1)
    mean = f"; did you mean {hint[0]!r}?" if hint else ""
    return f"unknown {what} {show(name)} (known: {', '.join(known)}){mean}"


def architectures(
    ctx: Ctx,
    doc: dict[str, Any],
    default: tuple[str, ...],
    check: Any,
    other_keys: tuple[str, ...] = (),
) -> tuple[str, ...]:
    """``[estimate] architectures``: a non-empty list of distinct names, each accepted by
    ``check(name)`` (which raises ValueError with the reason); `default` when absent.
    `other_keys`: the section's other keys the caller validates (a state's filter, ukf)."""
    est = table(ctx, doc, "estimate", required=False)
    if est is None:
        return default
    check_keys(ctx, est, "estimate", ("architectures", *other_keys))
    if "architectures" not in est:
        return default
    archs = est["architectures"]
    if not isinstance(archs, list):
        raise ctx.err("estimate.architectures", f"expected a list of names, got {tname(archs)}")
    if not archs:
        raise ctx.err("estimate.architectures", "empty: name at least one architecture")
    out: list[str] = []
    for i, a in enumerate(archs):
        where = f"estimate.architectures[{i}]"
        a = string(ctx, a, where)
        try:
            check(a)
        except ValueError as e:
            raise ctx.err(where, str(e)) from None
        if a in out:
            raise ctx.err(where, f"duplicate architecture {a!r}")
        out.append(a)
    return tuple(out)


def named_tables(
    ctx: Ctx,
    doc: dict[str, Any],
    key: str,
    keys: tuple[str, ...],
    missing: str,
    optional: tuple[str, ...] = (),
) -> list[tuple[str, dict[str, Any], str]]:
    """A required, non-empty array of tables ``[[key]]`` with the given (required) keys, the
    `optional` ones, and distinct ``name`` values: (key path, table, name) of each. `missing`
    ends the message when the array is absent (what to give)."""
    if key not in doc:
        raise ctx.err(key, f"missing: give at least one [[{key}]] table{missing}")
    items = doc[key]
    if isinstance(items, dict):
        raise ctx.err(key, f"expected an array of tables ([[{key}]]), got one table")
    if not isinstance(items, list) or not all(isinstance(t, dict) for t in items):
        raise ctx.err(key, f"expected an array of tables ([[{key}]]), got {tname(items)}")
    if not items:
        raise ctx.err(key, "empty: give at least one sensor")
    out: list[tuple[str, dict[str, Any], str]] = []
    seen: dict[str, int] = {}
    for j, t in enumerate(items):
        where = f"{key}[{j}]"
        check_keys(ctx, t, where, keys + optional, required=keys)
        nm = name(ctx, t["name"], f"{where}.name")
        if nm in seen:
            raise ctx.err(f"{where}.name", f"duplicate sensor name {nm!r} (also {key}[{seen[nm]}])")
        seen[nm] = j
        out.append((where, t, nm))
    return out
