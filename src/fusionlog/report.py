"""Plain-text reports: the Table I/II-style summary table and the golden-file comparison.

A summary.json is strict JSON: a non-finite metric is null and listed in the top-level
``non_finite`` note (`fusionlog.jsonout`). Both the table and the comparison read the noted
values back as floats (shown "inf", "nan"), so Infinity in both files is equal.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from fusionlog.errors import FusionlogError
from fusionlog.inputs import check_input
from fusionlog.jsonout import NON_FINITE, join_path, resolve_non_finite, to_strict_json

__all__ = [
    "check_summary",
    "check_tolerance",
    "compare_summaries",
    "format_table",
    "headline",
    "load_json",
]


def headline(sc: Any) -> str:
    """The line above a run's table: runs, instants and seed (a replay: one log, no seed)."""
    if sc.replay is not None:
        return f"{sc.name}: one recorded log, K = {sc.instants - 1} ({sc.instants} instants)"
    return f"{sc.name}: M = {sc.runs} runs, K = {sc.instants - 1}, seed {sc.seed}"


#: (header, getter) of the table columns, after the architecture name.
_COLUMNS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("MSE", ("mse",)),
    ("E[MSE]", ("expected", "mse")),
    ("DM", ("dm",)),
    ("E[DM]", ("expected", "dm")),
    ("ANEES", ("anees",)),
    ("E[ANEES]", ("expected", "anees")),
    ("in band", ("nees_fraction_inside",)),
)

#: Columns of an identity summary ("kind": "identity"; BAYES and DS): (header, getter, percent).
_IDENTITY_COLUMNS: tuple[tuple[str, tuple[str, ...], bool], ...] = (
    ("accuracy", ("accuracy",), True),
    ("accuracy at K", ("final", "accuracy"), True),
    ("log-loss", ("log_loss",), False),
    ("log-loss at K", ("final", "log_loss"), False),
    ("P(true)", ("mean_p_true",), False),
    ("Bel(true)", ("mean_belief_true",), False),
    ("Pl(true)", ("mean_plausibility_true",), False),
    ("conflict", ("mean_conflict",), False),
)


def _get(d: Any, keys: Sequence[str]) -> Any:
    for k in keys:
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _fmt(v: Any, percent: bool = False) -> str:
    if v is None or isinstance(v, bool) or not isinstance(v, int | float):
        return "—"
    v = float(v)
    if not math.isfinite(v):
        return str(v)
    if percent:
        return f"{100.0 * v:.1f} %"
    if v == 0.0 or 1e-3 <= abs(v) < 1e6:
        return f"{v:.4f}"
    return f"{v:.4e}"


def format_table(summary: Mapping[str, Any]) -> str:
    """The Table I/II-style table: one row per architecture, columns MSE (eq. 45), its expected
    value, DM (eq. 47), expected DM, ANEES, expected ANEES, and the share of steps whose
    run-averaged NEES is inside the chi-square band. Takes the whole summary.json dict (or just
    its "architectures" mapping); missing values show as "—". An identity summary
    ("kind": "identity", architectures BAYES and DS) gets its own columns instead: see
    `_identity_table`."""
    archs = summary.get("architectures", summary)
    if not isinstance(archs, Mapping):
        raise ValueError("summary has no 'architectures' mapping")
    if archs is not summary:  # noted non-finite values (null in the file) show as inf / nan
        summary = resolve_non_finite(summary, check=False)
        archs = summary.get("architectures", archs)
    if summary.get("kind") == "sweep":
        return _sweep_table(summary)
    if _is_identity(summary, archs):
        return _identity_table(summary, archs)
    has_nis = any(isinstance(e, Mapping) and "nis" in e for e in archs.values())
    truth_free = has_nis and not any(isinstance(e, Mapping) and "mse" in e for e in archs.values())
    if truth_free:  # a recorded log without truth: what the innovations say
        return _nis_table(archs)
    header = ["architecture"] + [h for h, _ in _COLUMNS]
    rows = [header]
    for arch, entry in archs.items():
        rows.append(
            [str(arch)] + [_fmt(_get(entry, keys), percent=h == "in band") for h, keys in _COLUMNS]
        )
    if isinstance(summary.get("pcrb"), Mapping):  # nonlinear models: the bound on the MSE
        rows.append(["PCRB (bound)", _fmt(_get(summary, ("pcrb", "mse")))] + ["—"] * 6)
    table = _layout(header, rows)
    return table + "\n\n" + _nis_table(archs) if has_nis else table


