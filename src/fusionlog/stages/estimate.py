"""`fusionlog estimate`: replay a sensors MCAP through fusion architectures."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusionlog.driver import KeptPlans
from fusionlog.errors import NumericalError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapFile, McapWriter
from fusionlog.io.mcap.topics import estimates_topic
from fusionlog.scenario import Scenario, kind_of_text, toml

from .common import (
    PROVENANCE_META,
    SCENARIO_META,
    Digest,
    progress,
    provenance,
    scenario_from_file,
)
from .kinds import kind_of


@dataclass
class EstimateResult:
    path: Path
    architectures: list[str]
    runs: int
    steps: int


def _kind_name(recorded: Scenario | None, model_path: Path | None) -> str:
    """The kind recorded in the sensors file, else that of the --model file, else state."""
    if recorded is not None:
        return recorded.kind
    if model_path is not None:
        return kind_of_text(toml.read_text(str(model_path)), str(model_path))
    return "state"


def estimate_to(
    sensors_path: Path,
    w: McapWriter,
    *,
    archs: list[str] | None = None,
    model_path: Path | None = None,
    filter_name: str | None = None,
    block: int | None = None,
    command: str = "fusionlog estimate",
    late: str | None = None,
    sensors_name: str | None = None,
    recorded: Scenario | None = None,
    sensors_sha256: str | None = None,
    kept: KeptPlans | None = None,
) -> EstimateResult:
    """Estimate every run of `sensors_path` with each architecture into an open writer:
    /estimates/<ARCH>, one message per step per block of runs. `recorded` is the scenario
    recorded in the sensors file and `sensors_sha256` its digest, when the caller (`run`, which
    wrote it) has them: each is then not read again. `filter_name` (--filter) sets the local
    filter of a state model, `late` (--late) its policy for late measurements. `kept` (`run`):
    per-run plans the evaluation takes next."""
    digest = None if sensors_sha256 else Digest(Path(sensors_path))
    mf = McapFile(sensors_path)
    if recorded is None:
        recorded = scenario_from_file(mf)
    kind = kind_of(_kind_name(recorded, model_path))
    model = kind.model(mf, recorded, model_path)
    if filter_name is not None or late is not None:
        from fusionlog.scenario import system_to_dict

        from .state_kind import with_filter, with_late

        system = with_late(with_filter(model.system, filter_name), late)
        model = model._replace(system=system, json=json.dumps(system_to_dict(system)))
    system = model.system
    topics = kind.check_sensor_topics(mf, system)
    # without --arch, the recorded scenario's list, which a --model's sensors may not fit
    where = "--arch" if archs else f"{sensors_name or sensors_path}: recorded architectures"
    archs = kind.check_architectures(archs or model.architectures, system, where)
    K, M = mf.steps() - 1, mf.runs()
    times = mf.times()
    # a replay's estimates keep its recording's clock: the log_time of its sensor messages
    w.set_time_origin(mf.time_origin_ns())
    est = kind.estimator(system, K, M, archs, mf, kept)
    B = est.block_runs(block)
    if SCENARIO_META in mf.metadata:
        w.add_metadata(SCENARIO_META, mf.metadata[SCENARIO_META])
    windows = est.time_windows(mf) if M == 1 else None
    try:  # nonlinear filters fail as their blocks are made: name the file
        for k0, k1, writers in windows or ():  # a long one-run log, in blocks of time
            named = [(estimates_topic(a), write) for a, write in writers.items()]
            _write_steps(w, named, times, k0, k1, 0)
    except NumericalError as e:
        raise NumericalError(f"{sensors_name or sensors_path}: {e}") from None
    blocks = mf.iter_run_blocks(topics, B) if windows is None else ()
    for off, _runs, data in progress(blocks, -(-M // B), "estimate"):
        try:
            writers = est.estimate(off, data)
        except NumericalError as e:  # the core names the architecture and step; the file here
            what = _infinite_reading(data, off) or str(e)  # an input to blame, else the step
            raise NumericalError(f"{sensors_name or sensors_path}: {what}") from None
        named = [(estimates_topic(a), write) for a, write in writers.items()]
        # The documented order (for each step, for each topic) lets a reader learn every
        # topic from the first messages of the file.
        try:  # nonlinear filters advance as they are written: their failures come here
            _write_steps(w, named, times, 0, K + 1, off)
        except NumericalError as e:
            raise NumericalError(f"{sensors_name or sensors_path}: {e}") from None
    # Written last, when what the whole file holds is known (e.g. the measurement pattern).
    w.add_metadata(
        PROVENANCE_META,
        provenance(
            command,
            recorded.seed if recorded is not None else None,
            sensors_sha256=sensors_sha256 or digest.value(),  # type: ignore[union-attr]
            sensors_file=sensors_name or Path(sensors_path).name,
            model_source=model.source,
            model=model.json,
            architectures=json.dumps(archs),
            **est.provenance(),
        ),
    )
    return EstimateResult(Path(sensors_path), archs, M, K)


def _write_steps(w: McapWriter, named: list, times: np.ndarray, k0: int, k1: int, off: int) -> None:
    """The messages of steps k0..k1-1 in the documented order (for each step, for each topic:
    a reader learns every topic from the file's first messages); one run's at once where every
    writer gives its column (`McapWriter.write_run_steps`, the same bytes)."""
    cols = [getattr(write, "column", lambda _: None)(topic) for topic, write in named]
    if off == 0 and named and all(c is not None for c in cols):  # one run: run 0
        w.write_run_steps(k0, times[k0:k1], cols)
        return
    for k in range(k0, k1):
        t = float(times[k])
        for topic, write in named:
            write(w, topic, k, t, off)


def _infinite_reading(data: dict, off: int) -> str | None:
    """Where a block of readings holds an infinite value (NaN marks a missing one; an infinity
    is no reading at all), for the error line: the overflow it causes shows up at whatever step
    the plans' products first spread it to, not at the reading's."""
    for topic, z in data.items():
        if isinstance(z, np.ndarray) and np.isinf(z).any():
            run, k = (int(i[0]) for i in np.nonzero(np.isinf(z).any(axis=-1)))
            return f"{topic}: an infinite reading at step {k}, run {off + run}"
    return None


def run_estimate(
    sensors_path: Path,
    out: Path,
    *,
    archs: list[str] | None = None,
    model_path: Path | None = None,
    filter_name: str | None = None,
    force: bool = False,
    block: int | None = None,
    command: str = "fusionlog estimate",
    late: str | None = None,
) -> EstimateResult:
    """Estimate `sensors_path` into the estimates file `out` (committed only when complete)."""
    out = Path(out)
    inputs = [Path(sensors_path)] + ([Path(model_path)] if model_path else [])
    with Outputs([out], force=force, inputs=inputs) as outs:
        with McapWriter(outs.open(out)) as w:
            res = estimate_to(
                sensors_path,
                w,
                archs=archs,
                model_path=model_path,
                filter_name=filter_name,
                block=block,
                command=command,
                late=late,
            )
        outs.commit()
    res.path = out
    return res
