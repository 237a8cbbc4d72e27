"""The evaluation recording (.rrd): metric time series, sample runs, summary, default layout.

Layout of the recording (all series sent with ``send_columns``; timelines ``step`` (sequence)
and ``time`` (duration, seconds)). ``<state>`` and ``<ARCH>`` are escaped entity-path parts
(see :func:`entity_path`; ``SKF:s2`` becomes ``SKF\\:s2``):

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
``runs/<m>/<state>/truth``                      true state of sample run m
``runs/<m>/<state>/<ARCH>/mean``                estimate of sample run m
``runs/<m>/<state>/<ARCH>/upper``, ``/lower``   mean +- 2 sigma
=============================================  ============================================

Steps where a value is not finite (undefined estimate) are simply not logged. Monte Carlo
curves are lines (``SeriesLines``), expected curves are markers (``SeriesPoints``) in the same
colour. Recording properties: ``scenario`` (name, seed, and the scenario text if given),
``summary`` (field ``json``: the summary table as JSON), and any further ``properties``.
"""

from __future__ import annotations

import contextlib
import json
import os
import uuid
import warnings
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from fusionlog.errors import FusionlogError
from fusionlog.jsonout import dumps

__all__ = [
    "APPLICATION_ID",
    "arch_color",
    "entity_path",
    "read_recording",
    "recording_id_for",
    "write_recording",
]

APPLICATION_ID = "fusionlog"

#: Stable colours (Tableau 10) per architecture; unknown names get one from a hash of the name.
_PALETTE: dict[str, tuple[int, int, int]] = {
    "CKF": (31, 119, 180),
    "HKF": (255, 127, 14),
    "MSC-GMF": (44, 160, 44),
    "MSC": (214, 39, 40),
    "SKF": (148, 103, 189),
    "CI": (140, 86, 75),
    "FBS": (227, 119, 194),
    "BAYES": (188, 189, 34),
    "DS": (23, 190, 207),
}
_EXTRA = [
    (174, 199, 232),
    (255, 187, 120),
    (152, 223, 138),
    (255, 152, 150),
    (197, 176, 213),
    (196, 156, 148),
    (247, 182, 210),
    (219, 219, 141),
    (158, 218, 229),
]
_TRUTH_COLOR = (230, 230, 230)
_BOUND_COLOR = (150, 150, 150)
_INPUT_COLOR = (140, 140, 140)
_CKF = "CKF"


def arch_color(arch: str) -> tuple[int, int, int]:
    """The fixed colour of an architecture in every plot (deterministic across runs)."""
    if arch in _PALETTE:
        return _PALETTE[arch]
    return _EXTRA[zlib.crc32(arch.encode()) % len(_EXTRA)]


def _width(arch: str) -> float:
    # The CKF is drawn wider so that an architecture that coincides with it (HKF) stays visible.
    return 4.0 if arch == _CKF else 2.0


def entity_path(*parts: str | int) -> str:
    """Entity path (no leading slash) from unescaped parts, as keys of `read_recording` series."""
    return "/".join(rr.escape_entity_path_part(str(p)) for p in parts)


