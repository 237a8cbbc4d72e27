"""The state kind's stage hooks for nonlinear sensors and motion: estimation by the EKF/UKF
architectures of `core.nonlinear` (per run, batched), the posterior Cramér-Rao bound beside the
Monte Carlo values, and ``--filter``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fusionlog.core.architectures import PlanCache
from fusionlog.core.model import System
from fusionlog.errors import FusionlogError

__all__ = ["PcrbPart", "scenario_bound", "simulated_readings", "step_writers", "with_filter"]


def with_filter(system: Any, name: str | None, where: str = "--filter") -> Any:
    """The system with its local filter set by ``--filter`` (None: as recorded); errors name
    the option as `where` (the Python API's argument: "filter")."""
    if name is None:
        return system
    from fusionlog.scenario.nonlinear import FILTERS

    if not isinstance(system, System):
        raise FusionlogError(f"{where}: only state scenarios have a local filter")
    if not isinstance(name, str) or name not in FILTERS:
        what = repr(name) if isinstance(name, str) else f"{name!r} ({type(name).__name__})"
        raise FusionlogError(f"{where}: unknown filter {what} (known: {', '.join(FILTERS)})")
    return dataclasses.replace(system, filter=name)


def step_writers(
    plans: PlanCache, archs: list[str], z: np.ndarray, run_offset: int
) -> dict[str, Any]:
    """The estimate stage's writers of a block (`plans`: the system and instants): each
    architecture's filter advances one instant when its message for that instant is written
    (the estimator's writers are called for k = 0..K in order), so only one instant of per-run
    covariances is held, not all of them (`core.nonlinear.estimate_steps`)."""
    from fusionlog.core.nonlinear import estimate_steps

    system, times = plans.system, plans.times  # the system is on the log's instants

    def writer(arch: str) -> Any:
        steps = estimate_steps(system, arch, z, times, run_offset)

        def write(w: Any, topic: str, k: int, t: float, off: int) -> None:
            mean, cov = next(steps)
            w.write_estimate(topic, k, t, off, mean, cov)

        return write

    return {a: writer(a) for a in archs}


class PcrbPart:
    """The evaluator's posterior Cramér-Rao bound: the truth and which sensors measured in each
    block go into `core.nonlinear.PcrbAccumulator`; `summary` and `per_state` after the last."""

    def __init__(self, system: System, times: np.ndarray) -> None:
        from fusionlog.core.nonlinear import PcrbAccumulator

        self.acc = PcrbAccumulator(system, times)
        self.topics = [f"/sensors/{s.name}" for s in system.sensors]
        self._bound: np.ndarray | None = None
        self.complete = True  # every block came with its readings

    def add(self, truth: np.ndarray, sensors: dict[str, np.ndarray] | None) -> None:
        if sensors is None or any(t not in sensors for t in self.topics):
            self.complete = False
            return
        present = np.stack([~np.isnan(sensors[t]).any(axis=-1) for t in self.topics], axis=-1)
        self.acc.add(truth, present)

    @property
    def bound(self) -> np.ndarray | None:
        """J_k^-1 (K+1, n, n), None when some block lacked its readings."""
        if self._bound is None and self.complete and self.acc.runs:
            self._bound = self.acc.bound()
        return self._bound

    def summary(self) -> dict[str, Any] | None:
        from fusionlog.core.nonlinear import pcrb_summary

        return None if self.bound is None else pcrb_summary(self.bound)

    def per_state(self) -> np.ndarray | None:
        """The bound on each state's MSE per instant (K+1, n)."""
        b = self.bound
        return None if b is None else np.diagonal(b, axis1=-2, axis2=-1).copy()


def simulated_readings(
    scenario: Any, run_offset: int, runs: int
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Truth and each sensor's readings {topic: (runs, K+1, dim)} of runs [run_offset, +runs),
    simulated: what the PCRB needs of runs whose estimates live elsewhere (Dask workers)."""
    from fusionlog.io.mcap import sensor_topic

    from .kinds import kind_of

    x, zs = kind_of(scenario.kind).simulate(scenario, run_offset, runs)
    names = [s.name for s in scenario.system.sensors]
    return x, {sensor_topic(n): z for n, z in zip(names, zs, strict=True)}


def scenario_bound(scenario: Any) -> dict[str, Any] | None:
    """summary.json's "pcrb" of a scenario with a nonlinear model, from all its runs simulated
    block by block (the bound needs their truth and which measurements they made, no
    estimate: a sweep's point, computed where the points are summarised); None when the
    model is linear (its exact analysis stands instead)."""
    if scenario.kind != "state" or scenario.system.linear:
        return None
    from .montecarlo import blocks

    part = PcrbPart(scenario.system, scenario.times)
    for off, n in blocks(scenario):
        part.add(*simulated_readings(scenario, off, n))
    return part.summary()
