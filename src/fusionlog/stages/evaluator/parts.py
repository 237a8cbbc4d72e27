"""The one interface of the evaluator's parts, and the records they share.

A part accumulates one concern of the evaluation (Monte Carlo metrics, the exact analysis, NIS,
the PCRB, sample runs, the plane view) block by block: `add` a block of runs evaluated here,
`merge` what other processes summed of runs not added here, `summarise` into the finished
record. The state evaluator (`.state_evaluator`) hands every block to every part, in one order,
and reads nothing of a part's inside.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Block", "Elsewhere", "Finished", "Part"]


@dataclass(frozen=True)
class Block:
    """One block of runs: `off` its first run; `truth` (runs, K+1, n) (NaN broadcast where the
    log has none: `has_truth` False); `estimates` {arch: (mean (runs, K+1, n), cov (K+1, n, n)
    shared or (runs, K+1, n, n))}; `sensors` the readings {topic: (runs, K+1, dim)} (NaN:
    absent) of the topics the parts asked for, None when the caller does not have them."""

    off: int
    truth: np.ndarray
    has_truth: bool
    estimates: dict[str, tuple[np.ndarray, np.ndarray]]
    sensors: dict[str, np.ndarray] | None

    @property
    def runs(self) -> int:
        return self.truth.shape[0]


@dataclass(frozen=True)
class Elsewhere:
    """What other processes computed of runs not `add`ed here: each architecture's metric sums
    (`core.metrics.MetricsAccumulator`), for per-run patterns their conditional exact sums
    (`core.exact.ConditionalExpected`), and runs' truth with their readings for what needs no
    estimate (the PCRB of a nonlinear model)."""

    sums: dict[str, Any] = field(default_factory=dict)
    expected: dict[str, Any] = field(default_factory=dict)
    readings: tuple[np.ndarray, dict[str, np.ndarray]] | None = None
    #: each architecture's trajectory sums (`core.trajectory.TrajectorySums`)
    trajectory: dict[str, Any] = field(default_factory=dict)


@dataclass
class Finished:
    """What the parts summarise into: summary.json (`summary`, with each architecture's entry
    in `archs`), the `Evaluation`'s other fields (`fields`), and what one part hands the next
    (`expected`: each architecture's exact values and whether they are conditional on the
    drawn patterns; `metric_runs`: the runs each architecture's metrics saw)."""

    summary: dict[str, Any]
    archs: dict[str, dict[str, Any]]
    fields: dict[str, Any] = field(default_factory=dict)
    expected: dict[str, tuple[Any, bool]] = field(default_factory=dict)
    metric_runs: dict[str, int] = field(default_factory=dict)


class Part(ABC):
    """One concern of the evaluation."""

    #: The sensor topics whose readings `add` needs (none unless the part says so).
    topics: Sequence[str] = ()

    @abstractmethod
    def add(self, block: Block) -> None:
        """Accumulate one block of runs evaluated here."""

    def merge(self, other: Elsewhere) -> None:  # noqa: B027 - most parts merge nothing
        """Accumulate what was computed elsewhere of runs not added here."""

    @abstractmethod
    def summarise(self, into: Finished) -> None:
        """Put what was accumulated into the finished record."""
