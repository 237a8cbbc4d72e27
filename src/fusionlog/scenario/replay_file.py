"""Replay files: a state scenario whose sensors come from recorded data (DESIGN.md, "Replay files").

    [scenario]   name, description, state_names, dt (optional: the nominal step of the
                 constant-velocity kind's N0 = n0 dt; default 1 s). No steps, runs, seed: one
                 run, whose instants are the measurement times found in the data.
    [model]      kind = "constant-velocity" (n0, axes) or "continuous" (A, Qc): a model that
                 can be discretised for any interval.
    [prior]      mean, cov (optional: without it the filters start with no information).
    [[sensors]]  name, H, and where the readings are: source (relative to the replay file: an
                 MCAP, a ROS 1 .bag, a ROS 2 bag folder or its .db3, or a text table of any
                 extension), topic (MCAP and bags), values (field paths, or column names),
                 time (optional field or column; default the log/record time or the column
                 `time`), time_unit (s, ms, us, ns); for tables delimiter, columns and
                 format = "tum"; geodetic = true (values are latitude, longitude[, altitude]:
                 converted to ENU metres) with origin = [lat, lon, alt] (default the first
                 fix); R, or covariance (a field holding a flat square covariance) with
                 covariance_index (its rows/columns of `values`), R then applying where a
                 message's matrix is all zero or not positive definite; arrival = "log_time"
                 (MCAP and bags, with `time`): each message arrived when it was logged, its
                 delay the log time minus `time` (DESIGN.md "Late measurements").
    [truth]      optional: the stream keys above, states (the state names those values are:
                 some or all), match = "nearest" | "interpolate" | "exact" and max_diff (s,
                 default 0.01): turns on the truth-based metrics, over the truthed states.
    [estimate], [evaluate] as in a scenario.

A replay is a scenario of the state kind with one run (`Scenario.replay` says where its data
are); `fusionlog import` reads the data into an ordinary sensors file.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from decimal import Decimal
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog.core.model import Sensor, System
from fusionlog.core.timing import MAX_PERIOD_S, MIN_PERIOD_S, TIME_UNITS
from fusionlog.errors import ValidationError

from . import estimate_keys, toml
from .latency import late_section
from .model_section import model_section
from .scenario_base import Header
from .sensors import sensor_matrices
from .state_file import (
    StateScenario,
    architectures_section,
    check_determined,
    correlations_section,
    evaluate_section,
    full_resolution_of,
    prior_section,
)
from .toml import Ctx
from .trajectory import trajectory_section

__all__ = ["Replay", "ReplayScenario", "Stream", "is_replay_doc", "replay_from_doc"]

_TOP_KEYS = ("scenario", "model", "prior", "truth", "sensors", "correlations", "estimate",
             "evaluate")  # fmt: skip
_SCENARIO_KEYS = ("name", "description", "state_names", "dt")
_STREAM_KEYS = ("source", "topic", "values", "time", "time_unit", "delimiter", "columns", "format",
                "geodetic", "origin")  # fmt: skip
_SENSOR_REQUIRED = ("name", "H", "source", "values")
_SENSOR_OPTIONAL = _STREAM_KEYS[2:] + ("topic", "R", "covariance", "covariance_index", "arrival")
#: the values of a replay sensor's ``arrival``: where its messages' arrival times are
ARRIVALS = ("log_time",)
MATCHES = ("nearest", "interpolate", "exact")
FORMATS = ("tum",)


@dataclass(frozen=True)
class Stream:
    """Where one stream of readings is: a file (resolved against the replay file's folder), an
    MCAP topic, the value fields, the time field and unit, the covariance field and rows."""

    source: Path
    topic: str | None
    values: tuple[str, ...]
    time: str | None = None
    time_unit: str = "s"
    covariance: str | None = None
    covariance_index: tuple[int, ...] | None = None
    delimiter: str | None = None
    columns: tuple[str, ...] | None = None
    format: str | None = None
    geodetic: bool = False
    origin: tuple[float, float, float] | None = None
    #: arrival = "log_time": each message arrived at its log (record) time
    arrival: bool = False

    def reader_args(self) -> dict[str, Any]:
        """The keyword arguments of `fusionlog.io.replay.read_series` besides the source."""
        return {k: getattr(self, k) for k in ("topic", "values", "time", "time_unit",
                                              "covariance", "covariance_index", "delimiter",
                                              "columns", "format")}  # fmt: skip


@dataclass(frozen=True)
class Replay:
    """The recorded data of a replay: one stream per sensor (in the system's order), the
    optional truth stream and the state indices its values are."""

    sensors: tuple[Stream, ...]
    truth: Stream | None = None
    truth_states: tuple[int, ...] = ()
    match: str = "nearest"  # how truth samples are associated with the instants
    max_diff_ns: int = 10_000_000  # the largest time difference of an associated sample


@dataclass(frozen=True, eq=False)
class ReplayScenario(StateScenario):
    """A state scenario whose sensors' readings are recorded (`replay`: where they are and how
    they are read): one run on the measurement times."""

    replay: Replay = None  # type: ignore[assignment] - always given (replay_from_doc)

    def check_overrides(self, file: str, given: list[str]) -> None:
        """As scenario.runs/steps/seed in the file: refused, never ignored."""
        if given:
            raise ValidationError(
                f"{file}: {', '.join(given)}: not used with a replay file (one recorded run; "
                "the instants are the measurement times)"
            )


def is_replay_doc(doc: dict[str, Any]) -> bool:
    """A scenario document whose sensors name a `source`."""
    sensors = doc.get("sensors")
    return isinstance(sensors, list) and any(isinstance(t, dict) and "source" in t for t in sensors)


def _source_kind(path: Path) -> str:
    from fusionlog.io.replay import source_kind  # the readers: only replay files need them

    return source_kind(path)


def _text_keys(ctx: Ctx, t: dict[str, Any], where: str, kind: str) -> dict[str, Any]:
    """delimiter, columns and format of a text table (refused for other sources)."""
    out: dict[str, Any] = {}
    for key in ("delimiter", "columns", "format"):
        if key in t and kind != "text":
            raise ctx.err(f"{where}.{key}", f"only used with a text table, not with {kind} sources")
    if "delimiter" in t:
        d = t["delimiter"]
        if not isinstance(d, str) or not (len(d) == 1 or d == "whitespace") or d in '\n\r"#':
            raise ctx.err(
                f"{where}.delimiter",
                f"expected one character (',', '\\t', ';' ...) or 'whitespace', got {toml.show(d)}",
            )
        out["delimiter"] = "whitespace" if d == " " else d
    if "columns" in t:
        c = t["columns"]
        if (
            not isinstance(c, list)
            or len(c) < 2
            or not all(isinstance(x, str) and x.strip() for x in c)
        ):
            raise ctx.err(
                f"{where}.columns",
                f"expected a list of at least 2 column names, got {toml.show(c)}",
            )
        names = [x.strip() for x in c]
        dup = sorted({x for x in names if names.count(x) > 1})
        if dup:
            raise ctx.err(f"{where}.columns", f"names a column twice: {dup[0]!r}")
        out["columns"] = tuple(names)
    if "format" in t:
        f = toml.string(ctx, t["format"], f"{where}.format")
        if f not in FORMATS:
            raise ctx.err(f"{where}.format", f"unknown format {f!r} (known: {', '.join(FORMATS)})")
        if "columns" in t:
            raise ctx.err(
                f"{where}.columns", "not used with format = 'tum' (its columns are fixed)"
            )
        out["format"] = f
    return out


def _geodetic(ctx: Ctx, t: dict[str, Any], where: str, d: int) -> dict[str, Any]:
    if "geodetic" not in t:
        if "origin" in t:
            raise ctx.err(f"{where}.origin", "only used with geodetic = true")
        return {}
    g = t["geodetic"]
    if not isinstance(g, bool):
        raise ctx.err(f"{where}.geodetic", f"expected true or false, got {toml.show(g)}")
    if not g:
        if "origin" in t:
            raise ctx.err(f"{where}.origin", "only used with geodetic = true")
        return {}
    if d not in (2, 3):
        raise ctx.err(
            f"{where}.values",
            f"{d} values with geodetic = true: give [latitude, longitude] or "
            "[latitude, longitude, altitude] (degrees, degrees, metres)",
        )
    out: dict[str, Any] = {"geodetic": True}
    if "origin" in t:
        o = t["origin"]
        if not isinstance(o, list) or len(o) != 3 or not all(toml.is_number(x) for x in o):
            raise ctx.err(
                f"{where}.origin",
                "expected [latitude, longitude, altitude] (degrees, degrees, metres), "
                f"got {toml.show(o)}",
            )
        lat, lon, alt = (float(x) for x in o)
        if not abs(lat) <= 90:
            raise ctx.err(f"{where}.origin", f"latitude {toml.fmt(lat)} is outside ±90 degrees")
        if not abs(lon) <= 180:
            raise ctx.err(f"{where}.origin", f"longitude {toml.fmt(lon)} is outside ±180 degrees")
        if not abs(alt) < 1e7:
            raise ctx.err(f"{where}.origin", f"altitude {toml.fmt(alt)} m is not an altitude")
        out["origin"] = (lat, lon, alt)
    return out


def _stream(ctx: Ctx, t: dict[str, Any], where: str, base: Path) -> Stream:
    source = toml.string(ctx, t["source"], f"{where}.source")
    path = base / source
    kind = _source_kind(path)
    if kind == "text" and path.is_dir():  # not "a topic for a text table": say what is wrong
        raise ctx.err(
            f"{where}.source",
            f"{str(path)!r} is a folder but not a ROS 2 bag (no metadata.yaml)",
        )
    topic = None
    if kind != "text":
        if "topic" not in t:
            raise ctx.err(f"{where}.topic", f"missing required key (an {kind} source needs it)")
        topic = toml.string(ctx, t["topic"], f"{where}.topic")
    elif "topic" in t:
        raise ctx.err(
            f"{where}.topic",
            f"only used with an MCAP or bag source ({source!r} is read as a text table)",
        )
    values = t["values"]
    if (
        not isinstance(values, list)
        or not values
        or not all(isinstance(v, str) and v.strip() for v in values)
    ):
        raise ctx.err(
            f"{where}.values", f"expected a non-empty list of field names, got {toml.show(values)}"
        )
    time = toml.string(ctx, t["time"], f"{where}.time") if "time" in t else None
    unit = toml.string(ctx, t.get("time_unit", "s"), f"{where}.time_unit")
    if unit not in TIME_UNITS:
        raise ctx.err(f"{where}.time_unit", f"unknown unit {unit!r} (known: s, ms, us, ns)")
    extra = _text_keys(ctx, t, where, kind) | _geodetic(ctx, t, where, len(values))
    degrees = [v for v in values if v.strip().split(".")[-1].lower() in ("latitude", "longitude")]
    if degrees and not extra.get("geodetic"):
        # a GNSS fix in degrees read as metres makes every NIS ~1e-10: never silently
        raise ctx.err(
            f"{where}.values",
            f"{degrees[0].strip()!r} is in degrees: give geodetic = true (with values "
            "[latitude, longitude, altitude]) to use the fixes as local east-north-up metres",
        )
    if "columns" in extra:
        for v in values + ([time] if time is not None else []):
            if v.strip() not in extra["columns"]:
                raise ctx.err(
                    f"{where}.values", toml.unknown_msg("column", v.strip(), extra["columns"])
                )
    return Stream(path, topic, tuple(v.strip() for v in values), time, unit, **extra)


def _arrival(ctx: Ctx, t: dict[str, Any], where: str, stream: Stream) -> bool:
    """``arrival = "log_time"``: the sensor's messages arrived when they were logged, taken
    at `time` (a header stamp); only where the source has log times and `time` is a field."""
    if "arrival" not in t:
        return False
    key = f"{where}.arrival"
    a = toml.string(ctx, t["arrival"], key)
    if a not in ARRIVALS:
        raise ctx.err(key, f"unknown arrival {a!r} (known: {', '.join(ARRIVALS)})")
    if stream.topic is None:
        raise ctx.err(
            key,
            f"{stream.source.name!r} is read as a text table, which has no log time (only MCAP "
            "files and bags log when each message was received)",
        )
    if stream.time is None:
        raise ctx.err(
            key,
            "without `time` the measurement time is the log time itself (no delay): give "
            "time, the field stamped when the message was measured (e.g. 'header.stamp')",
        )
    return True


def _late_probe(ctx: Ctx, system: System, streams: list[Stream]) -> System:
    """The system as the estimation will see it once the delays are read (`arrival` sensors
    late by an unknown delay): refused in one line where late measurements cannot be
    estimated (`core.late_policy.system_refusal`), and the architectures checked against it."""
    from fusionlog.core.late_policy import system_refusal
    from fusionlog.core.timing import SensorTiming

    late = [j for j, st in enumerate(streams) if st.arrival]
    sensors = tuple(
        replace(s, timing=SensorTiming(latency=(0.0, 1.0))) if j in late else s
        for j, s in enumerate(system.sensors)
    )
    probe = replace(system, sensors=sensors)
    if late and (why := system_refusal(probe)) is not None:
        key, reason = why
        where = f"sensors[{late[0]}].arrival" if key.endswith(".latency") else key
        raise ctx.err(where, f"a sensor with arrival = 'log_time' is late: {reason}")
    return probe


def _covariance(ctx: Ctx, t: dict[str, Any], where: str, m: int) -> tuple[str | None, Any]:
    if "covariance" not in t:
        if "covariance_index" in t:
            raise ctx.err(f"{where}.covariance_index", "only used with covariance")
        return None, None
    field = toml.string(ctx, t["covariance"], f"{where}.covariance")
    if "covariance_index" not in t:
        # never a default of [0..m-1]: the data say whether the matrix is exactly m x m (else
        # the reader asks for covariance_index instead of reading the wrong entries)
        return field, None
    idx = t["covariance_index"]
    if (
        not isinstance(idx, list)
        or len(idx) != m
        or not all(type(i) is int and i >= 0 for i in idx)
        or len(set(idx)) != m
    ):
        raise ctx.err(
            f"{where}.covariance_index",
            f"expected {m} distinct indices >= 0 (rows of the covariance for the {m} values), "
            f"got {toml.show(idx)}",
        )
    return field, tuple(idx)


def replay_from_doc(
    doc: dict[str, Any], file: str, source: str, path: str | None, *, recorded: bool = False
) -> ReplayScenario:
    """A replay scenario from a parsed TOML document (`file` names it in errors; sources are
    relative to the folder of `path`, or of `file` when there is no path; `recorded`: the
    record of a sensors file, `Ctx`)."""
    ctx = Ctx(file, recorded)
    base = Path(path if path is not None else file).parent
    toml.check_keys(ctx, doc, "(top level)", _TOP_KEYS, what="section")
    sc = toml.table(ctx, doc, "scenario", required=True)
    for key in ("steps", "runs", "seed"):
        if key in sc:
            raise ctx.err(
                f"scenario.{key}",
                "not used in a replay (one run; the instants are the measurement times)",
            )
    toml.check_keys(ctx, sc, "scenario", _SCENARIO_KEYS)
    if "name" not in sc:
        raise ctx.err("scenario.name", "missing required key")
    name = toml.name(ctx, sc["name"], "scenario.name")
    description = toml.string(ctx, sc.get("description", ""), "scenario.description")
    dt = 1.0
    if "dt" in sc:
        dt = toml.number(ctx, sc["dt"], "scenario.dt")
        if not dt > 0:
            raise ctx.err("scenario.dt", f"must be > 0, got {toml.fmt(dt)}")
    names = None
    if "state_names" in sc:
        names = toml.names_list(ctx, sc["state_names"], "scenario.state_names")
    md = toml.table(ctx, doc, "model", required=True)
    if "kind" not in md:
        raise ctx.err(
            "model.kind",
            "a replay's instants are irregular: give kind = 'constant-velocity' (n0, axes) or "
            "'continuous' (A, Qc), not F and Q",
        )
    F, Q, G, state_names, dt, continuous = model_section(ctx, doc, names, dt)
    n = F.shape[0]
    prior = prior_section(ctx, doc, F)

    sensors: list[Sensor] = []
    streams: list[Stream] = []
    tables = toml.named_tables(
        ctx, doc, "sensors", _SENSOR_REQUIRED, " (name, H, source, values)", _SENSOR_OPTIONAL
    )
    for where, t, sname in tables:
        H, R = sensor_matrices(ctx, t, where, n)
        cov_field, cov_index = _covariance(ctx, t, where, H.shape[0])
        if R is None and cov_field is None:
            raise ctx.err(f"{where}.R", "missing: give R, or covariance (a field of the data)")
        stream = _stream(ctx, t, where, base)
        if len(stream.values) != H.shape[0]:
            raise ctx.err(
                f"{where}.values",
                f"{len(stream.values)} values, but H has {H.shape[0]} rows",
            )
        streams.append(replace(stream, covariance=cov_field, covariance_index=cov_index,
                               arrival=_arrival(ctx, t, where, stream)))  # fmt: skip
        # Without R the sensor's nominal R is set when the data are read (from the messages'
        # own covariances); NaN until then.
        m = H.shape[0]
        sensors.append(Sensor(sname, H, R if R is not None else np.full((m, m), np.nan)))
    truth, truth_states, match, max_diff_ns = _truth(ctx, doc, base, state_names)
    cross_R = correlations_section(ctx, doc, tuple(sensors))
    system = System(F=F, Q=Q, G=G, sensors=tuple(sensors), prior=prior, cross_R=cross_R, dt=dt,
                    state_names=state_names, continuous=continuous,
                    ci_criterion=estimate_keys.ci_criterion(ctx, doc),
                    late=late_section(ctx, doc))  # fmt: skip
    check_determined(ctx, system)
    architectures = architectures_section(ctx, doc, _late_probe(ctx, system, streams))
    confidence, sample_runs, plane_view = evaluate_section(ctx, doc)
    if plane_view and n != 2:
        raise ctx.err("evaluate.plane_view", f"needs a 2-D state, this one has {n}")
    h = Header(name, description, 0, 1, 0, dt)
    return ReplayScenario.of(
        h,
        system,
        dt=dt,
        state_names=state_names,
        architectures=architectures,
        confidence=confidence,
        sample_runs=min(sample_runs, 1),
        plane_view=plane_view,
        full_resolution=full_resolution_of(ctx, doc),
        source=source,
        path=path,
        replay=Replay(tuple(streams), truth, truth_states, match, max_diff_ns),
        trajectory=trajectory_section(
            ctx, doc, state_names, [state_names[i] for i in truth_states] if truth else None
        ),
    )


def _truth(
    ctx: Ctx, doc: dict[str, Any], base: Path, state_names: tuple[str, ...]
) -> tuple[Stream | None, tuple[int, ...], str, int]:
    tr = toml.table(ctx, doc, "truth", required=False)
    if tr is None:
        return None, (), "nearest", 0
    toml.check_keys(ctx, tr, "truth", _STREAM_KEYS + ("states", "match", "max_diff"),
                    required=("source", "values", "states"))  # fmt: skip
    stream = _stream(ctx, tr, "truth", base)
    states = toml.names_list(ctx, tr["states"], "truth.states")
    for s in states:
        if s not in state_names:
            raise ctx.err("truth.states", toml.unknown_msg("state", s, state_names))
    if len(set(states)) != len(states):
        raise ctx.err("truth.states", "names a state twice")
    if len(states) != len(stream.values):
        raise ctx.err(
            "truth.states", f"{len(states)} states for {len(stream.values)} values (one each)"
        )
    match = toml.string(ctx, tr.get("match", "nearest"), "truth.match")
    if match not in MATCHES:
        raise ctx.err("truth.match", f"unknown match {match!r} (known: {', '.join(MATCHES)})")
    max_diff = 0.01
    if "max_diff" in tr:
        if match == "exact":
            raise ctx.err("truth.max_diff", "not used with match = 'exact'")
        max_diff = toml.number(ctx, tr["max_diff"], "truth.max_diff")
        # the range of a sensor's period (`core.timing`): whole nanoseconds, far inside the
        # 64-bit nanosecond clock
        if not MIN_PERIOD_S <= max_diff <= MAX_PERIOD_S:
            raise ctx.err(
                "truth.max_diff",
                f"must be > 0 seconds, from {toml.fmt(MIN_PERIOD_S)} (one nanosecond, the "
                f"resolution of a log's time) to {toml.fmt(MAX_PERIOD_S)} (about 31.7 years), "
                f"got {toml.fmt(max_diff)}",
            )
    max_diff_ns = round(Decimal(repr(max_diff)) * 1_000_000_000)
    return stream, tuple(state_names.index(s) for s in states), match, max_diff_ns