#: Columns of the innovation table: (header, key of a `nis` entry, percent).
_NIS_COLUMNS: tuple[tuple[str, str, bool], ...] = (
    ("NIS", "mean", False),
    ("dof", "dof", False),
    ("in band", "fraction_inside", True),
    ("max |autocorr|", "whiteness_max_abs_autocorr", False),
    ("bound", "whiteness_bound", False),
    ("white lags", "whiteness_fraction_inside", True),
)


def _nis_table(archs: Mapping[str, Any]) -> str:
    """One row per architecture and sensor: the mean NIS against its degrees of freedom, the
    share of instants whose NIS is inside the chi-square band, and the whiteness of the
    normalised innovations (largest autocorrelation over the lags, its bound, the share of lags
    inside it); then the mean trace of the reported covariance."""
    header = ["architecture", "sensor"] + [h for h, _, _ in _NIS_COLUMNS] + ["mean tr(P)"]
    rows = [header]
    for arch, entry in archs.items():
        nis = entry.get("nis") if isinstance(entry, Mapping) else None
        if not isinstance(nis, Mapping):
            continue
        # one innovation: its sensor's (SKF:<sensor>) or all sensors' stacked
        one = str(arch).split(":", 1)[1] if ":" in str(arch) else "all"
        parts = {one: nis} if "mean" in nis else nis
        for j, (sensor, e) in enumerate(parts.items()):
            rows.append(
                [str(arch) if j == 0 else "", str(sensor)]
                + [_fmt(_get(e, (k,)), percent=p) for _, k, p in _NIS_COLUMNS]
                + [_fmt(entry.get("mean_trace")) if j == 0 else ""]
            )
    return _layout(header, rows)


def _is_identity(summary: Mapping[str, Any], archs: Mapping[str, Any]) -> bool:
    if summary.get("kind") == "identity":
        return True
    entries = [e for e in archs.values() if isinstance(e, Mapping)]
    return bool(entries) and all("accuracy" in e and "mse" not in e for e in entries)


def _identity_table(summary: Mapping[str, Any], archs: Mapping[str, Any]) -> str:
    """Identity summary: accuracy (over runs and steps, and at k = K), log-loss (same), mean
    probability of the true class (DS: normalised plausibility), mean Bel and Pl of the true
    class and mean per-step conflict (DS); then the BAYES/DS disagreement if present."""
    header = ["architecture"] + [h for h, _, _ in _IDENTITY_COLUMNS]
    rows = [header]
    for arch, entry in archs.items():
        rows.append(
            [str(arch)] + [_fmt(_get(entry, keys), percent=pc) for _, keys, pc in _IDENTITY_COLUMNS]
        )
    out = _layout(header, rows)
    if "disagreement" in summary:
        out += (
            f"\nBAYES and DS decide differently: {_fmt(summary['disagreement'], percent=True)}"
            f" of runs and steps, {_fmt(summary.get('final_disagreement'), percent=True)} at K"
        )
    return out


#: A sweep's table lists every row up to this many; beyond, only each architecture's lowest MSE.
SWEEP_ROWS = 60


