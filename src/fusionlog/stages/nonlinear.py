"""The state kind's stage hooks for nonlinear sensors and motion: estimation by the EKF/UKF
architectures of `core.nonlinear` (per run, batched), the posterior Cramér-Rao bound beside the
Monte Carlo values, and ``--filter``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fusionlog.core.model import System
from fusionlog.errors import FusionlogError

__all__ = ["PcrbPart", "estimate_block", "step_writers", "with_filter"]


def with_filter(system: Any, name: str | None) -> Any:
    """The system with its local filter set by ``--filter`` (None: as recorded)."""
    if name is None:
        return system
    from fusionlog.scenario.nonlinear import FILTERS

    if not isinstance(system, System):
        raise FusionlogError("--filter: only state scenarios have a local filter")
    if name not in FILTERS:
        raise FusionlogError(f"--filter: unknown filter {name!r} (known: {', '.join(FILTERS)})")
    return dataclasses.replace(system, filter=name)


def estimate_block(
    system: System, arch: str, z: np.ndarray, times: np.ndarray, run_offset: int
) -> tuple[np.ndarray, np.ndarray]:
    """Means (M, K+1, n) and per-run covariances (M, K+1, n, n) of a block of runs."""
    from fusionlog.core.nonlinear import estimate

    _require_filter(system)
    tr = estimate(system, arch, z, times, run_offset)
    return tr.mean, tr.cov


def step_writers(
    system: System, archs: list[str], z: np.ndarray, times: np.ndarray, run_offset: int
) -> dict[str, Any]:
    """The estimate stage's writers of a block: each architecture's filter advances one
    instant when its message for that instant is written (the estimator's writers are called
    for k = 0..K in order), so only one instant of covariances is held, not all of them."""
    from fusionlog.core.nonlinear import estimate_steps

    _require_filter(system)

    def writer(arch: str) -> Any:
        steps = estimate_steps(system, arch, z, times, run_offset)

        def write(w: Any, topic: str, k: int, t: float, off: int) -> None:
            mean, cov = next(steps)
            w.write_estimate(topic, k, t, off, mean, cov)

        return write

    return {a: writer(a) for a in archs}


def _require_filter(system: System) -> None:
    if system.filter is None:  # a --model file without [estimate] filter
        raise FusionlogError(
            'the model is nonlinear: give [estimate] filter = "EKF" or "UKF", or --filter'
        )


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