def recording_id_for(scenario_name: str, seed: int) -> str:
    """Deterministic recording id from the scenario name and the seed."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"fusionlog:{scenario_name}:{seed}"))


# ---------------------------------------------------------------------------------------- write
def write_recording(
    path: str | os.PathLike[str],
    *,
    scenario_name: str,
    seed: int,
    times: np.ndarray,
    state_names: Sequence[str],
    series: Mapping[str, Mapping[str, np.ndarray]],
    summary: Mapping[str, Any],
    nees_bounds: tuple[np.ndarray, np.ndarray] | None = None,
    confidence: float | None = None,
    sample_runs: Mapping[int, tuple[np.ndarray, Mapping[str, tuple[np.ndarray, np.ndarray]]]]
    | None = None,
    properties: Mapping[str, Any] | None = None,
    recording_id: str | None = None,
    plane: Mapping[str, Any] | None = None,
    force: bool = False,
) -> Path:
    """Write the evaluation recording atomically; returns the final path.

    times: (K+1,) seconds. series: {ARCH: {"mse": (K+1, n), "trace": (K+1,), "nees": (K+1,),
    "dm": (K+1,), optionally "expected_mse" (K+1, n), "expected_nees" (K+1,),
    "expected_dm" (K+1,)}} in the order the legend should list them.
    nees_bounds: (lower, upper), each (K+1,), of the run-averaged NEES at `confidence`.
    sample_runs: {run index: (truth (K+1, n), {ARCH: (mean (K+1, n), std (K+1, n))})}.
    summary: the summary.json dict, stored as JSON in the property ``summary``.
    properties: more recording properties, e.g. {"scenario": TOML text, "provenance": {...}};
    a str value is stored as field ``text``, a mapping field by field (non-scalars as JSON).
    recording_id: defaults to :func:`recording_id_for` (scenario name, seed).
    plane: for a 2-D state, the state-plane view (the slides' plot2): {"truth": (K+1, 2),
    "estimates": {ARCH: (K+1, P, 2) sample estimates}, "ellipses": {label: (K+1, 2, 2)
    covariances, drawn centred on the truth}, "scale": ellipse radius in standard deviations}.

    Raises FusionlogError if `path` exists and not `force` (before anything is written), or if
    the data are inconsistent.
    """
    path = Path(path)
    _check_target(path, force)
    times = np.asarray(times, dtype=float)
    state_names = [str(s) for s in state_names]
    _check_inputs(path, times, state_names, series, nees_bounds, sample_runs)
    blueprint = _blueprint(state_names, list(series), sorted(sample_runs or {}), plane is not None)
    with _recording_file(path, scenario_name, seed, recording_id, blueprint) as rec:
        _send_properties(rec, scenario_name, seed, summary, properties)
        writer = _Writer(rec, times)
        writer.write_all(state_names, series, nees_bounds, confidence, sample_runs or {})
        if plane is not None:
            writer.write_plane(plane)
    return path


def _check_target(path: Path, force: bool) -> None:
    """Refuse an existing output without `force` (before anything is written)."""
    if path.exists() and not force:
        raise FusionlogError(f"{path}: already exists (use --force to overwrite)")
    if path.exists() and path.is_dir():
        raise FusionlogError(f"{path}: is a directory")


@contextlib.contextmanager
def _recording_file(
    path: Path,
    scenario_name: str,
    seed: int,
    recording_id: str | None,
    blueprint: rrb.Blueprint,
) -> Iterator[rr.RecordingStream]:
    """A recording stream (fusionlog application id, deterministic recording id, recording name
    set) saving to a temporary file beside `path`, renamed into place when the block completes
    and deleted if it raises. Shared by every recording writer (state and identity)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.tmp"
    rec = rr.RecordingStream(
        APPLICATION_ID,
        recording_id=recording_id or recording_id_for(scenario_name, seed),
        send_properties=False,  # no wall-clock start_time: identical inputs give identical data
    )
    try:
        rec.save(tmp, default_blueprint=blueprint)
        rec.send_recording_name(scenario_name)
        yield rec
        rec.disconnect()
        os.replace(tmp, path)
    except BaseException:
        try:
            rec.disconnect()
        finally:
            tmp.unlink(missing_ok=True)
        raise


def _check_inputs(
    path: Path,
    times: np.ndarray,
    state_names: list[str],
    series: Mapping[str, Mapping[str, np.ndarray]],
    nees_bounds: tuple[np.ndarray, np.ndarray] | None,
    sample_runs: Mapping[int, Any] | None,
) -> None:
    s, n = times.shape[0] if times.ndim == 1 else -1, len(state_names)

    def bad(msg: str) -> FusionlogError:
        return FusionlogError(f"{path}: cannot write recording: {msg}")

    if times.ndim != 1 or s < 1:
        raise bad(f"times must be a non-empty 1-D array, got shape {times.shape}")
    if len(set(state_names)) != n or n == 0:
        raise bad(f"state names must be unique and non-empty, got {state_names}")
    if "bounds" in series:
        raise bad("'bounds' cannot be an architecture name (metrics/nees/bounds is the band)")
    shapes = {
        "mse": (s, n),
        "trace": (s,),
        "nees": (s,),
        "dm": (s,),
        "expected_mse": (s, n),
        "expected_nees": (s,),
        "expected_dm": (s,),
    }
    for arch, d in series.items():
        for key in ("mse", "trace", "nees", "dm"):
            if key not in d:
                raise bad(f"architecture {arch}: missing series {key!r}")
        for key, arr in d.items():
            if key not in shapes:
                raise bad(f"architecture {arch}: unknown series {key!r}")
            if np.shape(arr) != shapes[key]:
                raise bad(
                    f"architecture {arch}: {key} has shape {np.shape(arr)}, want {shapes[key]}"
                )
    if nees_bounds is not None:
        for arr in nees_bounds:
            if np.shape(arr) != (s,):
                raise bad(f"NEES bounds have shape {np.shape(arr)}, want {(s,)}")
    for m, (truth, est) in (sample_runs or {}).items():
        if np.shape(truth) != (s, n):
            raise bad(f"sample run {m}: truth has shape {np.shape(truth)}, want {(s, n)}")
        for arch, (mean, std) in est.items():
            if np.shape(mean) != (s, n) or np.shape(std) != (s, n):
                raise bad(f"sample run {m}, {arch}: mean/std must have shape {(s, n)}")


