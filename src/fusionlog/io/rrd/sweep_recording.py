"""The recording of a parameter sweep (``sweep.rrd``): every metric against the swept parameter.

The x axis is the first varied key, on two timelines: one named by the key (``scenario.dt``), a
duration whose seconds are the key's values (a time-series view plots against a timeline, and a
duration is the timeline kind that holds any real number, here to the nanosecond), and the
sequence ``grid index``, the position along the first key. The views open on the key's values,
except for a log-spaced range (``start:stop:num:log``), whose points would crowd the left of a
linear axis: on the grid index they are evenly spaced, i.e. on a logarithmic axis, and the first
view's title says how an index reads as a value. Keys whose values are not numbers have only the
grid index. Each other varied key's values make lines of their own: one line per (architecture,
other values).

=============================================  ============================================
``sweep/<metric>/<line>/exact``                 the exact expected value (covariance
                                                analysis): a line
``sweep/<metric>/<line>/mc``                    the Monte Carlo value: dots on that line
``sweep/<metric>/reference``                    grey: what a consistent filter gives (ANEES
                                                n, DM E[sqrt(chi2_n)]) or the band's level
=============================================  ============================================

``<metric>`` is ``mse`` (eq. 45), ``anees``, ``dm`` (eq. 47) or ``nees_fraction_inside`` (Monte
Carlo only); ``<line>`` is the architecture, followed by the other keys' values when there are
several keys (``CKF | sensors.s1.R=2``). A line and its dots share their name and colour (the
legend lists each line once); lines of one architecture for different other values are
lighter shades of its colour. Values that do not exist (no exact analysis for runs with
dropouts, no Monte Carlo with --exact-only) are not logged. The summary property holds the
sweep's summary.json.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import IO, Any

import numpy as np
import rerun.blueprint as rrb

from fusionlog.jsonout import dumps

from .legend import legend_box, place_legend
from .stream import entity_path, recording_id_for, recording_stream
from .style import BOUND_COLOR, arch_color, arch_width, lighter
from .views import query, tabbed_blueprint, time_series_view

__all__ = ["INDEX_TIMELINE", "write_sweep_recording"]

#: The sequence timeline: position along the first varied key.
INDEX_TIMELINE = "grid index"
#: Durations are int64 nanoseconds: values beyond this many seconds do not fit.
_MAX_SECONDS = 9.0e9

#: (metric, view title, whether an exact value exists)
_METRICS = (
    ("mse", "MSE (eq. 45)", True),
    ("anees", "ANEES (grey: n, a consistent filter)", True),
    ("dm", "Mahalanobis distance DM (eq. 47; grey: a consistent filter)", True),
    ("nees_fraction_inside", "share of steps with the NEES inside the χ² band", False),
)


def _value_axis(values: list[Any]) -> np.ndarray | None:
    """The first key's values as duration seconds, or None when they are not numbers or a
    duration cannot hold them apart (beyond ±9e9, or closer than a nanosecond)."""
    if not values or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in values
    ):
        return None
    x = np.asarray(values, dtype=float)
    if not np.isfinite(x).all() or np.abs(x).max() > _MAX_SECONDS:
        return None
    ns = np.round(x * 1e9)
    if len(np.unique(ns)) != len(ns):
        return None
    return x


def _lines(summary: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """{line name: {"arch", "shade", metric or "expected_<metric>": (n0,) arrays}} from the
    summary's points (in product order, the first key slowest)."""
    grid = summary["grid"]
    n0 = len(grid[0]["values"])
    others = grid[1:]
    per_x = math.prod(len(g["values"]) for g in others)
    lines: dict[str, dict[str, Any]] = {}
    for p in summary["points"]:
        i, g = divmod(p["index"], per_x)
        rest = ", ".join(f"{o['key']}={_show(p['values'][o['key']])}" for o in others)
        for a, e in p["architectures"].items():
            name = f"{a} | {rest}" if rest else a
            line = lines.get(name)
            if line is None:
                line = lines[name] = {"arch": a, "shade": g, "shades": per_x}
                for m, _, exact in _METRICS:
                    line[m] = np.full(n0, np.nan)
                    if exact:
                        line[f"expected_{m}"] = np.full(n0, np.nan)
            for m, _, exact in _METRICS:
                line[m][i] = _num(e.get(m))
                if exact:
                    line[f"expected_{m}"][i] = _num(e["expected"].get(m))
    return lines


def _num(v: Any) -> float:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else math.nan


def _show(v: Any) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def _reference(metric: str, n: int, confidence: float) -> tuple[float, str] | None:
    """The grey line of a view: a consistent filter's ANEES (n) and DM, or the band's level."""
    if metric == "anees":
        return float(n), f"consistent: {n}"
    if metric == "dm":
        dm = math.sqrt(2.0) * math.exp(math.lgamma((n + 1) / 2.0) - math.lgamma(n / 2.0))
        return dm, f"consistent: {dm:.4f}"
    if metric == "nees_fraction_inside":
        return confidence, f"{confidence:.0%}"
    return None


