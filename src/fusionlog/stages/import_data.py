"""`fusionlog import`: a replay file's recorded data into an ordinary fusionlog sensors file.

The readings of every sensor (and of the optional truth) are read with the ecosystem's decoders
(:mod:`fusionlog.io.replay`), each stream's messages into an unnamed temporary file as they
come; the instants are the sorted union of the sensors' measurement times, merged from those
files a window at a time (:mod:`.import_windows`: memory that does not grow with the log,
issue 34); the file has one run, each sensor's topic a message only at its own instants (with its
covariance where R varies from message to message), times in seconds from the first instant,
and the recorded timestamps as ``log_time``. Where a message's covariance is all zero or not
positive definite (odometry drivers often leave it zero) the sensor's R applies, and the count
is reported. A sensor with ``arrival = "log_time"`` arrived when each message was logged: its
messages carry that time as their ``arrival`` field, and its latency is the range of the delays
(log time - `time`) read, so the estimate takes them as late (DESIGN.md "Late measurements").
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fusionlog.core.model import nominal_R_of
from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapWriter
from fusionlog.io.mcap.run_steps import RunColumn
from fusionlog.io.mcap.schema import VALUES
from fusionlog.io.mcap.topics import TRUTH, sensor_topic
from fusionlog.io.replay.rows import Rows
from fusionlog.scenario import Scenario, check_budget, scenario_with

from .common import PROVENANCE_META, SCENARIO_META, provenance, scenario_metadata, sha256_of
from .import_windows import TruthCursor, merged_windows
from .kinds import kind_of


@dataclass
class ImportResult:
    path: Path
    instants: int
    messages: int
    notes: list[str] = field(default_factory=list)


@dataclass
class _Sensor:
    """One sensor's readings (time-ordered records, `Rows`) and how they are written: with
    each message's covariance (`fill`: what replaces an unusable one) or None (the sensor's
    R), and with their arrival (their log times) or not."""

    rows: Rows
    fill: np.ndarray | float | None
    arrival: bool

    def window(self, b: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(values, covariances or None, arrivals ns or None) of records `b`."""
        cov = None
        if self.fill is not None:
            cov = _message_covs(b["c"], self.fill)
        arrival = None
        if self.arrival:
            arrival = b["t"] + np.maximum(b["r"] - b["t"], 0)
        return b["v"], cov, arrival


def _message_covs(c: np.ndarray, fill) -> np.ndarray:
    """Each message's R: its covariance used as its symmetric part (a driver's 1e-15
    asymmetry) where usable, else `fill`."""
    sym = 0.5 * (c + np.swapaxes(c, -1, -2))
    return np.where(_usable(c)[:, None, None], sym, fill)


def _read_all(replay, names: list[str]) -> tuple[list, list[str]]:
    """Every stream of the replay (sensors, then the truth) read, geodetic ones in ENU metres
    about one origin: each stream's own, else the first fix in time order of all geodetic
    streams without one (so that two receivers, or a receiver and an RTK truth, share a frame)."""
    from fusionlog.io.replay import read_streams, to_enu

    streams = list(replay.sensors) + ([replay.truth] if replay.truth is not None else [])
    whats = [f"sensors[{j}] ({n})" for j, n in enumerate(names)] + ["truth"]
    # every stream of one text table from one pass over it
    series = read_streams(
        [(st.source, st.reader_args(), what) for st, what in zip(streams, whats, strict=False)]
    )
    shared = [i for i, st in enumerate(streams) if st.geodetic and st.origin is None]
    # the shared origin's stream first: its first fix is the origin of the others
    order = sorted(shared, key=lambda i: series[i].rows.time_at(0))
    order += [i for i, st in enumerate(streams) if st.geodetic and st.origin is not None]
    origin = None
    notes = []
    for i in order:
        st = streams[i]
        given = st.origin if st.origin is not None else origin
        series[i], used = to_enu(st.source, whats[i], series[i], given)
        if st.origin is None:
            origin = used
        notes.append(
            f"{whats[i]}: geodetic fixes as ENU metres about latitude {used[0]:.9g}, "
            f"longitude {used[1]:.9g}, altitude {used[2]:.6g} m"
            + (" (the first fix)" if st.origin is None else "")
        )
    return series, notes


def replay_inputs(scenario: Scenario) -> list[Path]:
    """Every file the replay's readers open (a bag folder's .db3 files and metadata.yaml too,
    whichever of them is named): no output may be written onto one of them."""
    from fusionlog.io.replay import source_files

    replay = scenario.replay
    streams = list(replay.sensors) + ([replay.truth] if replay.truth is not None else [])
    return [f for st in streams for f in source_files(st.source)]