def _property_value(v: Any) -> str:
    """Every property field is a string: Rerun types a field name once for all properties, so
    `seed` as an int in one property and a string in another would be dropped with a warning."""
    if isinstance(v, str):
        return v
    return dumps(v, sort_keys=True, default=str)


def _send_properties(
    rec: rr.RecordingStream,
    scenario_name: str,
    seed: int,
    summary: Mapping[str, Any],
    properties: Mapping[str, Any] | None,
) -> None:
    props: dict[str, dict[str, Any]] = {"scenario": {"name": scenario_name, "seed": str(seed)}}
    for key, value in (properties or {}).items():
        fields = (
            {str(k): _property_value(v) for k, v in value.items()}
            if isinstance(value, Mapping)
            else {"text": _property_value(value)}
        )
        props.setdefault(str(key), {}).update(fields)
    props["summary"] = {"json": dumps(summary)}  # strict JSON; keeps the arch order
    for key in sorted(props):
        rec.send_property(key, rr.AnyValues(**props[key]))


class _Writer:
    def __init__(self, rec: rr.RecordingStream, times: np.ndarray) -> None:
        self.rec = rec
        self.times = times
        self.steps = np.arange(times.shape[0], dtype=np.int64)
        # Many entities share a style (an architecture's colour and name across states) and
        # most series are defined at every step: build those column batches once.
        self._styles: dict[tuple, Any] = {}
        self._full_index = self._index(np.ones(times.shape[0], dtype=bool))

    def _index(self, keep: np.ndarray) -> list[rr.TimeColumn]:
        return [
            rr.TimeColumn("step", sequence=self.steps[keep]),
            rr.TimeColumn("time", duration=self.times[keep]),
        ]

    # Styling goes out with send_columns and no index (= static), so that it lands in the file
    # right before its series instead of being batched; one unbatched chunk each, in order.
    def style_lines(self, path: str, name: str, color: Sequence[int], width: float) -> None:
        key = ("lines", name, tuple(color), width)
        if key not in self._styles:
            self._styles[key] = rr.SeriesLines.columns(
                names=[name], colors=[list(color)], widths=[width]
            )
        self.rec.send_columns(path, indexes=[], columns=self._styles[key], strict=True)

    def style_points(self, path: str, name: str, color: Sequence[int]) -> None:
        key = ("points", name, tuple(color))
        if key not in self._styles:
            self._styles[key] = rr.SeriesPoints.columns(
                names=[name], colors=[list(color)], markers=["circle"], marker_sizes=[2.5]
            )
        self.rec.send_columns(path, indexes=[], columns=self._styles[key], strict=True)

    def send(self, path: str, values: np.ndarray) -> None:
        values = np.asarray(values, dtype=float)
        keep = np.isfinite(values)
        if keep.all():
            indexes = self._full_index
        elif keep.any():
            indexes, values = self._index(keep), values[keep]
        else:
            return
        self.rec.send_columns(
            path, indexes=indexes, columns=rr.Scalars.columns(scalars=values), strict=True
        )

    def line(self, path: str, values: np.ndarray, name: str, color: Sequence[int], width: float):
        self.style_lines(path, name, color, width)
        self.send(path, values)

    def points(self, path: str, values: np.ndarray, name: str, color: Sequence[int]) -> None:
        self.style_points(path, name, color)
        self.send(path, values)

    def write_all(
        self,
        state_names: list[str],
        series: Mapping[str, Mapping[str, np.ndarray]],
        nees_bounds: tuple[np.ndarray, np.ndarray] | None,
        confidence: float | None,
        sample_runs: Mapping[int, tuple[np.ndarray, Mapping[str, tuple[np.ndarray, np.ndarray]]]],
    ) -> None:
        ckf = series.get(_CKF)
        for arch, d in series.items():
            col, w = arch_color(arch), _width(arch)
            mse = np.asarray(d["mse"], dtype=float)
            for i, state in enumerate(state_names):
                self.line(entity_path("metrics", "mse", state, arch), mse[:, i], arch, col, w)
                if ckf is not None and arch != _CKF:
                    diff = mse[:, i] - np.asarray(ckf["mse"], dtype=float)[:, i]
                    p = entity_path("metrics", "mse_minus_ckf", state, arch)
                    self.line(p, diff, f"{arch} − CKF", col, w)
                if "expected_mse" in d:
                    p = entity_path("metrics", "expected", "mse", state, arch)
                    self.points(p, np.asarray(d["expected_mse"])[:, i], f"{arch} expected", col)
            self.line(entity_path("metrics", "trace", arch), d["trace"], arch, col, w)
            self.line(entity_path("metrics", "nees", arch), d["nees"], arch, col, w)
            self.line(entity_path("metrics", "dm", arch), d["dm"], arch, col, w)
            for key, metric in (("expected_nees", "nees"), ("expected_dm", "dm")):
                if key in d:
                    p = entity_path("metrics", "expected", metric, arch)
                    self.points(p, d[key], f"{arch} expected", col)
        if nees_bounds is not None:
            label = f"χ² {confidence:.0%}" if confidence is not None else "χ²"
            for side, arr in zip(("lower", "upper"), nees_bounds, strict=True):
                p = entity_path("metrics", "nees", "bounds", side)
                self.line(p, arr, f"{label} {side}", _BOUND_COLOR, 1.5)
        for m in sorted(sample_runs):
            truth, est = sample_runs[m]
            truth = np.asarray(truth, dtype=float)
            for i, state in enumerate(state_names):
                p = entity_path("runs", m, state, "truth")
                self.line(p, truth[:, i], "truth", _TRUTH_COLOR, 2.5)
                for arch, (mean, std) in est.items():
                    col = arch_color(arch)
                    mu = np.asarray(mean, dtype=float)[:, i]
                    sd = np.asarray(std, dtype=float)[:, i]
                    self.line(entity_path("runs", m, state, arch, "mean"), mu, arch, col, 2.0)
                    self.line(
                        entity_path("runs", m, state, arch, "upper"),
                        mu + 2 * sd,
                        f"{arch} +2σ",
                        col,
                        0.75,
                    )
                    self.line(
                        entity_path("runs", m, state, arch, "lower"),
                        mu - 2 * sd,
                        f"{arch} −2σ",
                        col,
                        0.75,
                    )

    def write_plane(self, plane: Mapping[str, Any]) -> None:
        """The state plane: truth, sample estimates and covariance ellipses, one frame a step."""
        K1 = self.steps.shape[0]
        indexes = [
            rr.TimeColumn("step", sequence=self.steps),
            rr.TimeColumn("time", duration=self.times),
        ]
        truth = np.asarray(plane["truth"], dtype=float).reshape(K1, 2)
        self.rec.send_columns(
            entity_path("plane", "truth"),
            indexes=[],
            columns=rr.Points2D.columns(colors=[_TRUTH_COLOR], radii=[0.012], labels=["truth"]),
        )
        self.rec.send_columns(
            entity_path("plane", "truth"),
            indexes=indexes,
            columns=rr.Points2D.columns(positions=truth).partition(np.ones(K1, dtype=int)),
        )
        for arch, pts in plane.get("estimates", {}).items():
            pts = np.asarray(pts, dtype=float)
            path = entity_path("plane", "estimates", arch)
            self.rec.send_columns(
                path,
                indexes=[],
                columns=rr.Points2D.columns(colors=[arch_color(arch)], radii=[0.004]),
            )
            keep = np.isfinite(pts).all(axis=-1)
            self.rec.send_columns(
                path,
                indexes=indexes,
                columns=rr.Points2D.columns(positions=pts[keep]).partition(keep.sum(axis=1)),
            )
        angle = np.linspace(0.0, 2.0 * np.pi, 97)
        circle = np.stack([np.cos(angle), np.sin(angle)], axis=-1) * float(plane.get("scale", 2.0))
        for label, covs in plane.get("ellipses", {}).items():
            covs = np.asarray(covs, dtype=float).reshape(K1, 2, 2)
            ok = np.isfinite(covs).all(axis=(1, 2))
            if not ok.any():
                continue
            # x = truth + L u for u on the circle, L L^T = P: the ellipse of P around the truth.
            w, V = np.linalg.eigh(covs[ok])
            L = V * np.sqrt(np.clip(w, 0.0, None))[:, None, :]
            strips = truth[ok][:, None, :] + np.einsum("kij,pj->kpi", L, circle)
            arch = label.removeprefix("input ")
            color = arch_color(arch) if label == arch else _INPUT_COLOR
            path = entity_path("plane", "ellipses", label)
            self.rec.send_columns(
                path,
                indexes=[],
                columns=rr.LineStrips2D.columns(
                    colors=[color], radii=[0.003], labels=[label], show_labels=[False]
                ),
            )
            self.rec.send_columns(
                path,
                indexes=[
                    rr.TimeColumn("step", sequence=self.steps[ok]),
                    rr.TimeColumn("time", duration=self.times[ok]),
                ],
                columns=rr.LineStrips2D.columns(strips=list(strips)),
            )


