"""`fusionlog import`: a replay file's recorded data into an ordinary fusionlog sensors file.

The readings of every sensor (and of the optional truth) are read with the ecosystem's decoders
(:mod:`fusionlog.io.replay`); the instants are the sorted union of the sensors' measurement
times; the file has one run, each sensor's topic a message only at its own instants (with its
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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusionlog.core.model import nominal_R
from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapWriter
from fusionlog.io.mcap.run_steps import RunColumn
from fusionlog.io.mcap.schema import VALUES
from fusionlog.io.mcap.topics import TRUTH, sensor_topic
from fusionlog.scenario import Scenario, check_budget, scenario_with

from .common import PROVENANCE_META, SCENARIO_META, provenance, scenario_metadata, sha256_of
from .kinds import kind_of

_WINDOW = 1 << 16  # instants written at once (a few MB of rows)


@dataclass
class ImportResult:
    path: Path
    instants: int
    messages: int
    notes: list[str] = field(default_factory=list)


@dataclass
class _Sensor:
    """One sensor's readings on the instants: where it measures, its values and covariances."""

    at: np.ndarray  # (N,) instant indices
    values: np.ndarray  # (N, d)
    cov: np.ndarray | None  # (N, d, d), the R of every message, or None: the sensor's R
    arrival_ns: np.ndarray | None = None  # (N,) when each reading arrived, or None: on time


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
    order = sorted(shared, key=lambda i: int(series[i].times_ns[0]))
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


def _arrivals(what: str, s) -> tuple[np.ndarray | None, tuple[float, float], list[str]]:
    """A sensor's arrivals (N,) ns at its messages' log times, its latency (min, max) s, and a
    note. A message logged before its stamp (the two clocks disagree) arrived when it was
    measured: a filter cannot use a reading before it is taken."""
    delay = s.record_ns - s.times_ns
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
    if hi == 0:
        return None, (0.0, 0.0), notes
    return s.times_ns + delay, (lo / 1e9, hi / 1e9), notes


def _disjoint(names: list[str], times: list[str | None], series: list) -> list[str]:
    """A note when two sensors' readings do not overlap in time: the filters then predict
    across the whole gap. Usually one `time` is a header stamp and the other the log/record
    time (drivers stamp with another clock, or a bag was recorded days later)."""
    if len(series) < 2:
        return []
    a = max(range(len(series)), key=lambda j: int(series[j].times_ns[0]))  # starts last
    b = min(range(len(series)), key=lambda j: int(series[j].times_ns[-1]))  # ends first
    gap = int(series[a].times_ns[0]) - int(series[b].times_ns[-1])
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


@dataclass
class ReplayData:
    """A replay's data on its instants: the scenario with its steps (and any nominal R) set,
    the instants (ns), each sensor's readings, the truth ({at, values} or {}), notes."""

    scenario: Scenario
    instants: np.ndarray
    sensors: list[_Sensor]
    truth: dict
    notes: list[str]
    truth_info: dict = field(default_factory=dict)  # {states, matched, unmatched}, with a truth


