"""The exact analysis of a long one-run log with late sensors in blocks of time (issue 34), for
delays drawn or recorded and readings missing: the stacked filters' error covariances carried
from block to block (`core.latency_blocks.LateBlocks.error_covariances`, the truth the filters'
model; retrodicted, the moments of the plans of each block, `core.retrodict_blocks.
RetroBlocks`, the same interface; where the truth is not the model, `--model` or a `[truth]`,
the joint moments of the truth and each stacked filter carried, `LateBlocks.mismatch`,
`core.latency_mismatch`), each block's readings (which were taken) and arrivals read
from the sensors file as the blocks come (`..late_blocks.arrival_blocks`). With random delays
the values are conditional on the drawn (or recorded) delays, as the whole run's analysis of the
run's plans (`ExactPart`'s per-run route), and say so (`conditional`). The bound check's worst
instant is followed as the blocks come (`.long_exact.BoundStream`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from fusionlog.core.exact import Expected, shared_nees_and_dm
from fusionlog.core.late_policy import random_delays
from fusionlog.core.latency_blocks import LateBlocks
from fusionlog.core.model import System
from fusionlog.errors import FusionlogError

from ..late_blocks import arrival_blocks
from .long_exact import BoundStream

__all__ = ["LongLateExact"]


class LongLateExact:
    """Each architecture's exact values of the blocks of one run with late sensors (`window`,
    in order, blocks of `block` instants), read from `sensors` (its `topics`); `truth` the
    data's model where it is not the filters' (`blocks.takes(truth)`), else None."""

    def __init__(
        self,
        blocks: LateBlocks,
        sensors: Any,
        topics: list[str],
        per_run: bool,
        block: int,
        truth: System | None = None,
    ) -> None:
        self.blocks, self.sensors, self.topics, self.block = blocks, sensors, topics, block
        self.truth = truth
        system = blocks.late.system
        #: values conditional on the drawn delays (summary.json's expected.conditional)
        self.conditional = per_run and random_delays(system)
        self.bounds = {a: BoundStream() for a in blocks.archs}
        self.readings = sensors.iter_time_blocks(topics, block)
        self.arrivals = arrival_blocks(sensors, system, topics, block)

    def window(self, k0: int, k1: int) -> dict[str, tuple[Any, np.ndarray]]:
        """{arch: (Expected (w, ...), the bound check's ratio (w,))} at the instants k0..k1-1."""
        r0, r1, data = next(self.readings)
        arrival = next(self.arrivals)
        if (r0, r1) != (k0, k1):
            raise ValueError(f"blocks of time {k0}..{k1} and {r0}..{r1}")
        present = np.concatenate([~np.isnan(data[t][0]) for t in self.topics], axis=-1)
        try:
            if self.truth is None:  # the truth the model: unbiased, the filters' own recursion
                got = {
                    a: (mse, np.zeros(P.shape[:-1]), P)
                    for a, (mse, P) in self.blocks.error_covariances(
                        k0, k1, present, arrival
                    ).items()
                }
            else:
                got = self.blocks.mismatch(k0, k1, present, arrival, self.truth)
        except ValueError as e:
            raise FusionlogError(f"{self.sensors.path}: {e}") from None
        out = {}
        for a, (mse, bias, P) in got.items():
            nees, dm, _ = shared_nees_and_dm(P, bias, mse)
            ex = Expected(mse, bias, P, nees, dm)
            ratio = np.asarray(ex.bound, dtype=float)
            self.bounds[a].add(k0, ratio)
            out[a] = (ex, ratio)
        return out

    def bound_summary(self, arch: str) -> dict[str, Any] | None:
        """summary.json's ``bound`` of the instants seen (`core.bound.bound_summary`)."""
        return self.bounds[arch].summary()