def sha256_of_source(path: Path) -> str:
    """A source's sha256: the file's, or for a ROS 2 bag folder the hash of its files' names
    and hashes (sorted)."""
    if not path.is_dir():
        return sha256_of(path)
    import hashlib

    h = hashlib.sha256()
    for f in sorted(p for p in path.iterdir() if p.is_file()):
        h.update(f"{f.name}\0{sha256_of(f)}\n".encode())
    return h.hexdigest()


def _usable(cov: np.ndarray) -> np.ndarray:
    """(N,) whether each covariance is a usable R: not all zero, symmetric, positive definite."""
    ok = np.isfinite(cov).all(axis=(-2, -1)) & (np.abs(cov).max(axis=(-2, -1)) > 0)
    # per message (one asymmetric matrix must not send every message to R)
    sym = np.isclose(cov, np.swapaxes(cov, -1, -2), rtol=1e-9, atol=0.0).all(axis=(-2, -1))
    ok &= sym
    # a variance below the smallest normal double (uninitialised memory: 1.6e-315) passes a
    # Cholesky factorisation but its inverse overflows: not a usable R either
    ok &= (np.diagonal(cov, axis1=-2, axis2=-1) >= np.finfo(np.float64).tiny).all(axis=-1)
    out = np.zeros(len(cov), dtype=bool)
    for i in np.flatnonzero(ok):
        try:
            np.linalg.cholesky(cov[i])
            out[i] = True
        except np.linalg.LinAlgError:
            pass
    return out


def _arrivals(what: str, s) -> tuple[bool, tuple[float, float], list[str]]:
    """Whether a sensor's messages carry their log times as arrivals, its latency (min, max)
    s, and a note. A message logged before its stamp (the two clocks disagree) arrived when it
    was measured: a filter cannot use a reading before it is taken. (The delays, 8 bytes a
    message, are held while their median is taken.)"""
    delay = np.concatenate([b["r"] - b["t"] for b in s.rows.blocks()])
    early = int(np.count_nonzero(delay < 0))
    delay = np.maximum(delay, 0)
    lo, hi = int(delay.min()), int(delay.max())
    notes = [
        f"{what}: arrival = log time: delays {lo / 1e6:.6g} to {hi / 1e6:.6g} ms (median "
        f"{float(np.median(delay)) / 1e6:.6g} ms) over {len(delay)} messages"
    ]
    if early:
        notes.append(
            f"{what}: {early} of {len(delay)} messages logged before their stamp (time): "
            "taken as arrived when measured"
        )
    return hi > 0, ((lo / 1e9, hi / 1e9) if hi else (0.0, 0.0)), notes


def _disjoint(names: list[str], times: list[str | None], series: list) -> list[str]:
    """A note when two sensors' readings do not overlap in time: the filters then predict
    across the whole gap. Usually one `time` is a header stamp and the other the log/record
    time (drivers stamp with another clock, or a bag was recorded days later)."""
    if len(series) < 2:
        return []
    a = max(range(len(series)), key=lambda j: series[j].rows.time_at(0))  # starts last
    b = min(range(len(series)), key=lambda j: series[j].rows.time_at(-1))  # ends first
    gap = series[a].rows.time_at(0) - series[b].rows.time_at(-1)
    if gap <= 0:
        return []

    def clock(j: int) -> str:
        return f"time = {times[j]!r}" if times[j] is not None else "the default time"

    days = f" ({gap / 86400e9:.3g} days)" if gap >= 86400 * 10**9 else ""
    return [
        f"{names[a]} and {names[b]} do not overlap in time: {names[a]}'s first reading is "
        f"{gap / 1e9:.6g} s{days} after {names[b]}'s last ({names[a]}: {clock(a)}, {names[b]}: "
        f"{clock(b)}); the filters predict across that gap"
    ]


class Window(NamedTuple):
    """A window of instants: k0, the instants (w,) ns, each sensor's readings there (instant
    index within the window, values, covariances or None, arrivals ns or None), and the truth
    (instant index within the window, values (., n)) or None."""

    k0: int
    instants: np.ndarray
    sensors: list[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]]
    truth: tuple[np.ndarray, np.ndarray] | None


