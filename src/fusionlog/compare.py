"""summary.json checked against its schema and compared with a golden file (`fusionlog
compare`).

A summary.json is strict JSON: a non-finite metric is null and listed in the top-level
``non_finite`` note (`fusionlog.jsonout`). The comparison reads the noted values back as floats
(shown "inf", "nan"), so Infinity in both files is equal.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from fusionlog.errors import FusionlogError
from fusionlog.inputs import check_input
from fusionlog.jsonout import NON_FINITE, join_path, resolve_non_finite, to_strict_json

__all__ = ["check_summary", "check_tolerance", "compare_summaries", "load_json"]


# ----------------------------------------------------------------------------------- checking
#: Per-architecture metrics that are one number (DESIGN.md, summary.json; identity ones too).
_ARCH_NUMBERS = frozenset(
    {
        "mse",
        "mean_trace",
        "anees",
        "nees_fraction_inside",
        "dm",
        "excluded",
        "accuracy",
        "log_loss",
        "mean_p_true",
        "mean_belief_true",
        "mean_plausibility_true",
        "mean_conflict",
        "total_conflict",
    }
)

#: Per-architecture groups of metrics: key -> (container, whether a leaf may be null, levels
#: of nesting inside). Only `expected` may hold null: "no exact analysis" (unknown model,
#: per-run patterns). `nis` is one object, or one per sensor where there are several.
_ARCH_GROUPS: dict[str, tuple[type, bool, int]] = {
    "mse_per_state": (list, False, 0),
    "expected": (dict, True, 0),
    "stderr": (dict, False, 0),
    "final": (dict, False, 0),
    "nis": (dict, False, 1),
}

_TOP_NUMBERS = frozenset(
    {"seed", "runs", "steps", "confidence", "disagreement", "final_disagreement"}
)
_TOP_STRINGS = frozenset({"scenario", "kind"})


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _describe(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return f"a boolean ({'true' if v else 'false'})"
    if isinstance(v, str):
        return f"a string ({v[:40]!r})"
    if isinstance(v, Mapping):
        return "an object"
    if isinstance(v, list | tuple):
        return "a list"
    if isinstance(v, float) or (isinstance(v, int) and abs(v).bit_length() <= 64):
        return f"a number ({v!r})"
    return f"a {type(v).__name__}"


def _want_number(v: Any, path: str, nullable: bool) -> None:
    if _is_number(v) or (v is None and nullable):
        return
    hint = f" (a non-finite value is null listed in {NON_FINITE})" if v is None else ""
    raise ValueError(f"{path}: {_describe(v)} where a number is expected{hint}")


def _want_numbers(v: Any, path: str, nullable: bool, nesting: int) -> None:
    """A metric group: an object or list of numbers, containers `nesting` levels deep inside."""
    items = v.items() if isinstance(v, Mapping) else enumerate(v)
    for k, x in items:
        sub = join_path(path, k if isinstance(k, int) else str(k))
        if nesting > 0 and isinstance(x, Mapping | list | tuple):
            _want_numbers(x, sub, nullable, nesting - 1)
        else:
            _want_number(x, sub, nullable)


def _leaves(v: Any, path: str = ""):
    """(key path, leaf) of every non-container value; nesting already bounded."""
    if isinstance(v, Mapping):
        for k, x in v.items():
            yield from _leaves(x, join_path(path, str(k)))
    elif isinstance(v, list | tuple):
        for i, x in enumerate(v):
            yield from _leaves(x, join_path(path, i))
    else:
        yield path, v


def check_summary(doc: Any, *, strict: bool = False) -> dict[str, Any]:
    """`doc` checked as a summary.json and with its noted non-finite values put back as floats.

    Raises ValueError("<key path>: <problem>") for: nesting deeper than MAX_DEPTH; a number too
    large for a double (a 400-digit integer); with ``strict`` (a file's contents), a non-finite
    number (JSON has no NaN/Infinity: it must be null and listed in ``non_finite``); a malformed
    ``non_finite`` note; and where the schema (DESIGN.md) wants a number, anything else -- a
    string, a boolean, a list, an object, or null outside ``expected`` (null there means "no
    exact analysis") that no note explains. ``expected`` itself may be null only beside a
    top-level ``pcrb`` (a nonlinear model's summary, DESIGN.md). Keys the schema does not know
    are not checked.
    Without ``strict``, non-finite floats (an in-memory summary) are accepted as values.
    """
    if not isinstance(doc, Mapping):
        raise ValueError(f"not a summary: {_describe(doc)}, not an object")
    _, raw = to_strict_json(doc)  # also bounds the nesting for the walks below
    if strict and raw:
        path, token = next(iter(raw.items()))
        raise ValueError(f"{path}: {token} is not JSON (strict JSON: null, listed in {NON_FINITE})")
    for path, v in _leaves(doc):
        if isinstance(v, int) and not isinstance(v, bool) and abs(v).bit_length() > 1024:
            raise ValueError(f"{path}: a number too large for a double ({_describe_int(v)})")
    out = resolve_non_finite(doc, check=True)
    for key, v in out.items():
        if key in _TOP_NUMBERS:
            _want_number(v, key, nullable=False)
        elif key in _TOP_STRINGS and not isinstance(v, str):
            raise ValueError(f"{key}: {_describe(v)} where a string is expected")
        elif key == "state_names" and (
            not isinstance(v, list | tuple) or not all(isinstance(x, str) for x in v)
        ):
            raise ValueError(f"{key}: {_describe(v)} where a list of strings is expected")
    _check_architectures(out, "architectures")
    if out.get("kind") == "sweep":  # a sweep's architectures are its grid points'
        points = out.get("points")
        if not isinstance(points, list | tuple):
            raise ValueError(f"points: {_describe(points)} where a list of grid points is expected")
        for i, p in enumerate(points):
            if not isinstance(p, Mapping):
                raise ValueError(f"points[{i}]: {_describe(p)} where an object is expected")
            _check_architectures(p, f"points[{i}].architectures")
    return out


def _check_architectures(doc: Mapping[str, Any], at: str) -> None:
    archs = doc.get("architectures", {})
    if not isinstance(archs, Mapping):
        raise ValueError(f"{at}: {_describe(archs)} where an object is expected")
    for arch, entry in archs.items():
        where = join_path(at, str(arch))
        if not isinstance(entry, Mapping):
            raise ValueError(f"{where}: {_describe(entry)} where an object of metrics is expected")
        for key, v in entry.items():
            path = join_path(where, str(key))
            if key in _ARCH_NUMBERS:
                _want_number(v, path, nullable=False)
            elif key == "expected" and v is None and "pcrb" in doc:
                continue  # a nonlinear model: no exact analysis, the PCRB stands instead
            elif key in _ARCH_GROUPS:
                container, nullable, nesting = _ARCH_GROUPS[key]
                if not isinstance(v, list | tuple if container is list else Mapping):
                    kind = "a list" if container is list else "an object"
                    raise ValueError(f"{path}: {_describe(v)} where {kind} of numbers is expected")
                if key == "expected":  # per-run patterns: "conditional": true says so (DESIGN)
                    v = {k: x for k, x in v.items() if not _flag(k, x)}
                _want_numbers(v, path, nullable, nesting)


def _flag(key: str, v: Any) -> bool:
    """`expected`'s ``conditional`` flag: a boolean beside the numbers, not a metric."""
    return key == "conditional" and isinstance(v, bool)


def _describe_int(v: int) -> str:
    return f"about {int(abs(v).bit_length() * math.log10(2)) + 1} digits"


# ----------------------------------------------------------------------------------- comparison
def _show(v: Any) -> str:
    if _is_number(v):
        return f"{v:.10g}"
    return repr(v)


def _compare(actual: Any, golden: Any, where: str, rtol: float, atol: float, out: list[str]):
    if isinstance(golden, Mapping) and isinstance(actual, Mapping):
        for key in golden:
            sub = join_path(where, str(key))
            if key not in actual:
                out.append(f"{sub}: missing (golden {_show_short(golden[key])})")
            else:
                _compare(actual[key], golden[key], sub, rtol, atol, out)
        for key in actual:
            if key not in golden:
                sub = join_path(where, str(key))
                out.append(f"{sub}: extra (actual {_show_short(actual[key])}, not in golden)")
        return
    if isinstance(golden, list | tuple) and isinstance(actual, list | tuple):
        if len(golden) != len(actual):
            out.append(f"{where}: length {len(actual)}, golden {len(golden)}")
            return
        for i, (a, g) in enumerate(zip(actual, golden, strict=True)):
            _compare(a, g, join_path(where, i), rtol, atol, out)
        return
    if _is_number(golden) and _is_number(actual):
        a, g = float(actual), float(golden)
        if math.isnan(a) and math.isnan(g):
            return
        # Infinity equals only Infinity: with a tolerance, rtol * inf would accept any value.
        if a == g or (math.isfinite(a) and math.isfinite(g) and abs(a - g) <= atol + rtol * abs(g)):
            return
        rel = abs(a - g) / abs(g) if g != 0 and math.isfinite(g) else math.inf
        out.append(f"{where}: actual {_show(actual)}, golden {_show(golden)} (rel. diff {rel:.3g})")
        return
    if actual != golden:
        out.append(f"{where}: actual {_show(actual)}, golden {_show(golden)}")


def _show_short(v: Any) -> str:
    if isinstance(v, Mapping):
        return "{...}"
    if isinstance(v, list | tuple):
        return f"[{len(v)} items]"
    return _show(v)


def check_tolerance(value: float, name: str) -> float:
    """A tolerance must be a finite number >= 0 (ValueError otherwise)."""
    if not _is_number(value) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return float(value)


def compare_summaries(
    actual: Mapping[str, Any],
    golden: Mapping[str, Any],
    rtol: float = 1e-6,
    atol: float = 1e-12,
) -> list[str]:
    """Differences between two summary dicts, one human-readable line each; [] means they agree.

    A number passes when |actual - golden| <= atol + rtol * |golden| (both finite), or when
    both are the same infinity or both NaN; null equals null; other leaves must be equal.
    Values listed in a ``non_finite`` note are compared as the floats they stand for. Lines
    name the architecture and the metric, e.g.
    ``CKF: mse: actual 0.1012, golden 0.101 (rel. diff 0.00198)``; missing or extra
    architectures and keys are reported too.

    Raises ValueError for a negative or non-finite tolerance, and for a malformed summary
    (see :func:`check_summary`; the message starts with "actual: " or "golden: ").
    """
    rtol, atol = check_tolerance(rtol, "rtol"), check_tolerance(atol, "atol")
    docs = []
    for side, doc in (("actual", actual), ("golden", golden)):
        try:
            docs.append(check_summary(doc))
        except ValueError as e:
            raise ValueError(f"{side}: {e}") from None
    actual, golden = docs
    out: list[str] = []
    a_arch = actual.get("architectures", {})
    g_arch = golden.get("architectures", {})
    top_a = {k: v for k, v in actual.items() if k != "architectures"}
    top_g = {k: v for k, v in golden.items() if k != "architectures"}
    _compare(top_a, top_g, "", rtol, atol, out)
    if ("architectures" in actual) != ("architectures" in golden):
        side = "actual" if "architectures" not in actual else "golden"
        out.append(f"architectures: missing in {side}")
    for arch in g_arch:
        if arch not in a_arch:
            out.append(f"{arch}: architecture missing (in golden, not in actual)")
        else:
            sub: list[str] = []
            _compare(a_arch[arch], g_arch[arch], "", rtol, atol, sub)
            out += [f"{arch}: {line}" for line in sub]
    for arch in a_arch:
        if arch not in g_arch:
            out.append(f"{arch}: architecture extra (in actual, not in golden)")
    return out


def load_json(path: Path) -> Any:
    """A JSON file for `fusionlog compare`; every way it can fail is one FusionlogError line."""
    check_input(path)  # a FIFO or a device would block or never end
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as e:
        raise FusionlogError(f"{path}: no such file") from e
    except (OSError, UnicodeDecodeError) as e:
        raise FusionlogError(f"{path}: cannot read ({e})") from e
    except json.JSONDecodeError as e:
        raise FusionlogError(f"{path}: not valid JSON (line {e.lineno}: {e.msg})") from e
    except RecursionError:
        raise FusionlogError(f"{path}: nested too deeply to be a summary") from None
    except ValueError as e:  # Python refuses integers of more than 4300 digits
        raise FusionlogError(f"{path}: cannot read a number ({str(e).split(';')[0]})") from None
