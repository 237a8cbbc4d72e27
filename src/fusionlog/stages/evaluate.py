"""`fusionlog evaluate`: estimates against the truth into a Rerun recording and summary.json."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog.core.linalg import not_a_covariance
from fusionlog.driver import KeptPlans
from fusionlog.driver.long_log import time_block
from fusionlog.driver.plans import PATTERN
from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import TRUTH, McapFile, read_metadata
from fusionlog.jsonout import dumps
from fusionlog.memory import release_freed_memory
from fusionlog.report import model_sensors
from fusionlog.scenario import Scenario
from fusionlog.scenario.trajectory import with_align

from .common import PROVENANCE_META, open_evaluation_inputs, progress
from .kinds import kind_of


@dataclass
class EvaluateResult:
    recording: Path
    summary_path: Path | None
    summary: dict[str, Any]
    #: the filters' sensor names (`report.format_table` names a single sensor's row by it)
    sensors: list[str] | None = None


def evaluate_into(
    sensors_path: Path,
    estimates_path: Path,
    outs: Outputs,
    out: Path,
    summary_path: Path | None = None,
    *,
    block: int | None = None,
    scenario: Scenario | None = None,
    sensors_sha256: str | None = None,
    estimates_name: str | None = None,
    kept: KeptPlans | None = None,
    align: str | None = None,
) -> tuple[dict[str, Any], list[str] | None]:
    """Metrics of every architecture in `estimates_path` against the truth of `sensors_path`,
    written into the (uncommitted) outputs `out` (.rrd) and `summary_path` (JSON); returns
    the summary and the filters' sensor names (from the estimates' provenance).
    `estimates_name` names the estimates in errors (`run`: its output, not the temporary file);
    `kept` (`run`): the estimate stage's per-run plans, which the exact analysis takes;
    `align` (``--align``) overrides the scenario's ``[evaluate] align``.

    Metrics are sums over blocks of runs, so memory does not grow with M; what they are and
    which exact expected values stand beside them is the kind's business (its Evaluator).
    """
    sens, est, prov, sc = open_evaluation_inputs(
        sensors_path, estimates_path, scenario, sensors_sha256
    )
    sc = with_align(sc, align)
    kind = kind_of(sc.kind)
    ev = kind.evaluator(sc, est, prov, sens, kept)
    M = sens.runs()
    B = ev.block_runs(block)
    truth = [TRUTH] if TRUTH in sens.topics else []  # a recorded log may have none
    long = ev.time_windows() if M == 1 else None
    if long is not None:  # a long one-run log in blocks of time (stages/evaluator/long_*)
        T = time_block()
        read = truth + list(ev.sensor_topics)
        windows = zip(
            sens.iter_time_blocks(read, T) if read else _nothing(est.steps(), T),
            est.iter_time_blocks(ev.topics, T),
            strict=True,
        )
        keys = _pattern_aside(prov)
        for (k0, k1, sdata), (_, _, edata) in windows:
            for topic, e in edata.items():
                _check_variances(estimates_name or estimates_path, topic, e[1])
            long.add(k0, k1, sdata.pop(TRUTH, None), edata, sdata)
        del windows, sdata, edata
        _pattern_back(prov, keys, est)
        return _written(long.evaluation(), kind, outs, out, summary_path, prov)
    blocks = zip(
        sens.iter_run_blocks(truth + list(ev.sensor_topics), B),
        est.iter_run_blocks(ev.topics, B),
        strict=True,
    )
    for (off, _runs, sdata), (_, _, edata) in progress(blocks, -(-M // B), "evaluate"):
        for topic, e in edata.items():
            if isinstance(e, tuple):  # a state estimate: (mean, cov)
                _check_variances(estimates_name or estimates_path, topic, e[1])
        ev.add(off, sdata.pop(TRUTH, None), edata, sdata)
        # a block's arrays (of a long log: all its estimates, covariances included) are freed
        # before the next block is read and before the recording is encoded (what it draws,
        # the evaluator keeps)
        del sdata, edata
    del blocks  # a zip keeps its last result tuple, and with it the last block's arrays
    evaluation = ev.evaluation(prov)
    # What the recording draws is in `evaluation`; the accumulators and the open files (a long
    # log's times, twice) are not kept while the recording is encoded, the run's peak.
    del ev, sens, est
    return _written(evaluation, kind, outs, out, summary_path, prov)


def _pattern_aside(prov: dict[str, str]) -> list[str] | None:
    """Drop the estimates' ``measurement_pattern`` mask from `prov` (the dict the estimates
    file and the evaluator hold) while a long log's blocks are evaluated: the evaluator has
    read it, and its text, 3m + 2 bytes an instant, would be held through every block only
    for the recording's properties (issue 34). The keys' order for `_pattern_back`; None
    where the pattern is no mask."""
    if prov.get(PATTERN, "complete") in ("complete", "per-run"):
        return None
    keys = list(prov)
    del prov[PATTERN]
    return keys


def _pattern_back(prov: dict[str, str], keys: list[str] | None, est: McapFile) -> None:
    """The mask `_pattern_aside` dropped, read again from the estimates file, in its place."""
    if keys is not None:
        prov[PATTERN] = read_metadata(est.path, PROVENANCE_META)[PATTERN]
        for k in keys:  # the record's order, as the recording lists it
            prov[k] = prov.pop(k)


def _nothing(instants: int, T: int):
    """Blocks of time of no topic (a log read for nothing but its estimates)."""
    for k0 in range(0, instants, T):
        yield k0, min(k0 + T, instants), {}


def _written(evaluation, kind, outs: Outputs, out: Path, summary_path, prov):
    """Write the evaluation's recording and summary into the outputs; (summary, sensors)."""
    release_freed_memory()
    summary = evaluation.summary
    # The summary is made first: a recording is never committed beside a summary that failed.
    text = dumps(summary, indent=2) + "\n" if summary_path is not None else None
    kind.write_evaluation(outs.open(out), evaluation)
    if summary_path is not None:
        outs.open(summary_path).write(text.encode())
    return summary, model_sensors(prov)


def _check_variances(path: Path | str, topic: str, cov: np.ndarray) -> None:
    """A reported covariance with a negative variance is no covariance (a damaged or foreign
    estimates file): its NEES would come out negative, its DM zero. NaN (undefined) passes."""
    negative = not_a_covariance(cov, semidefinite=False)  # (K+1,) or (runs, K+1)
    if negative.any():
        k = int(np.flatnonzero(negative.reshape(-1, negative.shape[-1]).any(axis=0))[0])
        raise FusionlogError(f"{path}: {topic}: step {k}: a covariance with a negative variance")


def run_evaluate(
    sensors_path: Path,
    estimates_path: Path,
    out: Path,
    *,
    summary_path: Path | None = None,
    force: bool = False,
    block: int | None = None,
    align: str | None = None,
) -> EvaluateResult:
    """Evaluate into `out` (and `summary_path`): both committed together or neither."""
    targets = [Path(out)] + ([Path(summary_path)] if summary_path else [])
    inputs = [Path(sensors_path), Path(estimates_path)]
    with Outputs(targets, force=force, inputs=inputs) as outs:
        summary, sensors = evaluate_into(
            sensors_path, estimates_path, outs, Path(out), summary_path, block=block, align=align
        )
        outs.commit()
    return EvaluateResult(Path(out), summary_path, summary, sensors)