@dataclass
class ReplayData:
    """A replay's data: the scenario with its steps (and any nominal R) set, the number of
    instants and the first (ns), notes, and the readings on the instants window by window
    (`windows`, read back from the streams' temporary files each time)."""

    scenario: Scenario
    count: int
    first_ns: int
    notes: list[str]
    sensors: list[_Sensor]
    truth_rows: Rows | None
    truth_info: dict = field(default_factory=dict)  # {states, matched, unmatched}, with a truth

    def windows(self) -> Iterator[Window]:
        replay, system = self.scenario.replay, self.scenario.system
        cursor = None
        if self.truth_rows is not None:
            cursor = TruthCursor(self.truth_rows, replay.match, replay.max_diff_ns)
        k0 = 0
        for m in merged_windows([s.rows for s in self.sensors]):
            sensors = []
            for sen, b in zip(self.sensors, m.records, strict=True):
                sensors.append((np.searchsorted(m.instants, b["t"]), *sen.window(b)))
            truth = None
            if cursor is not None:
                at_instants = cursor.at(m.instants)
                matched = np.isfinite(at_instants).all(axis=1)
                values = np.full((int(matched.sum()), system.n), np.nan)
                values[:, list(replay.truth_states)] = at_instants[matched]
                truth = (np.flatnonzero(matched), values)
            yield Window(k0, m.instants, sensors, truth)
            k0 += len(m.instants)


def _sensor_R(j: int, sen, s, source) -> tuple[np.ndarray, np.ndarray | float | None, list[str]]:
    """A sensor's nominal R, what replaces an unusable message covariance (None: the messages
    carry none, or none that differs from R) and a note; passes over its records."""
    R = sen.R
    if not s.rows.has("c"):
        return R, None, []
    bad = total = 0
    for b in s.rows.blocks():
        good = _usable(b["c"])
        bad, total = bad + int((~good).sum()), total + len(good)
    if bad and not np.isfinite(R).all():
        raise FusionlogError(
            f"{source}: sensors[{j}] ({sen.name}): {bad} of {total} messages have a "
            "covariance that is all zero or not positive definite, and the sensor has no R "
            "to apply there: give R"
        )
    notes = []
    if bad:
        notes.append(
            f"{sen.name}: {bad} of {total} messages with an all-zero or not positive definite "
            "covariance: R applied"
        )
    fill = R if np.isfinite(R).all() else 0.0
    if not np.isfinite(R).all():  # a sensor given by its messages alone: their mean
        R = nominal_R_of(_message_covs(b["c"], fill) for b in s.rows.blocks())
    same = all(
        np.array_equal(c, np.broadcast_to(R, c.shape))
        for c in (_message_covs(b["c"], fill) for b in s.rows.blocks())
    )
    return R, (None if same else fill), notes


def read_replay(scenario: Scenario) -> ReplayData:
    """Read every stream of the replay `scenario` (each into an unnamed temporary file) and
    learn its instants: their count and the first, and the truth's matches (one pass over
    the merged streams); the readings are placed on the instants by `ReplayData.windows`."""
    replay = scenario.replay
    system = scenario.system
    names = [sen.name for sen in system.sensors]
    series, notes = _read_all(replay, names)
    for name, s in zip(names + ["truth"], series, strict=False):
        notes += [f"{name}: {n}" for n in s.notes]
    sensor_series = series[: len(names)]
    notes += _disjoint(names, [replay.sensors[j].time for j in range(len(names))], sensor_series)
    sensors: list[_Sensor] = []
    nominal = []
    latencies = []
    for j, (sen, s) in enumerate(zip(system.sensors, sensor_series, strict=True)):
        R, fill, more = _sensor_R(j, sen, s, replay.sensors[j].source)
        notes += more
        nominal.append(R)
        arrival, latency = False, (0.0, 0.0)
        if replay.sensors[j].arrival:
            arrival, latency, more = _arrivals(sen.name, s)
            notes += more
        latencies.append(latency)
        sensors.append(_Sensor(s.rows, fill, arrival))
    t = series[-1] if replay.truth is not None else None
    cursor = TruthCursor(t.rows, replay.match, replay.max_diff_ns) if t is not None else None
    count, first, last, n_matched = 0, 0, 0, 0
    for m in merged_windows([s.rows for s in sensors]):
        if not count:
            first = int(m.instants[0])
        count, last = count + len(m.instants), int(m.instants[-1])
        if cursor is not None:
            n_matched += int(np.isfinite(cursor.at(m.instants)).all(axis=1).sum())
    truth_info: dict = {}
    if t is not None:
        states = [system.state_names[i] for i in replay.truth_states]
        truth_info = {"states": states, "matched": n_matched, "unmatched": count - n_matched}
        if not n_matched:
            within = (
                "at an instant"
                if replay.match == "exact"
                else f"within max_diff = {replay.max_diff_ns / 1e9:g} s of an instant"
            )
            raise FusionlogError(
                f"{replay.truth.source}: truth: none of its {len(t)} samples is {within} "
                f"of the sensors (match = {replay.match!r}; the sensors' instants span "
                f"{first}..{last} ns, the truth {t.rows.time_at(0)}..{t.rows.time_at(-1)} ns)"
            )
        if n_matched < count:
            notes.append(
                f"truth: {count - n_matched} of {count} instants without a truth "
                f"sample (match = {replay.match!r}): not in the truth metrics"
            )
    new_sensors = tuple(
        dataclasses.replace(
            sen, R=np.asarray(R), timing=dataclasses.replace(sen.timing, latency=lat)
        )
        for sen, R, lat in zip(system.sensors, nominal, latencies, strict=True)
    )
    sc = dataclasses.replace(scenario, system=dataclasses.replace(system, sensors=new_sensors))
    sc = scenario_with(sc, steps=count - 1)
    rows = t.rows if t is not None else None
    return ReplayData(sc, count, first, notes, sensors, rows, truth_info)


