"""Pieces the three stage drivers share: block sizes, provenance, progress bars, the scenario
recorded in a sensors file, and the checks every evaluation makes first."""

from __future__ import annotations

import hashlib
import sys
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np

from fusionlog import __version__
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.topics import TRUTH
from fusionlog.scenario import Scenario, scenario_from_metadata

SCENARIO_META = "fusionlog.scenario"
PROVENANCE_META = "fusionlog.provenance"
RUN_STEPS_PER_BLOCK = 1 << 20

T = TypeVar("T")


def block_runs(steps: int, runs: int, requested: int | None = None) -> int:
    """Runs per block: about a million run-steps, so memory is set by the block, not by M."""
    if requested is not None:
        return max(1, min(requested, runs))
    return max(1, min(runs, RUN_STEPS_PER_BLOCK // (steps + 1)))


def progress(items: Iterable[T], total: int, desc: str, unit: str = "block") -> Iterator[T]:
    """A progress bar on a terminal, silence when stderr is piped or captured."""
    if not sys.stderr.isatty():  # what tqdm(disable=True) would do, without importing it
        yield from items
        return
    from tqdm import tqdm  # here: ~0.03 s of import that a piped or captured run never needs

    yield from tqdm(items, total=total, desc=desc, unit=unit, leave=False)


class Counter:
    """A progress bar counting events of unknown number (an optimiser's iterations) on a
    terminal, nothing when stderr is piped or captured (as `progress`)."""

    def __init__(self, desc: str, unit: str) -> None:
        self._bar = None
        if sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(desc=desc, unit=unit, leave=False)

    def update(self, n: int = 1) -> None:
        if self._bar is not None:
            self._bar.update(n)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def sha256_of(path: Path) -> str:
    # hashlib's own loop reads into one buffer of 256 KiB: its memory does not grow with a
    # file below a read's size, as a 1 MiB read's did (a peak that grew with short logs)
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


class Digest:
    """`sha256_of(path)` computed in a thread from now on, `value()` when it is needed: file
    reads and hashlib release the GIL, so the hash of a 20 MB sensors file (~20 ms) overlaps
    the estimation on another core instead of adding to it. Errors are raised by `value()`."""

    def __init__(self, path: Path) -> None:
        self._result: list = []
        self._thread = threading.Thread(target=self._run, args=(path,), daemon=True)
        self._thread.start()

    def _run(self, path: Path) -> None:
        try:
            self._result.append(sha256_of(path))
        except BaseException as e:  # handed to the caller of value()
            self._result.append(e)

    def value(self) -> str:
        self._thread.join()
        r = self._result[0]
        if isinstance(r, BaseException):
            raise r
        return r


def provenance(command: str, seed: int | None, **extra: str) -> dict[str, str]:
    """Provenance record; no wall-clock time, so that same-seed outputs are identical."""
    out = {"fusionlog_version": __version__, "command": command}
    if seed is not None:
        out["seed"] = str(seed)
    out.update(extra)
    return out


def scenario_metadata(scenario: Scenario, system_fields: dict[str, str]) -> dict[str, str]:
    """The `fusionlog.scenario` record: the kind, the TOML as written and the values actually
    used (the kind adds its resolved system under its own field names)."""
    return {
        "kind": scenario.kind,
        "toml": scenario.source,
        "name": scenario.name,
        "steps": str(scenario.steps),
        "runs": str(scenario.runs),
        "seed": str(scenario.seed),
        "dt": repr(scenario.dt),
        **system_fields,
    }


def scenario_from_file(mf: McapFile) -> Scenario | None:
    """The scenario recorded in a sensors file (None if it has no record)."""
    meta = mf.metadata.get(SCENARIO_META)
    if meta is None:
        return None
    return scenario_from_metadata(meta, f"{mf.path}: metadata {SCENARIO_META}")


def open_evaluation_inputs(
    sensors_path: Path,
    estimates_path: Path,
    recorded: Scenario | None = None,
    sensors_sha256: str | None = None,
) -> tuple[McapFile, McapFile, dict[str, str], Scenario]:
    """What every evaluation checks first: both files readable, the truth and the scenario
    present, the estimates made from this very sensors file and of the same size.
    Returns the two files, the estimates' provenance record and the recorded scenario
    (`recorded` and the sensors file's digest when the caller has them: not read again)."""
    sens = McapFile(sensors_path)
    est = McapFile(estimates_path)
    sc = recorded
    if sc is None and SCENARIO_META in sens.metadata:
        sc = scenario_from_file(sens)
    if TRUTH not in sens.topics and (sc is None or sc.replay is None):
        # a replayed recording without [truth] is evaluated without it (NIS); a simulation
        # always has its truth
        raise FusionlogError(f"{sensors_path}: no /truth topic, nothing to evaluate against")
    if sc is None:
        raise FusionlogError(f"{sensors_path}: no {SCENARIO_META} metadata (not a simulation)")
    prov = est.metadata.get(PROVENANCE_META, {})
    digest = prov.get("sensors_sha256")
    if digest is not None and digest != (sensors_sha256 or sha256_of(Path(sensors_path))):
        raise FusionlogError(
            f"{estimates_path}: was estimated from another sensors file "
            f"({prov.get('sensors_file', '?')}, sha256 {digest[:12]}...), not {sensors_path}"
        )
    if est.steps() != sens.steps() or est.runs() != sens.runs():
        raise FusionlogError(
            f"{estimates_path}: {est.runs()} runs x {est.steps()} steps do not match "
            f"{sensors_path} ({sens.runs()} x {sens.steps()})"
        )
    t_est, t_sens = est.times(), sens.times()  # the exact analysis runs on the estimates' times
    if not np.array_equal(t_est, t_sens):
        k = int(np.flatnonzero(t_est != t_sens)[0])
        raise FusionlogError(
            f"{estimates_path}: step {k} is at {float(t_est[k])!r} s, in {sensors_path} at "
            f"{float(t_sens[k])!r} s"
        )
    est.share_times(t_sens)  # the same instants: one array of their times for both files
    return sens, est, prov, sc
