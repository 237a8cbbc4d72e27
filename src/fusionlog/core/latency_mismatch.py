"""The exact analysis of a long one-run log with late sensors whose truth is not the filters'
model (issue 34: `estimate --model`, a scenario's `[truth]`), reprocess and neglect, in blocks
of time (`core.latency_blocks`).

The whole run's route is the late plans' analysis (`exact.analyse` of `latency.LateModel.
build`'s plans, the truth apart): the plan's state s_k = [s~_k; z_k; ...; z_{k-W+1}] keeps the
stacked filter's state and the readings still to arrive, the truth's raw model drives the
joint moments of [x_k; s_k - D x_k]. Here the same moments come from the stacked filters
carried from block to block (`LateBlocks`' `_Stacked`): the truth on the stacked state
X_k = [x_k; ...; x_{k-W}] is the stacked model of the truth's own F, Q, H, R
(`latency_stacked.stacked_system` with the filters' lags), X_k = F~_t X_{k-1} + [w_k; 0],
and what reaches a stacked filter at k is

    z~_k = H~_t X_k + v~_k,    v~_k[(j, l, o)] = v_{k-l}[o],

the raw reading of instant k - l where it arrives at k (a zero gain column elsewhere). Each
raw reading reaches a filter once, so v~ is white with the stacked R~_t (the noises of one
instant correlated as the truth's R says, of different instants independent) wherever the
readings correlated under the model or the truth arrive together: then the stacked filter
is an affine map of white noises like an on-time one, s~_k = T_k s~_{k-1} + U_k z~_k, and
`exact_mismatch.MismatchBlocks` propagates the joint moments of [X_k; s~_k - D X_k] -- the
same definitions, on the stacked model -- reading out x_k's error, the first n rows.

Not here (None: the whole run): correlated readings arriving apart under the model or the
truth (the stacked noise is then correlated across instants: the plans keep the raw readings,
`latency_joint`, `latency_apart` keeps the model's own noises only), a truth with a
covariance per message or a motion model, or of other sizes than the filters'.
"""

from __future__ import annotations

import dataclasses

from .architectures.replay_blocks import ReplayBlocks, system_window
from .exact_mismatch import MismatchBlocks, coupling_of
from .latency_corr import apart_pairs
from .latency_stacked import stacked_system
from .model import System

__all__ = ["StackedMismatch", "takes_truth"]


def takes_truth(model: System, truth: System) -> bool:
    """Whether `StackedMismatch` is exact for the filters of `model` (late, reprocess or
    neglect) on data from `truth` (module docstring)."""
    if not truth.linear or truth.motion_model is not None or truth.Rs is not None:
        return False
    if truth.n != model.n or [s.dim for s in truth.sensors] != [s.dim for s in model.sensors]:
        return False
    return not apart_pairs(model) and not apart_pairs(model, truth.cross_R)


class StackedMismatch(MismatchBlocks):
    """`MismatchBlocks` of one architecture's stacked filters `blocks` (`latency_blocks.
    _Stacked`: `blocks.late` its late model) of the raw model `model` on data from the raw
    `truth`: the truth stacked with the filters' lags, made per block of time where its F, Q
    vary (nothing of the log's length is stacked), x_k's error read out."""

    def __init__(self, blocks: ReplayBlocks, model: System, truth: System) -> None:
        lags = blocks.late.lags
        shape = dataclasses.replace(truth, Fs=None, Qs=None, intervals=None)
        # x leaves the joint where the raw F and H are the truth's: the stacked ones then are
        super().__init__(
            blocks.system, stacked_system(shape, lags), blocks, coupled=coupling_of(model, truth)
        )
        self.raw, self.lags, self.keep = truth, lags, model.n

    def truth_window(self, k0: int, k1: int) -> System:
        raw = system_window(self.raw, k0, k1, k0 > 0)
        return self.truth if raw is self.raw else stacked_system(raw, self.lags)
