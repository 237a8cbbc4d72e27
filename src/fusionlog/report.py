"""Plain-text reports: the Table I/II-style summary table and the golden-file comparison."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["compare_summaries", "format_table"]

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
    if _is_identity(summary, archs):
        return _identity_table(summary, archs)
    header = ["architecture"] + [h for h, _ in _COLUMNS]
    rows = [header]
    for arch, entry in archs.items():
        rows.append(
            [str(arch)] + [_fmt(_get(entry, keys), percent=h == "in band") for h, keys in _COLUMNS]
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


# ----------------------------------------------------------------------------------- comparison
def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _show(v: Any) -> str:
    if _is_number(v):
        return f"{v:.10g}"
    return repr(v)


def _compare(actual: Any, golden: Any, where: str, rtol: float, atol: float, out: list[str]):
    if isinstance(golden, Mapping) and isinstance(actual, Mapping):
        for key in golden:
            sub = f"{where}.{key}" if where else str(key)
            if key not in actual:
                out.append(f"{sub}: missing (golden {_show_short(golden[key])})")
            else:
                _compare(actual[key], golden[key], sub, rtol, atol, out)
        for key in actual:
            if key not in golden:
                sub = f"{where}.{key}" if where else str(key)
                out.append(f"{sub}: extra (actual {_show_short(actual[key])}, not in golden)")
        return
    if (
        isinstance(golden, list | tuple)
        and isinstance(actual, list | tuple)
        and not isinstance(golden, str)
    ):
        if len(golden) != len(actual):
            out.append(f"{where}: length {len(actual)}, golden {len(golden)}")
            return
        for i, (a, g) in enumerate(zip(actual, golden, strict=True)):
            _compare(a, g, f"{where}[{i}]", rtol, atol, out)
        return
    if _is_number(golden) and _is_number(actual):
        a, g = float(actual), float(golden)
        if math.isnan(a) and math.isnan(g):
            return
        if a == g or (math.isfinite(a) and abs(a - g) <= atol + rtol * abs(g)):
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


def compare_summaries(
    actual: Mapping[str, Any],
    golden: Mapping[str, Any],
    rtol: float = 1e-6,
    atol: float = 1e-12,
) -> list[str]:
    """Differences between two summary dicts, one human-readable line each; [] means they agree.

    A number passes when |actual - golden| <= atol + rtol * |golden| (NaN equals NaN, null
    equals null); other leaves must be equal. Lines name the architecture and the metric, e.g.
    ``CKF: mse: actual 0.1012, golden 0.101 (rel. diff 0.00198)``; missing or extra
    architectures and keys are reported too.
    """
    out: list[str] = []
    a_arch = actual.get("architectures", {}) if isinstance(actual, Mapping) else {}
    g_arch = golden.get("architectures", {}) if isinstance(golden, Mapping) else {}
    top_a = {k: v for k, v in actual.items() if k != "architectures"}
    top_g = {k: v for k, v in golden.items() if k != "architectures"}
    _compare(top_a, top_g, "", rtol, atol, out)
    if ("architectures" in actual) != ("architectures" in golden):
        side = "actual" if "architectures" not in actual else "golden"
        out.append(f"architectures: missing in {side}")
    if isinstance(a_arch, Mapping) and isinstance(g_arch, Mapping):
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
