"""`fusionlog import`: a replay file's recorded data into an ordinary fusionlog sensors file.

The readings of every sensor (and of the optional truth) are read with the ecosystem's decoders
(:mod:`fusionlog.io.replay`); the instants are the sorted union of the sensors' measurement
times; the file has one run, each sensor's topic a message only at its own instants (with its
covariance where R varies from message to message), times in seconds from the first instant,
and the recorded timestamps as ``log_time``. Where a message's covariance is all zero or not
positive definite (odometry drivers often leave it zero) the sensor's R applies, and the count
is reported.
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
from fusionlog.io.mcap.topics import TRUTH, sensor_topic
from fusionlog.scenario import Scenario, Stream, check_budget, scenario_with

from .common import PROVENANCE_META, SCENARIO_META, provenance, scenario_metadata, sha256_of
from .kinds import kind_of


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


def _read(stream: Stream, what: str):
    from fusionlog.io.replay import read_series  # the decoders: only an import needs them

    return read_series(stream.source, **stream.reader_args(), what=what)


def _usable(cov: np.ndarray) -> np.ndarray:
    """(N,) whether each covariance is a usable R: not all zero, symmetric, positive definite."""
    ok = np.isfinite(cov).all(axis=(-2, -1)) & (np.abs(cov).max(axis=(-2, -1)) > 0)
    ok &= np.allclose(cov, np.swapaxes(cov, -1, -2), rtol=1e-9, atol=0.0) | ~ok
    out = np.zeros(len(cov), dtype=bool)
    for i in np.flatnonzero(ok):
        try:
            np.linalg.cholesky(cov[i])
            out[i] = True
        except np.linalg.LinAlgError:
            pass
    return out


@dataclass
class ReplayData:
    """A replay's data on its instants: the scenario with its steps (and any nominal R) set,
    the instants (ns), each sensor's readings, the truth ({at, values} or {}), notes."""

    scenario: Scenario
    instants: np.ndarray
    sensors: list[_Sensor]
    truth: dict
    notes: list[str]


def read_replay(scenario: Scenario) -> ReplayData:
    """Read every stream of the replay `scenario` and place the readings on the instants."""
    replay = scenario.replay
    system = scenario.system
    notes: list[str] = []
    series = []
    for j, (sen, stream) in enumerate(zip(system.sensors, replay.sensors, strict=True)):
        s = _read(stream, f"sensors[{j}] ({sen.name})")
        notes += [f"{sen.name}: {n}" for n in s.notes]
        series.append(s)
    instants = np.unique(np.concatenate([s.times_ns for s in series]))
    sensors: list[_Sensor] = []
    nominal = []
    for j, (sen, s) in enumerate(zip(system.sensors, series, strict=True)):
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
            cov = np.where(good[:, None, None], s.cov, R if np.isfinite(R).all() else 0.0)
            if not np.isfinite(R).all():
                R = nominal_R(cov)  # a sensor given by its messages alone
            if np.array_equal(cov, np.broadcast_to(R, cov.shape)):
                cov = None  # R does not vary: no per-message covariance needed
        nominal.append(R)
        sensors.append(_Sensor(at, s.values, cov))
    truth: dict = {}
    if replay.truth is not None:
        t = _read(replay.truth, "truth")
        notes += [f"truth: {n}" for n in t.notes]
        pos = np.searchsorted(instants, t.times_ns)
        match = (pos < len(instants)) & (instants[np.minimum(pos, len(instants) - 1)] == t.times_ns)
        if not match.any():
            raise FusionlogError(
                f"{replay.truth.source}: truth: none of its {len(match)} times is an instant of "
                "the sensors (the truth is used only where its time equals a measurement time)"
            )
        if not match.all():
            notes.append(f"truth: {int((~match).sum())} of {len(match)} readings at no instant "
                         "of the sensors (unmatched, not used)")  # fmt: skip
        values = np.full((int(match.sum()), system.n), np.nan)
        values[:, list(replay.truth_states)] = t.values[match]
        truth = {"at": pos[match], "values": values}
    new_sensors = tuple(
        dataclasses.replace(sen, R=np.asarray(R))
        for sen, R in zip(system.sensors, nominal, strict=True)
    )
    sc = dataclasses.replace(scenario, system=dataclasses.replace(system, sensors=new_sensors))
    sc = scenario_with(sc, steps=len(instants) - 1)
    return ReplayData(sc, instants, sensors, truth, notes)


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
    times = (instants - instants[0]) / 1e9
    meta = scenario_metadata(sc, kind.system_fields(sc))
    meta["replay_notes"] = json.dumps(notes)
    w.add_metadata(SCENARIO_META, meta)
    sources = sorted({str(s.source) for s in sc.replay.sensors}
                     | ({str(sc.replay.truth.source)} if sc.replay.truth else set()))  # fmt: skip
    extra = {f"source_sha256:{p}": sha256_of(Path(p)) for p in sources}
    w.add_metadata(PROVENANCE_META, provenance(command, None, sources=json.dumps(sources), **extra))
    topics = [sensor_topic(s.name) for s in sc.system.sensors]
    # readings per instant: (sensor, row) pairs, in instant order
    rows: list[list[tuple[int, int]]] = [[] for _ in instants]
    for j, s in enumerate(sensors):
        for r, k in enumerate(s.at.tolist()):
            rows[k].append((j, r))
    truth_row = np.full(len(instants), -1)
    if truth:
        truth_row[truth["at"]] = np.arange(len(truth["at"]))
    messages = 0
    for k, t in enumerate(times.tolist()):
        if truth_row[k] >= 0:
            w.write_values(TRUTH, k, t, 0, truth["values"][truth_row[k]][None])
            messages += 1
        for j, r in rows[k]:
            s = sensors[j]
            cov = None if s.cov is None else s.cov[r][None]
            w.write_values(topics[j], k, t, 0, s.values[r][None], cov)
            messages += 1
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
    inputs += [s.source for s in scenario.replay.sensors]
    if scenario.replay.truth is not None:
        inputs.append(scenario.replay.truth.source)
    with Outputs([out], force=force, inputs=inputs) as outs:
        data = read_replay(scenario)
        with McapWriter(outs.open(out), time_origin_ns=int(data.instants[0])) as w:
            messages = import_to(data, w, command=command)
        outs.commit()
    return ImportResult(out, len(data.instants), messages, data.notes)