def _ts_view(name: str, contents: list[str], legend: bool = True) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(
        origin="/",
        contents=contents,
        name=name,
        plot_legend=rrb.PlotLegend(corner="RightTop", visible=legend),
    )


def _blueprint(
    state_names: list[str], archs: list[str], run_ids: list[int], plane: bool = False
) -> rrb.Blueprint:
    def q(*parts: str | int) -> str:
        return "+ /" + entity_path(*parts)

    # Colours are the same in every view, so only the first MSE view carries the full legend
    # (lines: Monte Carlo, dots: expected); the small views stay uncluttered.
    fig4 = [
        _ts_view(
            f"Fig. 4: MSE of {s} (lines: Monte Carlo, dots: expected)",
            [q("metrics", "mse", s) + "/**", q("metrics", "expected", "mse", s) + "/**"],
            legend=i == 0,
        )
        for i, s in enumerate(state_names)
    ]
    fig5 = [
        _ts_view(
            f"Fig. 5: MSE − MSE of CKF, {s}",
            [q("metrics", "mse_minus_ckf", s) + "/**"],
            legend=i == 0,
        )
        for i, s in enumerate(state_names)
    ]
    fig6 = _ts_view("Fig. 6: trace of P", [q("metrics", "trace") + "/**"], legend=False)
    nees = _ts_view(
        "NEES, run average (grey: χ² band)",
        [q("metrics", "nees") + "/**", q("metrics", "expected", "nees") + "/**"],
        legend=False,
    )
    dm = _ts_view(
        "Mahalanobis distance, run average",
        [q("metrics", "dm") + "/**", q("metrics", "expected", "dm") + "/**"],
        legend=False,
    )
    columns: list[rrb.Container] = [rrb.Vertical(*fig4, name="Fig. 4")]
    if _CKF in archs and len(archs) > 1:
        columns.append(rrb.Vertical(*fig5, name="Fig. 5"))
    columns.append(rrb.Vertical(fig6, nees, dm, name="Fig. 6 and consistency"))
    tabs: list[rrb.Container | rrb.View] = [rrb.Horizontal(*columns, name="Overview")]
    if run_ids:
        run_views = [
            _ts_view(
                f"run {m}: {s} (truth, estimate ± 2σ)",
                [q("runs", m, s) + "/**"],
                legend=j == 0 and i == 0,
            )
            for j, m in enumerate(run_ids)
            for i, s in enumerate(state_names)
        ]
        tabs.append(rrb.Grid(*run_views, grid_columns=len(state_names), name="Sample runs"))
    if plane:
        tabs.insert(
            0,
            rrb.Spatial2DView(
                origin="/plane",
                name=f"State plane ({state_names[0]}, {state_names[1]}): estimates and ellipses",
            ),
        )
    return rrb.Blueprint(
        rrb.Tabs(*tabs, active_tab=0),
        rrb.TimePanel(timeline="step", state="collapsed", play_state="paused"),
        collapse_panels=True,
    )


