"""The evaluation recording of a state-estimation scenario: metric time series, sample runs,
state plane, summary, default layout (the paper's Figs. 4-6 and a consistency view).

Layout of the recording (timelines ``step`` and ``time``; ``<state>`` and ``<ARCH>`` are escaped
entity-path parts, see :func:`~fusionlog.io.rrd.stream.entity_path`: ``SKF:s2`` becomes
``SKF\\:s2``):

=============================================  ============================================
``metrics/mse/<state>/<ARCH>``                  MSE per state and step (eq. 44, Fig. 4)
``metrics/mse_minus_ckf/<state>/<ARCH>``        MSE minus the CKF's (Fig. 5; only with CKF,
                                                CKF itself omitted)
``metrics/trace/<ARCH>``                        run-averaged trace of P (Fig. 6)
``metrics/nees/<ARCH>``                         run-averaged NEES
``metrics/nees/bounds/lower``, ``.../upper``    two-sided chi-square band of the averaged NEES
``metrics/dm/<ARCH>``                           run-averaged Mahalanobis distance (eq. 46)
``metrics/expected/mse/<state>/<ARCH>``         exact expected MSE (covariance analysis)
``metrics/expected/nees/<ARCH>``                exact expected NEES
``metrics/expected/dm/<ARCH>``                  exact expected Mahalanobis distance
``metrics/bound/<ARCH>``                        the bound check: lambda_max(P^-1 E[e e^T]) per
                                                step (exact, or a Monte Carlo estimate)
``metrics/bound/limit``                         the line 1 (at most 1: P bounds the error)
``metrics/pcrb/mse/<state>``                    the posterior Cramér-Rao bound on the MSE
                                                (nonlinear models: no exact analysis)
``runs/<m>/<state>/truth``                      true state of sample run m
``runs/<m>/<state>/<ARCH>/mean``                estimate of sample run m
``runs/<m>/<state>/<ARCH>/upper``, ``/lower``   mean +- 2 sigma, sigma = sqrt(P_ii)
``plane/...``                                   the state plane (:mod:`.plane`)
``metrics/nis/...``, ``sensors/...``           truth-free consistency and sensor availability
                                                (:mod:`.consistency_views`)
=============================================  ============================================

When the instants are not whole seconds apart (multi-rate sensors, irregular instants) the
views open on the ``time`` timeline, so that every instant is plotted where it is.

Steps where a value is not finite (undefined estimate) are simply not logged. Monte Carlo
curves are lines (``SeriesLines``), expected curves are markers (``SeriesPoints``) in the same
colour and under the same legend name, so that the legend lists each architecture once.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import partial
from typing import IO, Any

import numpy as np
import rerun.blueprint as rrb

from fusionlog.core.decimate import decimate_evaluation
from fusionlog.core.evaluation import Evaluation
from fusionlog.core.linalg import overflow_is_inf

from .consistency_views import NisSeries, check_consistency, consistency_views, write_consistency
from .legend import legend_box, place_legend
from .log_recording import opening_range, plane_states, replay_blueprint, write_replay
from .plane import check_plane, write_plane
from .stream import SeriesWriter, check_axes, entity_path, recording_error, recording_stream
from .style import BOUND_COLOR, CKF, TRUTH_COLOR, arch_color, arch_width, class_color
from .trajectory import trajectory_tabs, write_trajectory
from .views import query, tabbed_blueprint, time_series_view

__all__ = ["write_evaluation", "write_recording"]

#: Per-architecture series: name -> shape, with s steps and n states.
_SHAPES = {
    "mse": "sn",
    "trace": "s",
    "nees": "s",
    "dm": "s",
    "expected_mse": "sn",
    "expected_nees": "s",
    "expected_dm": "s",
    "mse_minus_ckf": "sn",  # a decimated log's, decimated as drawn (core.decimate)
    "bound": "s",
}
_REQUIRED = ("mse", "trace", "nees", "dm")

SampleRuns = Mapping[int, tuple[np.ndarray, Mapping[str, tuple[np.ndarray, np.ndarray]]]]


def write_recording(
    file: IO[bytes],
    *,
    scenario_name: str,
    seed: int,
    times: np.ndarray,
    state_names: Sequence[str],
    series: Mapping[str, Mapping[str, np.ndarray]],
    summary: Mapping[str, Any],
    nees_bounds: tuple[np.ndarray, np.ndarray] | None = None,
    confidence: float | None = None,
    sample_runs: SampleRuns | None = None,
    properties: Mapping[str, Any] | None = None,
    recording_id: str | None = None,
    plane: Mapping[str, Any] | None = None,
    availability: Mapping[str, np.ndarray] | None = None,
    nis: NisSeries | None = None,
    traces: Mapping[str, np.ndarray] | None = None,
    measured: Mapping[int, Mapping[str, np.ndarray]] | None = None,
    pcrb: np.ndarray | None = None,
) -> None:
    """Write the evaluation recording into the binary file object `file`.

    times: (K+1,) seconds. series: {ARCH: {"mse": (K+1, n), "trace": (K+1,), "nees": (K+1,),
    "dm": (K+1,), optionally "expected_mse" (K+1, n), "expected_nees" (K+1,),
    "expected_dm" (K+1,)}} in the order the legend should list them.
    nees_bounds: (lower, upper), each (K+1,), of the run-averaged NEES at `confidence`.
    sample_runs: {run index: (truth (K+1, n), {ARCH: (mean (K+1, n), std (K+1, n))})}; the
    band drawn is mean +- 2 std.
    summary: the summary.json dict, stored as JSON in the property ``summary``.
    properties: more recording properties, e.g. {"scenario": TOML text, "provenance": {...}};
    a str value is stored as field ``text``, a mapping field by field (non-scalars as JSON).
    recording_id: defaults to :func:`~fusionlog.io.rrd.stream.recording_id_for` (name, seed).
    plane: for a 2-D state, the state-plane view (see :func:`.plane.write_plane`).
    availability: {sensor: (K+1,) share of runs measured, NaN where the sensor does not
    measure}, drawn in a "Sensors" tab.
    nis: {ARCH: {part: (run-averaged NIS, band lower, band upper)}} (`.consistency_views`).
    Without truth (a replay of a recorded log), `series` may be empty and `traces` ({ARCH:
    (K+1,) trace of P}) gives Fig. 6's curves. measured: {state index: {sensor: (K+1,)}},
    the first sample run's readings of sensors that measure a state directly (dots
    ``runs/0/<state>/measured/<sensor>`` under the estimates). pcrb: (K+1, n), the posterior
    Cramér-Rao bound on each state's MSE, drawn as a line on the MSE views.

    Raises FusionlogError if the data are inconsistent (before anything is written) and
    OutputError if writing `file` fails.
    """
    ev = Evaluation(
        dict(summary), times, tuple(state_names), confidence, dict(series), nees_bounds,
        dict(sample_runs or {}), plane, dict(availability or {}), dict(nis or {}),
        None if traces is None else dict(traces), dict(measured or {}), dict(properties or {}),
        pcrb,
    )  # fmt: skip
    write_evaluation(file, ev, scenario_name, seed, recording_id)


def write_evaluation(
    file: IO[bytes],
    ev: Evaluation,
    scenario_name: str | None = None,
    seed: int | None = None,
    recording_id: str | None = None,
) -> None:
    """Write the recording of an evaluation (`core.evaluation.Evaluation`) into `file`; the
    recording is named by the summary's scenario and seed unless given (see
    `write_recording` for what each part draws and the errors)."""
    if scenario_name is None:
        scenario_name, seed = ev.summary["scenario"], ev.summary["seed"]
    ev = decimate_evaluation(ev, CKF)  # a long log: a few 10^4 points per series
    times = np.asarray(ev.times, dtype=float)
    state_names = [str(s) for s in ev.state_names]
    series, nees_bounds, confidence, plane = ev.series, ev.nees_bounds, ev.confidence, ev.plane
    samples, summary, properties = ev.samples, ev.summary, ev.properties
    availability, nis, traces, measured = ev.availability, ev.nis, ev.traces, ev.measured
    pcrb = ev.pcrb
    _check(file, times, state_names, series, nees_bounds, samples)
    if pcrb is not None and np.shape(pcrb) != (times.shape[0], len(state_names)):
        raise recording_error(file, f"PCRB has shape {np.shape(pcrb)}, want (K+1, n)")
    if plane is not None:
        check_plane(file, times.shape[0], plane)
    avail = {k: np.asarray(v, dtype=float) for k, v in (availability or {}).items()}
    nis = nis or {}
    check_consistency(file, times.shape[0], nis, avail)
    # Instants k dt with dt = 1 read the same on both timelines; otherwise time is the axis.
    timeline = "step" if np.array_equal(times, np.arange(len(times))) else "time"
    traces = {a: np.asarray(t, dtype=float) for a, t in (traces or {}).items()}
    replay = ev.innovations is not None
    if replay:  # one recorded log: its own layout (io/rrd/log_recording.py)
        ij = plane_states(state_names, measured or {})
        all_traces = traces or {a: np.asarray(d["trace"], dtype=float) for a, d in series.items()}
        nees = {a: np.asarray(d["nees"], dtype=float) for a, d in series.items()}
        bound = {a: np.asarray(d["bound"], float) for a, d in series.items() if "bound" in d}
        blueprint = replay_blueprint(state_names, ij, samples, nis, ev.innovations, nees,
                                     nees_bounds, all_traces, timeline,
                                     trajectory_tabs(ev.trajectory), bound)  # fmt: skip
    else:
        extra = consistency_views(nis, avail, bool(traces)) + trajectory_tabs(ev.trajectory)
        blueprint = _blueprint(
            state_names, series, samples, plane is not None, extra, timeline, pcrb is not None
        )
    axes = None
    if ev.steps is not None:  # a long log's series, decimated before (core/decimate.py)
        axes = {"step": ("sequence", np.asarray(ev.steps)), "time": ("duration", times)}
        properties = {**(properties or {}), "decimation": dict(ev.decimation or {})}
    # A sensor's readings have one colour in every view (its place among the sensors, as in
    # the Sensors tab), not its place among the sensors of one state.
    sensors = dict.fromkeys([*avail, *(s for by in (measured or {}).values() for s in by)])
    sensor_color = {s: class_color(k) for k, s in enumerate(sensors)}
    args = (scenario_name, seed, times, summary, properties, recording_id)
    with recording_stream(file, blueprint, *args, axes=axes) as w:
        _write_metrics(w, state_names, series, nees_bounds, confidence)
        for i, state in enumerate(state_names if pcrb is not None else []):
            p = entity_path("metrics", "pcrb", "mse", state)
            w.line(p, np.asarray(pcrb, dtype=float)[:, i], "PCRB", BOUND_COLOR, 2.5)
        _write_sample_runs(w, state_names, samples, ev.bands)
        for i, by_sensor in (measured or {}).items():
            for sensor, v in by_sensor.items():
                p = entity_path("runs", 0, state_names[i], "measured", sensor)
                w.points(p, v, f"{sensor} (measured)", sensor_color[sensor])
        write_consistency(w, nis, avail, confidence)
        for arch, t in traces.items():
            w.line(
                entity_path("metrics", "trace", arch), t, arch, arch_color(arch), arch_width(arch)
            )
        if plane is not None:
            write_plane(w, plane)
        if replay:
            write_replay(w, ij, samples, measured or {}, ev.innovations, sensor_color)
        if ev.trajectory:
            write_trajectory(w, ev.trajectory, samples, ev.trajectory["positions"])


def _check(
    file: IO[bytes],
    times: np.ndarray,
    state_names: list[str],
    series: Mapping[str, Mapping[str, np.ndarray]],
    nees_bounds: tuple[np.ndarray, np.ndarray] | None,
    sample_runs: SampleRuns,
) -> None:
    s, n = check_axes(file, times, state_names, least=1, what="state names")
    bad = partial(recording_error, file)
    if "bounds" in series:
        raise bad("'bounds' cannot be an architecture name (metrics/nees/bounds is the band)")
    if "limit" in series:
        raise bad("'limit' cannot be an architecture name (metrics/bound/limit is the line 1)")
    for arch, d in series.items():
        for key in _REQUIRED:
            if key not in d:
                raise bad(f"architecture {arch}: missing series {key!r}")
        for key, arr in d.items():
            if key not in _SHAPES:
                raise bad(f"architecture {arch}: unknown series {key!r}")
            want = (s, n) if _SHAPES[key] == "sn" else (s,)
            if np.shape(arr) != want:
                raise bad(f"architecture {arch}: {key} has shape {np.shape(arr)}, want {want}")
    if nees_bounds is not None:
        for arr in nees_bounds:
            if np.shape(arr) != (s,):
                raise bad(f"NEES bounds have shape {np.shape(arr)}, want {(s,)}")
    for m, (truth, est) in sample_runs.items():
        if np.shape(truth) != (s, n):
            raise bad(f"sample run {m}: truth has shape {np.shape(truth)}, want {(s, n)}")
        for arch, (mean, std) in est.items():
            if np.shape(mean) != (s, n) or np.shape(std) != (s, n):
                raise bad(f"sample run {m}, {arch}: mean/std must have shape {(s, n)}")


@overflow_is_inf  # inf - inf: NaN, drawn as a gap
def _write_metrics(
    w: SeriesWriter,
    state_names: list[str],
    series: Mapping[str, Mapping[str, np.ndarray]],
    nees_bounds: tuple[np.ndarray, np.ndarray] | None,
    confidence: float | None,
) -> None:
    ckf = series.get(CKF)
    for arch, d in series.items():
        col, width = arch_color(arch), arch_width(arch)
        mse = np.asarray(d["mse"], dtype=float)
        for i, state in enumerate(state_names):
            w.line(entity_path("metrics", "mse", state, arch), mse[:, i], arch, col, width)
            if "mse_minus_ckf" in d:
                diff = np.asarray(d["mse_minus_ckf"], dtype=float)[:, i]
                p = entity_path("metrics", "mse_minus_ckf", state, arch)
                w.line(p, diff, f"{arch} − CKF", col, width)
            elif ckf is not None and arch != CKF:
                diff = mse[:, i] - np.asarray(ckf["mse"], dtype=float)[:, i]
                p = entity_path("metrics", "mse_minus_ckf", state, arch)
                w.line(p, diff, f"{arch} − CKF", col, width)
            if "expected_mse" in d:
                p = entity_path("metrics", "expected", "mse", state, arch)
                w.points(p, np.asarray(d["expected_mse"])[:, i], arch, col)
        w.line(entity_path("metrics", "trace", arch), d["trace"], arch, col, width)
        w.line(entity_path("metrics", "nees", arch), d["nees"], arch, col, width)
        w.line(entity_path("metrics", "dm", arch), d["dm"], arch, col, width)
        for key, metric in (("expected_nees", "nees"), ("expected_dm", "dm")):
            if key in d:
                w.points(entity_path("metrics", "expected", metric, arch), d[key], arch, col)
        if "bound" in d:
            w.line(entity_path("metrics", "bound", arch), d["bound"], arch, col, width)
    if any("bound" in d for d in series.values()):
        one = np.ones(len(next(iter(series.values()))["trace"]))
        w.line(
            entity_path("metrics", "bound", "limit"), one, "1: P bounds the error", BOUND_COLOR, 1.5
        )
    if nees_bounds is not None:
        label = f"χ² {confidence:.0%}" if confidence is not None else "χ²"
        for side, arr in zip(("lower", "upper"), nees_bounds, strict=True):
            p = entity_path("metrics", "nees", "bounds", side)
            w.line(p, arr, f"{label} {side}", BOUND_COLOR, 1.5)


def _write_sample_runs(
    w: SeriesWriter, state_names: list[str], sample_runs: SampleRuns, bands: Any = None
) -> None:
    """Each sample run: the truth, and per architecture the estimate with its ±2σ band (as
    given in `bands`, a decimated log's, else mean ∓ 2 std)."""
    for m in sorted(sample_runs):
        truth, est = sample_runs[m]
        truth = np.asarray(truth, dtype=float)
        for i, state in enumerate(state_names):
            w.line(entity_path("runs", m, state, "truth"), truth[:, i], "truth", TRUTH_COLOR, 2.5)
            for arch, (mean, std) in est.items():
                col = arch_color(arch)
                mu = np.asarray(mean, dtype=float)[:, i]
                sd = np.asarray(std, dtype=float)[:, i]
                base = ("runs", m, state, arch)
                w.line(entity_path(*base, "mean"), mu, arch, col, 2.0)
                # The band shares the estimate's legend entry (one toggle for both).
                lower, upper = mu - 2 * sd, mu + 2 * sd
                if bands and arch in bands.get(m, {}):
                    lower, upper = (np.asarray(v, dtype=float)[:, i] for v in bands[m][arch])
                w.line(entity_path(*base, "upper"), upper, arch, col, 0.75)
                w.line(entity_path(*base, "lower"), lower, arch, col, 0.75)


@overflow_is_inf  # inf - inf: NaN, drawn as a gap
def _blueprint(
    state_names: list[str],
    series: Mapping[str, Mapping[str, np.ndarray]],
    sample_runs: SampleRuns,
    plane: bool = False,
    extra_tabs: list | None = None,
    timeline: str = "step",
    pcrb: bool = False,
) -> rrb.Blueprint:
    """Tabs: [state plane], Overview (Figs. 4, 5, 6, NEES, DM), [sample runs]. Figs. 4-6
    open on the values after the start where its transient would flatten them (multirate.toml:
    `.log_recording.opening_range`), else on all of them.

    Colours are the same in every view, so each group of views (Fig. 4, Fig. 5, the sample
    runs) shows one legend, one entry per architecture (its line, dots and band share the
    name), on the view and in the corner where it hides the fewest curve points
    (:mod:`.legend`); the other views stay uncluttered."""
    archs = list(series)
    n = len(state_names)
    with_fig5 = CKF in archs and len(archs) > 1
    n_columns = 3 if with_fig5 else 2

    def legend(views: list[list[np.ndarray]], names: list[str], rows: int, cols: int):
        box = legend_box(len(names), max(map(len, names), default=0), rows, cols)
        return place_legend(views, box)

    def col(d: Mapping[str, np.ndarray], key: str, i: int) -> np.ndarray:
        return np.asarray(d[key], dtype=float)[:, i]

    mse = [
        [col(d, k, i) for d in series.values() for k in ("mse", "expected_mse") if k in d]
        for i in range(n)
    ]
    at4 = legend(mse, archs, n, n_columns)
    reference = "grey: PCRB" if pcrb else "dots: expected"
    fig4 = [
        time_series_view(
            f"Fig. 4: MSE of {s} (lines: Monte Carlo, {reference})",
            [query("metrics", "mse", s) + "/**", query("metrics", "expected", "mse", s) + "/**"]
            + ([query("metrics", "pcrb", "mse", s)] if pcrb else []),
            legend=i == at4[0],
            corner=at4[1],
            y_range=opening_range(mse[i], 0.0),
        )
        for i, s in enumerate(state_names)
    ]
    others = [a for a in archs if a != CKF]
    diff = (
        [[col(series[a], "mse", i) - col(series[CKF], "mse", i) for a in others] for i in range(n)]
        if with_fig5
        else []
    )
    at5 = legend(diff, [f"{a} − CKF" for a in others], n, n_columns)
    fig5 = [
        time_series_view(
            f"Fig. 5: MSE − MSE of CKF, {s}",
            [query("metrics", "mse_minus_ckf", s) + "/**"],
            legend=i == at5[0],
            corner=at5[1],
            y_range=opening_range(diff[i]) if diff else None,
        )
        for i, s in enumerate(state_names)
    ]
    traces = [np.asarray(d["trace"], dtype=float) for d in series.values()]
    fig6 = time_series_view("Fig. 6: trace of P", [query("metrics", "trace") + "/**"], False,
                            y_range=opening_range(traces, 0.0))  # fmt: skip
    nees = time_series_view(
        "NEES, run average (grey: χ² band)",
        [query("metrics", "nees") + "/**", query("metrics", "expected", "nees") + "/**"],
        legend=False,
    )
    dm = time_series_view(
        "Mahalanobis distance, run average",
        [query("metrics", "dm") + "/**", query("metrics", "expected", "dm") + "/**"],
        legend=False,
    )
    consistency = [fig6, nees, dm]
    if any("bound" in d for d in series.values()):  # DESIGN.md "the bound check"
        consistency.append(
            time_series_view(
                "bound check: λmax of P^-1 E[e e^T] (grey: 1; above it P does not bound the error)",
                [query("metrics", "bound") + "/**"],
                legend=False,  # the colours of Fig. 4's legend, as the NEES and DM views
            )
        )
    columns: list[rrb.Container] = [rrb.Vertical(*fig4, name="Fig. 4")]
    if with_fig5:
        columns.append(rrb.Vertical(*fig5, name="Fig. 5"))
    columns.append(rrb.Vertical(*consistency, name="Fig. 6 and consistency"))
    # Without truth (a recorded log) there are no Monte Carlo metrics: no Overview.
    tabs: list[rrb.Container | rrb.View] = (
        [rrb.Horizontal(*columns, name="Overview")] if series else []
    )
    run_ids = sorted(sample_runs)
    if run_ids:
        cells = [(m, i) for m in run_ids for i in range(n)]
        curves = []
        for m, i in cells:
            truth, est = sample_runs[m]
            c = [np.asarray(truth, dtype=float)[:, i]]
            for mean, std in est.values():
                mu, sd = np.asarray(mean, dtype=float)[:, i], np.asarray(std, dtype=float)[:, i]
                c += [mu, mu + 2 * sd, mu - 2 * sd]
            curves.append(c)
        names = ["truth", *sample_runs[run_ids[0]][1]]
        at = legend(curves, names, len(run_ids), n)
        run_views = [
            time_series_view(
                f"run {m}: {state_names[i]} (truth, estimate ± 2σ)",
                [query("runs", m, state_names[i]) + "/**"],
                legend=k == at[0],
                corner=at[1],
            )
            for k, (m, i) in enumerate(cells)
        ]
        tabs.append(rrb.Grid(*run_views, grid_columns=n, name="Sample runs"))
    tabs += extra_tabs or []
    if plane:
        tabs.insert(
            0,
            rrb.Spatial2DView(
                origin="/plane",
                name=f"State plane ({state_names[0]}, {state_names[1]}): estimates and ellipses",
            ),
        )
    return tabbed_blueprint(tabs, timeline)