def _sweep_table(summary: Mapping[str, Any]) -> str:
    """A sweep summary ("kind": "sweep"): one row per grid point and architecture (the varied
    keys' values, then the columns of the run table) when there are at most SWEEP_ROWS, and
    each architecture's lowest MSE over the grid."""
    keys = [g.get("key") for g in summary.get("grid", [])]
    header = [*map(str, keys), "architecture"] + [h for h, _ in _COLUMNS]
    rows = [header]
    for p in summary.get("points", []):
        values = [_value(p.get("values", {}).get(k)) for k in keys]
        for arch, entry in p.get("architectures", {}).items():
            cells = [_fmt(_get(entry, keys_), percent=h == "in band") for h, keys_ in _COLUMNS]
            rows.append([*values, str(arch), *cells])
    lines = []
    if len(rows) - 1 <= SWEEP_ROWS:
        # left-aligned key values, like the architecture column
        width = [max(len(r[j]) for r in rows) for j in range(len(header))]
        for r in rows:
            left = [c.ljust(w) for c, w in zip(r[: len(keys) + 1], width, strict=False)]
            right = [
                c.rjust(w) for c, w in zip(r[len(keys) + 1 :], width[len(keys) + 1 :], strict=True)
            ]
            lines.append("  ".join(left + right).rstrip())
        lines.insert(1, "  ".join("-" * w for w in width))
    else:
        lines.append(f"({len(rows) - 1} rows: see sweep.parquet or summary.json)")
    lowest = summary.get("lowest_mse", {})
    if lowest:
        lines.append("lowest MSE over the grid (exact where every point has it, else Monte Carlo):")
        name = max(len(str(a)) for a in lowest)
        for arch, b in lowest.items():
            by = b.get("by") == "expected"
            v = b.get("expected_mse") if by else b.get("mse")
            at = ", ".join(f"{k}={_value(x)}" for k, x in b.get("values", {}).items())
            lines.append(f"  {str(arch).ljust(name)}  {_fmt(v)} at {at}")
    return "\n".join(lines)


def _value(v: Any) -> str:
    """A varied key's value as the table shows it."""
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def _layout(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(r[j]) for r in rows) for j in range(len(header))]

    def line(r: list[str]) -> str:
        cells = [r[0].ljust(widths[0])] + [
            c.rjust(w) for c, w in zip(r[1:], widths[1:], strict=True)
        ]
        return "  ".join(cells).rstrip()

    out = [line(header), "  ".join("-" * w for w in widths)]
    out += [line(r) for r in rows[1:]]
    return "\n".join(out)


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
    if out.get("kind") == "sweep" and isinstance(out.get("points"), list):  # a sweep's points
        for i, point in enumerate(out["points"]):
            try:
                check_summary(point)
            except ValueError as e:
                raise ValueError(f"points[{i}]: {e}") from None
    for key, v in out.items():
        if key in _TOP_NUMBERS:
            _want_number(v, key, nullable=False)
        elif key in _TOP_STRINGS and not isinstance(v, str):
            raise ValueError(f"{key}: {_describe(v)} where a string is expected")
        elif key == "state_names" and (
            not isinstance(v, list | tuple) or not all(isinstance(x, str) for x in v)
        ):
            raise ValueError(f"{key}: {_describe(v)} where a list of strings is expected")
    archs = out.get("architectures", {})
    if not isinstance(archs, Mapping):
        raise ValueError(f"architectures: {_describe(archs)} where an object is expected")
    for arch, entry in archs.items():
        where = join_path("architectures", str(arch))
        if not isinstance(entry, Mapping):
            raise ValueError(f"{where}: {_describe(entry)} where an object of metrics is expected")
        for key, v in entry.items():
            path = join_path(where, str(key))
            if key in _ARCH_NUMBERS:
                _want_number(v, path, nullable=False)
            elif key == "expected" and v is None and "pcrb" in out:
                continue  # a nonlinear model: no exact analysis, the PCRB stands instead
            elif key in _ARCH_GROUPS:
                container, nullable, nesting = _ARCH_GROUPS[key]
                if not isinstance(v, list | tuple if container is list else Mapping):
                    kind = "a list" if container is list else "an object"
                    raise ValueError(f"{path}: {_describe(v)} where {kind} of numbers is expected")
                _want_numbers(v, path, nullable, nesting)
    return out


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
