"""Plain-text reports: the Table I/II-style summary table (the golden-file comparison is
`fusionlog.compare`).

A summary.json is strict JSON: a non-finite metric is null and listed in the top-level
``non_finite`` note (`fusionlog.jsonout`); the table reads the noted values back as floats
(shown "inf", "nan").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from fusionlog.jsonout import resolve_non_finite

__all__ = ["format_table", "headline", "model_sensors", "recording_report"]


def headline(sc: Any) -> str:
    """The line above a run's table: runs, instants and seed (a replay: one log, no seed)."""
    return _headline(sc.name, sc.runs, sc.instants - 1, sc.replay is not None, sc.seed)


def recording_report(summary: Mapping[str, Any], properties: Mapping[str, Any]) -> str:
    """What `fusionlog summary` prints of a recording: its headline and `format_table`, told
    by its properties (`io.rrd.read_recording`) whether it is a replay's (one recorded log:
    its one run and seed 0 are no Monte Carlo settings) and what the filters' sensors are.
    ValueError when `summary` is not one."""
    from fusionlog.errors import FusionlogError
    from fusionlog.scenario import is_replay_text

    text = _get(properties, ("scenario", "text"))
    try:
        replay = isinstance(text, str) and is_replay_text(text, "the recorded scenario")
    except FusionlogError:  # a recording of another version: told as a simulation's
        replay = False
    table = format_table(summary, model_sensors(properties.get("provenance")))
    head = _headline(summary.get("scenario"), summary.get("runs"), summary.get("steps"), replay)
    return f"{head}\n{table}"


def _headline(name: Any, runs: Any, steps: Any, replay: bool, seed: Any = None) -> str:
    if replay:
        instants = f" ({steps + 1} instants)" if isinstance(steps, int) else ""
        return f"{name}: one recorded log, K = {steps}{instants}"
    return f"{name}: M = {runs} runs, K = {steps}" + (f", seed {seed}" if seed is not None else "")


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


#: The trajectory metrics' columns, after MSE where an architecture has them (RMSE, metres).
_TRAJECTORY_COLUMNS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("APE", ("ape", "rmse")),
    ("RPE", ("rpe", "rmse")),
)


#: The bound check's column, last where an architecture has one (DESIGN.md "Unknown correlation
#: and the bound check"): the worst lambda_max(P^-1 E[e e^T]), and where it exceeds 1 the step.
BOUND_COLUMN = ("bound", ("bound",))


def _columns(archs: Mapping[str, Any]) -> tuple[tuple[str, tuple[str, ...]], ...]:
    cols = _COLUMNS
    if any(isinstance(e, Mapping) and "ape" in e for e in archs.values()):
        cols = _COLUMNS[:1] + _TRAJECTORY_COLUMNS + _COLUMNS[1:]
    if any(isinstance(e, Mapping) and isinstance(e.get("bound"), Mapping) for e in archs.values()):
        cols = (*cols, BOUND_COLUMN)
    return cols


def _bound_cell(b: Any) -> str:
    """The bound column's cell: the worst ratio, "ok" where the reported covariance bounds the
    error at every instant, else "fails at k"; a Monte Carlo estimate as "~value ± stderr"."""
    if not isinstance(b, Mapping) or not isinstance(b.get("worst"), int | float):
        return "—"
    mc = b.get("monte_carlo") is True
    value = f"~{_fmt(b['worst'])} ± {_fmt(b.get('stderr'))}" if mc else _fmt(b["worst"])
    return f"{value} ok" if b.get("holds") else f"{value} fails at k={b.get('worst_step')}"


def _cell(entry: Any, header: str, keys: tuple[str, ...]) -> str:
    if (header, keys) == BOUND_COLUMN:
        return _bound_cell(_get(entry, keys))
    return _fmt(_get(entry, keys), percent=header == "in band")