# ----------------------------------------------------------------------------------------- read
def read_recording(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read an evaluation recording offline (no viewer, no network).

    Returns {"application_id", "recording_id", "name", "properties": {property: {field: value}},
    "summary": dict, "steps": (S,) int array, "times": (S,) float seconds,
    "series": {entity path (see `entity_path`): (S,) float array, NaN where not logged}}
    with S the union of logged steps, sorted. Raises FusionlogError (one line) if the file is
    missing, unreadable or not a fusionlog recording.
    """
    from rerun.chunk import RrdReader

    path = Path(path)
    if not path.is_file():
        raise FusionlogError(f"{path}: no such file")
    try:
        with warnings.catch_warnings():
            # a damaged file first warns "no footer", then fails below: report only the failure
            warnings.simplefilter("ignore")
            reader = RrdReader(str(path))
            stores = [s for s in reader.recordings() if s.kind == "recording"]
            chunks = list(reader.store().stream().to_chunks())
    except Exception as exc:  # the Rust reader raises assorted errors on damaged files
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FusionlogError(f"{path}: not a readable Rerun recording ({reason})") from None
    if not stores:
        raise FusionlogError(f"{path}: contains no recording")

    properties: dict[str, dict[str, Any]] = {}
    name = None
    raw: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for ch in chunks:
        ent = str(ch.entity_path)
        rb = ch.to_record_batch()
        cols = {c: rb.column(c) for c in rb.schema.names if c != "rerun.controls.RowId"}
        if ent == "/__properties" or ent.startswith("/__properties/"):
            if ent == "/__properties":
                if "RecordingInfo:name" in cols:
                    name = cols["RecordingInfo:name"].to_pylist()[-1][0]
                continue
            prop = ent.removeprefix("/__properties/")
            fields = properties.setdefault(prop, {})
            for c, arr in cols.items():
                vals = arr.to_pylist()[-1]
                fields[c] = vals[0] if isinstance(vals, list) and len(vals) == 1 else vals
            continue
        if ch.is_static or "Scalars:scalars" not in cols or "step" not in cols:
            continue
        steps = cols["step"].to_numpy(zero_copy_only=False).astype(np.int64)
        if "time" in cols:
            t = cols["time"].cast("int64").to_numpy(zero_copy_only=False) / 1e9
        else:
            t = np.full(steps.shape, np.nan)
        vals = cols["Scalars:scalars"].flatten().to_numpy(zero_copy_only=False).astype(float)
        if vals.shape != steps.shape:
            continue  # not one scalar per row: not one of ours
        raw.setdefault(ent.lstrip("/"), []).append((steps, t, vals))

    if "summary" not in properties or "json" not in properties["summary"]:
        raise FusionlogError(f"{path}: not a fusionlog recording (no summary property)")
    try:
        summary = json.loads(properties["summary"]["json"])
    except (TypeError, ValueError) as exc:
        raise FusionlogError(f"{path}: corrupt summary property ({exc})") from None

    all_steps = (
        np.unique(np.concatenate([s for parts in raw.values() for s, _, _ in parts]))
        if raw
        else np.zeros(0, dtype=np.int64)
    )
    times = np.full(all_steps.shape, np.nan)
    series: dict[str, np.ndarray] = {}
    for ent, parts in raw.items():
        out = np.full(all_steps.shape, np.nan)
        for steps, t, vals in parts:
            idx = np.searchsorted(all_steps, steps)
            out[idx] = vals
            times[idx] = t
        series[ent] = out
    return {
        "application_id": stores[0].application_id,
        "recording_id": stores[0].recording_id,
        "name": name,
        "properties": properties,
        "summary": summary,
        "steps": all_steps,
        "times": times,
        "series": dict(sorted(series.items())),
    }