def write_sweep_recording(
    file: IO[bytes],
    summary: Mapping[str, Any],
    properties: Mapping[str, Any] | None = None,
) -> None:
    """Write the sweep recording of `summary` (a sweep's summary.json dict) into `file`."""
    grid = summary["grid"]
    key, values = grid[0]["key"], list(grid[0]["values"])
    n0 = len(values)
    index = np.arange(n0, dtype=np.int64)
    x = _value_axis(values)
    axes: dict[str, tuple[str, np.ndarray]] = {INDEX_TIMELINE: ("sequence", index)}
    if x is not None:
        axes[key] = ("duration", x)
    lines = _lines(summary)
    n = len(summary["state_names"])
    confidence = float(summary["confidence"])
    log = bool(grid[0].get("log"))
    blueprint = _blueprint(key, values, lines, x, log, bool(summary.get("exact_only")))
    name = f"{summary['scenario']}_sweep"
    # deterministic, and not the same for two different grids of one scenario (the viewer
    # merges recordings that share an id)
    grid_id = dumps([(g["key"], g["values"]) for g in grid])
    with recording_stream(
        file,
        blueprint,
        name,
        int(summary["seed"]),
        index.astype(float),
        summary,
        properties,
        recording_id_for(f"{name}:{grid_id}", int(summary["seed"])),
        axes,
    ) as w:
        for line_name, line in lines.items():
            base = arch_color(line["arch"])
            # other keys' values: lighter shades of the architecture's colour
            col = lighter(base, 0.6 * line["shade"] / max(line["shades"] - 1, 1))
            width = arch_width(line["arch"])
            for m, _, exact in _METRICS:
                # a series with no value at all (no exact analysis, --exact-only) is left out
                if exact and np.isfinite(line[f"expected_{m}"]).any():
                    p = entity_path("sweep", m, line_name, "exact")
                    w.line(p, line[f"expected_{m}"], line_name, col, width)
                if np.isfinite(line[m]).any():
                    w.points(entity_path("sweep", m, line_name, "mc"), line[m], line_name, col)
        for m, _, _ in _METRICS:
            ref = _reference(m, n, confidence)
            if ref is not None:
                p = entity_path("sweep", m, "reference")
                w.line(p, np.full(n0, ref[0]), ref[1], BOUND_COLOR, 1.5)


def _on_axis(y: np.ndarray, x: np.ndarray | None) -> np.ndarray:
    """A curve as the view draws it, for the legend placement (which reads curves as evenly
    spaced samples): on the value axis, resampled at even steps of x."""
    if x is None or len(x) < 2:
        return y
    order = np.argsort(x)
    xs, ys = x[order], y[order]
    ok = np.isfinite(ys)
    if ok.sum() < 2:
        return y
    return np.interp(np.linspace(xs[0], xs[-1], 400), xs[ok], ys[ok])


def _axis_note(key: str, values: list[Any]) -> str:
    """How the grid index reads as the key's value on a log-spaced range."""
    a, b, n = values[0], values[-1], len(values) - 1
    return f"{key} = {a:.4g} x {b / a:.4g}^(i/{n}) at grid index i"


def _blueprint(
    key: str,
    values: list[Any],
    lines: Mapping[str, Mapping[str, Any]],
    x: np.ndarray | None,
    log: bool,
    exact_only: bool,
) -> rrb.Blueprint:
    """One view per metric in a 2 x 2 grid (no Monte Carlo, no band share), the legend once,
    on the view and in the corner where it hides the fewest points.

    The time panel opens on the key's own timeline (its values), except for a log-spaced range,
    whose points crowd the left of a linear axis: there the grid index is the log axis, and the
    first view's title says how an index reads as a value (the value timeline stays a click
    away in the time panel)."""
    metrics = [m for m in _METRICS if m[2] or not exact_only]
    on_index = x is None or (log and len(values) > 2)
    # nonlinear models have no exact analysis: their points are Monte Carlo dots only
    exact = any(np.isfinite(line["expected_mse"]).any() for line in lines.values())
    how = "lines: exact" if exact_only else "dots: Monte Carlo, no exact values"
    if exact and not exact_only:
        how = "lines: exact, dots: Monte Carlo"
    if on_index and x is not None:
        how += "; " + _axis_note(key, values)
    names = list(lines)
    curves = [
        [
            _on_axis(np.asarray(line[k]), None if on_index else x)
            for line in lines.values()
            for k in (m, f"expected_{m}")
            if k in line
        ]
        for m, _, _ in metrics
    ]
    box = legend_box(len(names), max(map(len, names), default=0), 2, 2)
    at = place_legend(curves, box)
    views = [
        time_series_view(
            f"{title} against {key} ({how})" if i == 0 else f"{title} against {key}",
            [query("sweep", m) + "/**"],
            legend=i == at[0],
            corner=at[1],
        )
        for i, (m, title, _) in enumerate(metrics)
    ]
    sweep = rrb.Grid(*views, grid_columns=2, name=f"Sweep of {key}")
    return tabbed_blueprint([sweep], INDEX_TIMELINE if on_index else key)