def import_to(data: ReplayData, w: McapWriter, *, command: str) -> int:
    """Write a replay's data as a sensors file into an open writer whose time_origin_ns is
    the first instant (`run_import`), window by window; returns the message count."""
    sc, notes = data.scenario, data.notes
    kind = kind_of(sc.kind)
    check_budget(sc, kind.bytes_per_run_step(sc), "importing")
    meta = scenario_metadata(sc, kind.system_fields(sc))
    meta["replay_notes"] = json.dumps(notes)
    if data.truth_info:
        meta["replay_truth"] = json.dumps(data.truth_info)
    w.add_metadata(SCENARIO_META, meta)
    sources = sorted({str(s.source) for s in sc.replay.sensors}
                     | ({str(sc.replay.truth.source)} if sc.replay.truth else set()))  # fmt: skip
    extra = {f"source_sha256:{p}": sha256_of_source(Path(p)) for p in sources}
    w.add_metadata(PROVENANCE_META, provenance(command, None, sources=json.dumps(sources), **extra))
    topics = [sensor_topic(s.name) for s in sc.system.sensors]
    if any(s.arrival for s in data.sensors):  # late sensors: the schema says arrival
        w.declare_arrival()
    # every message in instant order, the truth first at an instant, then the sensors in
    # their order, each topic where it has a reading: a window of instants at a time, encoded
    # at once (`McapWriter.write_run_steps`, the bytes of one `write_values` per message)
    messages = 0
    for win in data.windows():
        streams = [(TRUTH, *win.truth, None, None)] if win.truth is not None else []
        streams += [(topics[j], *r) for j, r in enumerate(win.sensors)]
        n = len(win.instants)
        columns, present = [], np.zeros((n, len(streams)), dtype=bool)
        for c, (topic, rows, values, cov, arrival_ns) in enumerate(streams):
            present[rows, c] = True
            parts = []
            for x in (values, cov, arrival_ns):
                part = None
                if x is not None:
                    part = np.zeros((n, *x.shape[1:]), dtype=x.dtype)
                    part[rows] = x
                parts.append(part)
            arrival = None
            if parts[2] is not None:  # s from the first instant, as the times
                arrival = (parts[2] - data.first_ns).astype(np.float64) / 1e9
            columns.append(RunColumn(topic, VALUES, parts[0], parts[1], arrival))
        times = (win.instants - data.first_ns) / 1e9
        w.write_run_steps(win.k0, times, columns, present)
        messages += int(np.count_nonzero(present))
    return messages


def run_import(
    scenario: Scenario, out: Path, *, force: bool = False, command: str = "fusionlog import"
) -> ImportResult:
    """Import the replay `scenario` into the sensors file `out` (committed only when complete)."""
    if scenario.replay is None:
        raise FusionlogError(
            f"{scenario.path or scenario.name}: not a replay file (no [[sensors]] with a source)"
        )
    out = Path(out)
    inputs = [Path(scenario.path)] if scenario.path else []
    inputs += replay_inputs(scenario)
    with Outputs([out], force=force, inputs=inputs) as outs:
        data = read_replay(scenario)
        instants, notes = data.count, data.notes
        with McapWriter(outs.open(out), time_origin_ns=data.first_ns) as w:
            messages = import_to(data, w, command=command)
        outs.commit()
    return ImportResult(out, instants, messages, notes)
