"""A one-run replay in blocks of time (issue 34): the plan-free path of `replay` carried from
block to block, so that a recorded log with irregular instants, per-message R, missing readings
(and a partial truth, which only the evaluation sees) is estimated in memory that does not grow
with its instants.

Each block [k0, k1) runs `replay._Replay` from the state the block before left
(`replay.Carried`: the slots' covariances -- CKF, the per-sensor local KFs, HKF's fused filter
--, every filter's mean, the local filters' joint error covariance of eq. (35) where a rule
reads it, HKF's error covariance for the exact route): the same formulas, instant by instant,
as the whole log (eqs. 14-18, HKF 36-40, the rules 6-7 and 32-35), the block's first instant
predicted from the carried state. FBS's backward information filter (eqs. 25-28) runs from the
log's end: `backward` takes the blocks in reverse order, carrying S, y_b and the information
of the block after's first instant; the caller keeps its vectors (`driver.long_log` spools
them to an unnamed temporary file) for the forward pass, which fuses them block by block.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ...errors import NumericalError
from ..linalg import NUMERICAL_FAILURES, all_finite
from ..model import System
from .plan import Estimate
from .replay import MASKED_BYTES_AT_MOST, Carried, _bases, _hkf_wide, _Replay
from .replay_filters import backward_information, backward_means, information, masked_rows

__all__ = ["ReplayBlocks", "system_window"]


def system_window(system: System, k0: int, k1: int, into_first: bool) -> System:
    """The system on the instants k0..k1-1: its per-instant R of those instants, and its F, Q
    (a nonlinear motion's intervals) into k0+1..k1-1 (`into_first`: into k0 too, the block's
    first instant predicted from the one before). A time-invariant system is itself."""
    per_interval = {f: getattr(system, f) for f in ("Fs", "Qs", "intervals")}
    if all(v is None for v in per_interval.values()) and system.Rs is None:
        return system
    a = k0 - 1 if into_first else k0
    got = {f: None if v is None else v[a : k1 - 1] for f, v in per_interval.items()}
    Rs = system.Rs[k0:k1] if system.Rs is not None else None
    return dataclasses.replace(system, Rs=Rs, **got)


class ReplayBlocks:
    """The architectures `archs` of one run of `system` (`steps` + 1 instants) block of time by
    block, in order (`estimates`, `error_covariances`); `backward` (FBS) in reverse order
    first. `ReplayBlocks.of` says whether the path takes the system."""

    def __init__(self, system: System, archs: Sequence[str], steps: int, criterion: str, bases):
        self.system, self.archs, self.steps, self.criterion = system, list(archs), steps, criterion
        self.bases = bases
        self.need = {b.locals for b, _ in bases}
        self.smoother = "smoother" in self.need
        self.carried: Carried | None = None
        self.next_instant = 0

    @classmethod
    def of(
        cls,
        system: System,
        archs: Sequence[str],
        steps: int,
        block: int,
        criterion: str | None = None,
    ) -> ReplayBlocks | None:
        """The blocked path of `replay` for one run in blocks of `block` instants; None where
        that path does not apply (a nonlinear model or one without a prior, HKF on noise levels
        spanning 1e8, a name no definition has, a block's masked H and R beyond
        `MASKED_BYTES_AT_MOST`)."""
        if system.prior is None or system.motion_model is not None or not system.linear:
            return None
        S, m, n = len(system.sensors), system.m, system.n
        if block * (2 * S + 2) * m * (m + n) * 8 > MASKED_BYTES_AT_MOST:
            return None
        bases = _bases(system, archs)
        if bases is None or any(_hkf_wide(system, b) for b, _ in bases):
            return None
        return cls(system, archs, steps, criterion or system.ci_criterion, bases)

    def window_system(self, k0: int, k1: int, into_first: bool) -> System:
        """The system on the instants k0..k1-1 (`system_window`; a late model's stacked one
        is made per block, `core.latency_blocks`)."""
        return system_window(self.system, k0, k1, into_first)

    def replay(self, system: System, z: np.ndarray, backward) -> _Replay:
        """The recursions of one block from the carried state (a late model where correlated
        readings arrive apart keeps their noises too, `core.latency_apart`)."""
        return _Replay(system, z, self.need, self.criterion, self.carried, backward)

    def _block(self, k0: int, k1: int, z: np.ndarray, backward, what):
        """what(_Replay of the block from the carried state); the block's last state carried.
        A numerical failure names the block's instants (no plans to hand it to, as the
        whole log's path does: its earlier blocks are written)."""
        if k0 != self.next_instant:
            raise ValueError(f"blocks of time in order: {k0} after {self.next_instant}")
        system = self.window_system(k0, k1, k0 > 0)
        try:
            with np.errstate(all="ignore"):
                r = self.replay(system, z, backward)
                out = what(r)
        except (NumericalError, *NUMERICAL_FAILURES) as e:
            raise NumericalError(f"instants {k0}..{k1 - 1}: {e}") from None
        self.carried = r.carried()
        x = self.carried.x
        if not all_finite(self.carried.P) or (x is not None and not all_finite(x)):
            raise NumericalError(f"instants {k0}..{k1 - 1}: a number beyond the float range")
        self.next_instant = k1
        return out

    def estimates(
        self, k0: int, k1: int, z: np.ndarray, backward: tuple[np.ndarray, np.ndarray] | None
    ) -> dict[str, Estimate]:
        """Each architecture's estimate (mean (1, w, n), cov (w, n, n)) at the instants
        k0..k1-1 from their readings z (w, m) (NaN: missing) and the state carried from the
        block before; FBS takes the block's (y_b (w, n), S (w, n, n)) of `backward`."""
        return self._block(k0, k1, z, backward, lambda r: r.estimates(self.archs, self.bases))

    def error_covariances(
        self, k0: int, k1: int, present: np.ndarray, backward=None
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Each architecture's true error covariance and reported covariance (w, n, n) at the
        instants k0..k1-1 under the model (`replay.replay_error_covariances`), `present`
        (w, m) the readings there; FBS takes the block's `backward` (its S: the y_b do not
        matter)."""
        z = np.where(present, 0.0, np.nan)
        return self._block(
            k0, k1, z, backward, lambda r: r.error_covariances(self.archs, self.bases)
        )

    def backward(
        self, k0: int, k1: int, z: np.ndarray, after: tuple | None
    ) -> tuple[np.ndarray, np.ndarray, tuple]:
        """FBS's backward information filter over the instants k0..k1-1 (eq. 25, as
        `replay_filters.backward_information` and `backward_means` over the whole log), from
        their readings z (w, m) and `after` (what the block after returned; None for the log's
        last block): y_b (w, n), S (w, n, n), and what the block before takes."""
        sysw = system_window(self.system, k0, k1, False)
        w, m = z.shape
        present = ~np.isnan(z)
        R = sysw.Rs if sysw.Rs is not None else np.broadcast_to(sysw.R, (w, m, m))
        Hm, Rm = masked_rows(self.system.linear_measurement(), R, present[:, None, :])
        W, c = information(Hm[:, 0], Rm[:, 0], np.where(present, z, 0.0))
        last = after is None
        Fs, Qs = self.system.transitions(k0, k1 - 1 if last else k1)
        if last:
            L, Smat = backward_information(W, Fs, Qs)
            yb = backward_means(L, c)
        else:
            S1, y1, W1, c1 = after
            L, Smat = backward_information(np.concatenate([W, W1[None]]), Fs, Qs, S1)
            yb = backward_means(L, np.concatenate([c, c1[None]]), y1)
            Smat, yb = Smat[:w], yb[:w]
        return yb, Smat, (Smat[0].copy(), yb[0].copy(), W[0].copy(), c[0].copy())