def alignment_lines(archs: Mapping[str, Any]) -> str:
    """The alignment of each architecture's positions onto the truth (rotation angle, and
    axis in 3-D; translation; scale), below the table; empty without one (align "none", or
    several runs, each with its own)."""
    import numpy as np

    from fusionlog.core.trajectory import rotation_angles

    out = []
    for arch, entry in archs.items():
        ape = entry.get("ape") if isinstance(entry, Mapping) else None
        if not isinstance(ape, Mapping) or ape.get("align") in (None, "none"):
            continue
        if ape.get("rotation") is None:
            continue
        angle, axis = rotation_angles(np.asarray(ape["rotation"], dtype=float))
        about = "" if axis is None else " about [" + ", ".join(f"{v:.4f}" for v in axis) + "]"
        t = ", ".join(f"{v:.6g}" for v in ape.get("translation") or [])
        out.append(
            f"{arch}: {ape['align']} alignment: rotation {angle:.4f}°{about}, "
            f"translation [{t}], scale {ape.get('scale'):.9g}"
        )
    return "\n" + "\n".join(out) if out else ""


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


def format_table(summary: Mapping[str, Any], sensors: Sequence[str] | None = None) -> str:
    """The Table I/II-style table: one row per architecture, columns MSE (eq. 45), its expected
    value, DM (eq. 47), expected DM, ANEES, expected ANEES, and the share of steps whose
    run-averaged NEES is inside the chi-square band. Takes the whole summary.json dict (or just
    its "architectures" mapping); missing values show as "—". An identity summary
    ("kind": "identity", architectures BAYES and DS) gets its own columns instead: see
    `_identity_table`. `sensors`, the filters' sensor names (`model_sensors`), name the row of
    an innovation that summary.json does not split by sensor: that of a single sensor."""
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
        return _nis_table(archs, sensors)
    columns = _columns(archs)
    header = ["architecture"] + [h for h, _ in columns]
    rows = [header]
    for arch, entry in archs.items():
        rows.append([str(arch)] + [_cell(entry, h, keys) for h, keys in columns])
    if isinstance(summary.get("pcrb"), Mapping):  # nonlinear models: the bound on the MSE
        rows.append(
            ["PCRB (bound)", _fmt(_get(summary, ("pcrb", "mse")))] + ["—"] * (len(columns) - 1)
        )
    table = _layout(header, rows) + alignment_lines(archs)
    return table + "\n\n" + _nis_table(archs, sensors) if has_nis else table


#: Columns of the innovation table: (header, key of a `nis` entry, percent).
_NIS_COLUMNS: tuple[tuple[str, str, bool], ...] = (
    ("NIS", "mean", False),
    ("dof", "dof", False),
    ("in band", "fraction_inside", True),
    ("max |autocorr|", "whiteness_max_abs_autocorr", False),
    ("bound", "whiteness_bound", False),
    ("white lags", "whiteness_fraction_inside", True),
)


def _nis_table(archs: Mapping[str, Any], sensors: Sequence[str] | None = None) -> str:
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
        # one innovation: its sensor's (SKF:<sensor>), or the only sensor's
        one = str(arch).split(":", 1)[1] if ":" in str(arch) else _only(sensors)
        parts = {one: nis} if "mean" in nis else nis
        for j, (sensor, e) in enumerate(parts.items()):
            rows.append(
                [str(arch) if j == 0 else "", str(sensor)]
                + [_fmt(_get(e, (k,)), percent=p) for _, k, p in _NIS_COLUMNS]
                + [_fmt(entry.get("mean_trace")) if j == 0 else ""]
            )
    return _layout(header, rows)


def _only(sensors: Sequence[str] | None) -> str:
    """The name of the filters' only sensor ("all" when it is not known)."""
    return sensors[0] if sensors is not None and len(sensors) == 1 else "all"


def model_sensors(provenance: Any) -> list[str] | None:
    """The sensor names of the filters' model that an estimates file's provenance records
    (its "model" JSON, `system_to_dict`); None when it records none."""
    import json

    try:
        model = json.loads(provenance["model"])
        return [str(s["name"]) for s in model["sensors"]]
    except (KeyError, TypeError, ValueError):
        return None


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
    every = [e for p in summary.get("points", []) for e in p.get("architectures", {}).values()]
    columns = _columns(dict(enumerate(every)))  # APE and RPE where a point has them
    header = [*map(str, keys), "architecture"] + [h for h, _ in columns]
    rows = [header]
    for p in summary.get("points", []):
        values = [_value(p.get("values", {}).get(k)) for k in keys]
        for arch, entry in p.get("architectures", {}).items():
            cells = [_cell(entry, h, keys_) for h, keys_ in columns]
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