def read_replay(scenario: Scenario) -> ReplayData:
    """Read every stream of the replay `scenario` and place the readings on the instants."""
    from fusionlog.core.associate import associate

    replay = scenario.replay
    system = scenario.system
    names = [sen.name for sen in system.sensors]
    series, notes = _read_all(replay, names)
    for name, s in zip(names + ["truth"], series, strict=False):
        notes += [f"{name}: {n}" for n in s.notes]
    sensor_series = series[: len(names)]
    notes += _disjoint(names, [replay.sensors[j].time for j in range(len(names))], sensor_series)
    # the sorted union by a sort (numpy 2.4's np.unique hashes: 2 s for 2·10^6 times)
    every = np.concatenate([s.times_ns for s in sensor_series])
    every.sort()  # in place: one array of the readings' times, not two
    instants = every[np.concatenate(([True], every[1:] != every[:-1]))]
    del every
    sensors: list[_Sensor] = []
    nominal = []
    latencies = []
    for j, (sen, s) in enumerate(zip(system.sensors, sensor_series, strict=True)):
        at = np.searchsorted(instants, s.times_ns)
        cov = None
        R = sen.R
        if s.cov is not None:
            good = _usable(s.cov)
            bad = int((~good).sum())
            if bad and not np.isfinite(R).all():
                raise FusionlogError(
                    f"{replay.sensors[j].source}: sensors[{j}] ({sen.name}): {bad} of "
                    f"{len(good)} messages have a covariance that is all zero or not positive "
                    "definite, and the sensor has no R to apply there: give R"
                )
            if bad:
                notes.append(
                    f"{sen.name}: {bad} of {len(good)} messages with an all-zero or not "
                    "positive definite covariance: R applied"
                )
            # symmetric to rounding (a driver's 1e-15 asymmetry): used as its symmetric part
            sym = 0.5 * (s.cov + np.swapaxes(s.cov, -1, -2))
            cov = np.where(good[:, None, None], sym, R if np.isfinite(R).all() else 0.0)
            if not np.isfinite(R).all():
                R = nominal_R(cov)  # a sensor given by its messages alone
            if np.array_equal(cov, np.broadcast_to(R, cov.shape)):
                cov = None  # R does not vary: no per-message covariance needed
        nominal.append(R)
        arrival, latency = None, (0.0, 0.0)
        if replay.sensors[j].arrival:
            arrival, latency, more = _arrivals(sen.name, s)
            notes += more
        latencies.append(latency)
        sensors.append(_Sensor(at, s.values, cov, arrival))
        series[j] = sensor_series[j] = s = None  # its times (8 bytes a reading) freed: `at` now
    truth: dict = {}
    truth_info: dict = {}
    if replay.truth is not None:
        t = series[-1]
        # a window of instants at a time: each instant's sample is found on its own, and the
        # search's temporaries (~50 bytes per instant) stay a window's
        at_instants = np.empty((len(instants), t.values.shape[1]))
        for k0 in range(0, len(instants), _WINDOW):
            at_instants[k0 : k0 + _WINDOW] = associate(
                instants[k0 : k0 + _WINDOW], t.times_ns, t.values, replay.match, replay.max_diff_ns
            )
        matched = np.isfinite(at_instants).all(axis=1)
        n_matched = int(matched.sum())
        states = [system.state_names[i] for i in replay.truth_states]
        truth_info = {"states": states, "matched": n_matched,
                      "unmatched": int(len(instants) - n_matched)}  # fmt: skip
        if not n_matched:
            within = (
                "at an instant"
                if replay.match == "exact"
                else f"within max_diff = {replay.max_diff_ns / 1e9:g} s of an instant"
            )
            raise FusionlogError(
                f"{replay.truth.source}: truth: none of its {len(t.times_ns)} samples is {within} "
                f"of the sensors (match = {replay.match!r}; the sensors' instants span "
                f"{instants[0]}..{instants[-1]} ns, the truth {t.times_ns[0]}..{t.times_ns[-1]} ns)"
            )
        if n_matched < len(instants):
            notes.append(
                f"truth: {len(instants) - n_matched} of {len(instants)} instants without a truth "
                f"sample (match = {replay.match!r}): not in the truth metrics"
            )
        values = np.full((n_matched, system.n), np.nan)
        values[:, list(replay.truth_states)] = at_instants[matched]
        truth = {"at": np.flatnonzero(matched), "values": values}
    new_sensors = tuple(
        dataclasses.replace(
            sen, R=np.asarray(R), timing=dataclasses.replace(sen.timing, latency=lat)
        )
        for sen, R, lat in zip(system.sensors, nominal, latencies, strict=True)
    )
    sc = dataclasses.replace(scenario, system=dataclasses.replace(system, sensors=new_sensors))
    sc = scenario_with(sc, steps=len(instants) - 1)
    return ReplayData(sc, instants, sensors, truth, notes, truth_info)


def import_to(data: ReplayData, w: McapWriter, *, command: str) -> int:
    """Write a replay's data as a sensors file into an open writer whose time_origin_ns is
    the first instant (`run_import`); returns the message count."""
    sc, instants, sensors, truth, notes = (
        data.scenario,
        data.instants,
        data.sensors,
        data.truth,
        data.notes,
    )
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
    if any(s.arrival_ns is not None for s in sensors):  # late sensors: the schema says arrival
        w.declare_arrival()
    # every message in instant order, the truth first at an instant, then the sensors in
    # their order, each topic where it has a reading: a window of instants at a time, encoded
    # at once (`McapWriter.write_run_steps`, the bytes of one `write_values` per message)
    streams = [(TRUTH, truth["at"], truth["values"], None, None)] if truth else []
    streams += [(topics[j], s.at, s.values, s.cov, s.arrival_ns) for j, s in enumerate(sensors)]
    messages = 0
    for k0 in range(0, len(instants), _WINDOW):
        k1 = min(len(instants), k0 + _WINDOW)
        columns, present = [], np.zeros((k1 - k0, len(streams)), dtype=bool)
        for c, (topic, at, values, cov, arrival_ns) in enumerate(streams):
            a, b = np.searchsorted(at, [k0, k1])
            rows = at[a:b] - k0
            present[rows, c] = True
            parts = []
            for x in (values, cov, arrival_ns):
                part = None
                if x is not None:
                    part = np.zeros((k1 - k0, *x.shape[1:]), dtype=x.dtype)
                    part[rows] = x[a:b]
                parts.append(part)
            arrival = None
            if parts[2] is not None:  # s from the first instant, as the times
                arrival = (parts[2] - instants[0]).astype(np.float64) / 1e9
            columns.append(RunColumn(topic, VALUES, parts[0], parts[1], arrival))
        times = (instants[k0:k1] - instants[0]) / 1e9  # a window's: the same numbers
        w.write_run_steps(k0, times, columns, present)
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
        instants, notes = len(data.instants), data.notes
        with McapWriter(outs.open(out), time_origin_ns=int(data.instants[0])) as w:
            messages = import_to(data, w, command=command)
            data = None  # the readings freed before the writer's layout record is formed
        outs.commit()
    return ImportResult(out, instants, messages, notes)
