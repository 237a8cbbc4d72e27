"""The exact analysis of one recorded log without plans (issue 22d).

The plans' analysis (`exact.analyse`) propagates the joint moments of the truth and every
estimator state through each step's maps T, U, O: what a model mismatch needs. When the truth
is the filters' model itself (the same F, G Q G^T, H, R at every instant and the prior as the
initial distribution: a replay's usual case), the true error statistics are what the filters
already compute: zero means, and the error covariances of `replay.replay_error_covariances`
(a Kalman filter's or the smoother's own P, O J O^T for a fusion O of the local filters, J of
eq. 35, HKF's own recursion). The NEES and DM follow from them as in the plans' analysis
(`shared_nees_and_dm`). Anything else (a mismatched truth, what the replay path refuses, a
reported covariance not positive definite) is left to the plans, which name a failing step.

`ExpectedBlocks`: the same in blocks of time (issue 34), the error covariances' recursions
carried from block to block (`architectures.replay_blocks`); where a block's reported
covariance is not positive definite its NEES and DM are NaN there (no plans to hand it to).
A long log whose truth is not the model goes in blocks too, `exact_mismatch`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from .architectures.replay import replay_error_covariances
from .architectures.replay_blocks import ReplayBlocks
from .exact import Expected, shared_nees_and_dm
from .intervals import same_per_interval
from .model import System

if TYPE_CHECKING:
    from .exact_mismatch import MismatchBlocks


def truth_is_model(model: System, truth: System, steps: int) -> bool:
    """Whether `truth` (as the filters see it) is `model` on the instants k = 0..steps: the
    same matrices bit for bit and the prior as its initial distribution."""
    if model.prior is None or model.n != truth.n or model.m != truth.m:
        return False
    if not (model.linear and truth.linear):
        return False
    init = truth.truth_initial
    same = [
        (model.linear_measurement(), truth.linear_measurement()),
        (model.prior.mean, init.mean),
        (model.prior.cov, init.cov),
    ]
    # F, Q of every interval and R of every instant a stretch at a time (`core.intervals`:
    # not formed whole)
    per = (("Fs", "F", steps), ("Qs", "GQG", steps), ("Rs", "R", steps + 1))
    return all(a.shape == b.shape and np.array_equal(a, b) for a, b in same) and all(
        same_per_interval(
            getattr(model, f), getattr(model, d), getattr(truth, f), getattr(truth, d), count
        )
        for f, d, count in per
    )


def replay_expected(
    model: System,
    truth: System,
    archs: Sequence[str],
    present: np.ndarray | None,
    steps: int,
    criterion: str | None = None,
) -> dict[str, Expected]:
    """The exact expected statistics (`exact.Expected`, (K+1, ...)) of the architectures of
    one run with the measurement mask `present` (K+1, m) (None: all present) that this path
    covers, equal to `exact.analyse` of their plans to rounding; the others are not in it."""
    if not truth_is_model(model, truth, steps):
        return {}
    if present is None:
        present = np.ones((steps + 1, model.m), dtype=bool)
    covs = replay_error_covariances(model, list(archs), present, criterion)
    if covs is None:
        return {}
    out = {}
    for a, (mse, P) in covs.items():
        bias = np.zeros(P.shape[:-1])
        nees, dm, definite = shared_nees_and_dm(P, bias, mse)
        if definite.all() and np.isfinite(nees).all() and np.isfinite(dm).all():
            out[a] = Expected(mse, bias, P, nees, dm)
    return out


class ExpectedBlocks:
    """`replay_expected` block of time by block, in order (`ReplayBlocks.error_covariances`)."""

    def __init__(self, blocks: ReplayBlocks) -> None:
        self.blocks = blocks

    @property
    def smoother(self) -> bool:
        """FBS is among the architectures: `window` needs its backward S (`backward`)."""
        return self.blocks.smoother

    def backward(self, k0: int, k1: int, present: np.ndarray, after: tuple | None):
        """FBS's backward pass over the block (`ReplayBlocks.backward`), from the log's end."""
        return self.blocks.backward(k0, k1, np.where(present, 0.0, np.nan), after)

    def window(self, k0: int, k1: int, present: np.ndarray, backward=None) -> dict[str, Expected]:
        """Each architecture's `Expected` (w, ...) at the instants k0..k1-1, `present` (w, m)
        their readings, `backward` FBS's (y_b, S) there."""
        out = {}
        for a, (mse, P) in self.blocks.error_covariances(k0, k1, present, backward).items():
            bias = np.zeros(P.shape[:-1])
            nees, dm, _ = shared_nees_and_dm(P, bias, mse)
            out[a] = Expected(mse, bias, P, nees, dm)
        return out


def replay_expected_blocks(
    model: System,
    truth: System,
    archs: Sequence[str],
    steps: int,
    block: int,
    criterion: str | None = None,
) -> ExpectedBlocks | MismatchBlocks | None:
    """`ExpectedBlocks` of one run of instants 0..`steps` in blocks of `block` instants where
    the truth is the model and the replay path takes every architecture; where the truth is
    not the model, the joint moments of the truth and the filters carried from block to
    block (`exact_mismatch.mismatch_blocks`); else None."""
    blocks = ReplayBlocks.of(model, archs, steps, block, criterion)
    if blocks is None:
        return None
    if not truth_is_model(model, truth, steps):
        from .exact_mismatch import mismatch_blocks

        return mismatch_blocks(model, truth, blocks)
    return ExpectedBlocks(blocks)
