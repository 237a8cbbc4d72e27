"""A replay's recording: what one recorded log needs, not the Monte Carlo layout.

One run has no Monte Carlo curves to average: its squared errors are noise, and the first
instant's transient (a prior's large covariance) sets the range of every view that starts there.
A replay's recording therefore opens on (tabs, in order):

- **Trajectory**: the plane of two position states: each sensor's readings of both, each
  architecture's estimated path, the truth where there is one;
- **States**: each state over time, every architecture's estimate with its ±2σ band, the
  truth and the sensors' direct readings (``runs/0/...``, as the sample runs of a scenario);
- **NIS**: one view per sensor, every architecture's NIS of that sensor with its χ² band;
- **Innovations**: one view per sensor, the normalised innovations (each component divided by
  its predicted standard deviation; white noise of unit variance for a consistent filter) with
  the ±2 band;
- **Errors** (with truth): the NEES of the truthed states with its χ² band, and the trace of P.

Entities added here (the others are those of :mod:`.state_recording` and :mod:`.consistency_views`):

=============================================  ============================================
``trajectory/measured/<sensor>``               the sensor's readings of the two plane states
``trajectory/estimates/<ARCH>``                the architecture's path in the plane
``trajectory/truth``                           the true path (where there is truth)
``innovations/<sensor>/<component>/<ARCH>``    normalised innovation of that component
``innovations/bounds/upper``, ``lower``        ±2
=============================================  ============================================

Ranges: every time-series view opens on the range of its values after the start
(``view_range``: the 0.5 %–99.5 % quantiles of the instants after the first 2 %, padded by a
tenth), so that the transient does not flatten the rest; zooming out shows it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from .stream import SeriesWriter, entity_path
from .style import BOUND_COLOR, TRUTH_COLOR, arch_color, arch_width, class_color
from .views import WHOLE_X, query, tabbed_blueprint

__all__ = ["opening_range", "plane_states", "replay_blueprint", "view_range", "write_replay"]

#: {ARCH: {sensor: (K+1, r) normalised innovations of the first run}}
Innovations = Mapping[str, Mapping[str, np.ndarray]]


def view_range(curves: Sequence[np.ndarray], floor: float | None = None) -> tuple[float, float]:
    """(low, high) of the curves' values after the start: the quantiles 0.5 % and 99.5 % over
    the instants after the first 2 % (at least one), widened by a tenth of the span; `floor`
    (e.g. 0 for a NIS) bounds it below."""
    vals = []
    for c in curves:
        c = np.asarray(c, dtype=float)
        skip = max(1, len(c) // 50) if len(c) > 2 else 0
        v = c[skip:]
        vals.append(v[np.isfinite(v)])
    v = np.concatenate(vals) if vals else np.zeros(0)
    if v.size == 0:
        return (0.0, 1.0)
    lo, hi = (float(x) for x in np.quantile(v, [0.005, 0.995]))
    pad = 0.1 * (hi - lo) if hi > lo else max(abs(hi), 1.0) * 0.1
    lo, hi = lo - pad, hi + pad
    if floor is not None:
        lo = max(lo, floor)
    return lo, hi


def opening_range(
    curves: Sequence[np.ndarray], floor: float | None = None
) -> tuple[float, float] | None:
    """The range a Monte Carlo view opens on when the start's transient would flatten the
    rest (a value beyond twice the span of `view_range` from its edge: multirate.toml's MSE
    of x falls from 27 to 0.07, so every curve lay on the axis), else None (the viewer fits
    all values, as the paper's figures show them)."""
    lo, hi = view_range(curves, floor)
    finite = [v[np.isfinite(v)] for v in (np.asarray(c, dtype=float) for c in curves)]
    v = np.concatenate(finite) if finite else np.zeros(0)
    span = hi - lo
    if v.size == 0 or not (np.isfinite(span) and span > 0):
        return None
    if v.max() <= hi + 2 * span and v.min() >= lo - 2 * span:
        return None
    return lo, hi


def plane_states(
    state_names: Sequence[str], measured: Mapping[int, Mapping[str, Any]]
) -> tuple[int, int]:
    """The two states of the trajectory plane: the first pair a sensor reads directly (a
    position sensor), else the first two states read directly, else the first two states."""
    by_sensor: dict[str, list[int]] = {}
    for i in sorted(measured):
        for sensor in measured[i]:
            by_sensor.setdefault(sensor, []).append(i)
    for states in by_sensor.values():
        if len(states) >= 2:
            return states[0], states[1]
    direct = sorted(measured)
    if len(direct) >= 2:
        return direct[0], direct[1]
    return 0, min(1, len(state_names) - 1)


#: Rerun draws 2-D positions in float32: points beyond its range cannot be drawn.
_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _strip(xy: np.ndarray) -> np.ndarray:
    """The drawable points of a path: finite, within float32 (a recorded 1e300 is data, not
    a place in the plane; the time series still show it)."""
    return xy[(np.abs(xy) <= _FLOAT32_MAX).all(axis=1)]


def write_replay(
    w: SeriesWriter,
    ij: tuple[int, int],
    samples: Mapping[int, Any],
    measured: Mapping[int, Mapping[str, np.ndarray]],
    innovations: Innovations,
    sensor_color: Mapping[str, tuple[int, int, int]] | None = None,
) -> None:
    """The trajectory (static 2-D strips and points) and the normalised innovations;
    `sensor_color` gives each sensor's readings the colour they have in the other views."""
    i, j = ij
    rec = w.rec
    n = 1  # a long log's samples come decimated (core/decimate.py)
    if 0 in samples:
        truth, est = samples[0]
        t = _strip(np.asarray(truth, dtype=float)[::n, [i, j]])
        if len(t):
            rec.log("trajectory/truth", rr.LineStrips2D([t], colors=[TRUTH_COLOR], radii=[-2.0],
                                                        labels=["truth"]), static=True)  # fmt: skip
        for arch, (mean, _) in est.items():
            path = _strip(np.asarray(mean, dtype=float)[::n, [i, j]])
            strip = rr.LineStrips2D(
                [path], colors=[arch_color(arch)], radii=[-arch_width(arch)], labels=[arch]
            )
            rec.log(entity_path("trajectory", "estimates", arch), strip, static=True)
    sensors = [s for s in measured.get(i, {}) if s in measured.get(j, {})]
    for k, s in enumerate(sensors):
        pts = _strip(np.stack([measured[i][s], measured[j][s]], axis=1))[::n]
        col = (sensor_color or {}).get(s, class_color(k))
        rec.log(entity_path("trajectory", "measured", s),
                rr.Points2D(pts, colors=[col], radii=[-2.5]), static=True)  # fmt: skip
    for arch, parts in innovations.items():
        for part, nu in parts.items():
            for c in range(nu.shape[1]):
                p = entity_path("innovations", part, f"z{c}", arch)
                w.line(p, nu[:, c], f"{arch} z{c}", arch_color(arch), arch_width(arch))
    if innovations:
        n = len(w.times)
        for side, v in (("upper", 2.0), ("lower", -2.0)):
            w.line(entity_path("innovations", "bounds", side), np.full(n, v), "±2",
                   BOUND_COLOR, 1.0)  # fmt: skip


def _ts(name: str, contents: list[str], rng: tuple[float, float], legend: bool = True):
    return rrb.TimeSeriesView(
        origin="/",
        contents=contents,
        name=name,
        axis_x=WHOLE_X,
        axis_y=rrb.ScalarAxis(range=rng, zoom_lock=False),
        plot_legend=rrb.PlotLegend(corner="RightTop", visible=legend),
    )


def replay_blueprint(
    state_names: Sequence[str],
    ij: tuple[int, int],
    samples: Mapping[int, Any],
    nis: Mapping[str, Mapping[str, tuple[np.ndarray, ...]]],
    innovations: Innovations,
    nees: Mapping[str, np.ndarray] | None,
    nees_bounds: tuple[np.ndarray, np.ndarray] | None,
    traces: Mapping[str, np.ndarray],
    timeline: str,
    more: Sequence[Any] = (),
    bound: Mapping[str, np.ndarray] | None = None,
) -> rrb.Blueprint:
    """Trajectory, States, NIS, Innovations[, Errors] (see the module's docstring), then the
    tabs `more` (the trajectory metrics': `.trajectory`); `bound` the bound check's ratio of
    the architectures that have one (drawn under Errors with the line 1)."""
    tabs: list = [
        rrb.Spatial2DView(
            origin="/trajectory",
            name=f"Trajectory ({state_names[ij[0]]}, {state_names[ij[1]]}): readings, "
            "estimates, truth",
        )
    ]
    if 0 in samples:
        truth, est = samples[0]
        views = []
        for i, s in enumerate(state_names):
            curves = [np.asarray(truth, dtype=float)[:, i]]
            for mean, std in est.values():
                mu, sd = np.asarray(mean)[:, i], np.asarray(std)[:, i]
                curves += [mu + 2 * sd, mu - 2 * sd]
            title = f"{s}: estimates ± 2σ, truth, readings"
            views.append(_ts(title, [query("runs", 0, s) + "/**"], view_range(curves), i == 0))
        tabs.append(rrb.Grid(*views, name="States"))
    parts = list(dict.fromkeys(p for by_part in nis.values() for p in by_part))
    if parts:
        views = []
        for part in parts:
            curves = [v[0] for by_part in nis.values() for p, v in by_part.items() if p == part]
            curves += [v[2] for by_part in nis.values() for p, v in by_part.items() if p == part]
            contents = [query("metrics", "nis", a, part) + "/**" for a in nis if part in nis[a]]
            views.append(_ts(f"NIS of {part} (grey: χ² band)", contents, view_range(curves, 0.0)))
        tabs.append(rrb.Grid(*views, name="NIS"))
    if innovations:
        views = []
        for part in dict.fromkeys(p for by_part in innovations.values() for p in by_part):
            contents = [query("innovations", part) + "/**", query("innovations", "bounds") + "/**"]
            views.append(
                _ts(f"innovations of {part}, normalised (grey: ±2)", contents, (-4.5, 4.5))
            )
        tabs.append(rrb.Grid(*views, name="Innovations"))
    errors = []
    if nees:
        curves = list(nees.values()) + ([nees_bounds[1]] if nees_bounds is not None else [])
        errors.append(_ts("NEES of the truthed states (grey: χ² band)",
                          [query("metrics", "nees") + "/**"], view_range(curves, 0.0)))  # fmt: skip
    if bound:
        title = "bound check: λmax of P^-1 E[e e^T] (grey: 1)"
        span = view_range([*bound.values(), np.ones(1)], 0.0)
        errors.append(_ts(title, [query("metrics", "bound") + "/**"], span))
    if traces:
        errors.append(_ts("trace of P", [query("metrics", "trace") + "/**"],
                          view_range(list(traces.values()), 0.0)))  # fmt: skip
    if errors:
        tabs.append(rrb.Vertical(*errors, name="Errors" if nees else "Trace of P"))
    return tabbed_blueprint(tabs + list(more), timeline)
