"""One run with late sensors without plans: the one-run fast path (`architectures.replay`) on
the stacked model of `core.latency`.

The plans of late sensors are plans of the stacked model X_k = [x_k; ...; x_{k-W}] whose
measurement at k is what arrives at k, wrapped to keep the W last readings. One run needs no
maps: the readings of the stacked model are laid out once, z~[k, c] = the reading of slot c
(sensor j, lag l, its combination of the readings of instant k - l: `latency_corr`) where it
arrives at k, NaN elsewhere, and the stacked model's filters run on them through
`replay.replay_estimates`, the same formulas as the plans (so the same estimates to rounding,
tests/test_latency_corr.py). The estimate of x_k is the first block of the stacked one.

Covered: the filters fusing every sensor (CKF, on the decorrelated readings where correlated
ones arrive apart; HKF) and one sensor's (SKF), under reprocess and neglect. The per-sensor
rules fuse the locals' current blocks only (`latency_stacked.fused_plan`) and retrodiction is
a plan of its own: those go to the plans (None), as does a steady model with fixed
latencies and every reading present (the plans' steady shortcut repeats one map,
`filters.Steady`). A long log in blocks of time: the same filters carried from block to block
(`core.latency_blocks`, `stacked_readings` of a window reaching W instants back), the
per-sensor rules there too (their stacked locals carried with eq. (35)'s J, the rule on their
current blocks), which a log of one block still takes through the plans.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .architectures.plan import Estimate
from .architectures.replay import replay_estimates
from .latency import LateModel

__all__ = ["late_replay_estimates"]


def stacked_readings(z: np.ndarray, slots: np.ndarray, coef: np.ndarray | None) -> np.ndarray:
    """z~ (K+1, m~) of the run z (K+1, m) (NaN read as 0: absent slots are masked after):
    slot c = (sensor, lag l, component[, condition]) reads coef[c] . z[k - l] (default
    z[k - l, component])."""
    z0 = np.where(np.isnan(z), 0.0, z)
    K1, m = z0.shape
    coef = np.eye(m)[slots[:, 2]] if coef is None else coef
    out = np.full((K1, len(slots)), np.nan)
    for lag in np.unique(slots[:, 1]).tolist():
        cols = np.flatnonzero(slots[:, 1] == lag)
        out[lag:, cols] = z0[: K1 - lag] @ coef[cols].T
    return out


def late_replay_estimates(
    late: LateModel,
    archs: Sequence[str],
    z: np.ndarray,
    arrival: np.ndarray | None,
    criterion: str | None = None,
) -> dict[str, Estimate] | None:
    """Each architecture's estimate of the one run z (1, K+1, m) whose readings arrived at
    `arrival` (1, K+1, S) s (None: the fixed latencies'), as its plan gives it; None when an
    architecture is not covered here (module docstring) or the replay path declines."""
    if z.shape[0] != 1 or late.system.late == "retrodict":
        return None
    if late.per_run and arrival is None:
        return None
    if not late.per_run and late.system.time_invariant and not np.isnan(z).any():
        return None  # fixed latencies on a steady model: the plans repeat their steady step
    arrive = late.arrivals_of(arrival)
    present = ~np.isnan(z[0])
    n = late.system.n
    out: dict[str, Estimate] = {}
    for arch in archs:
        _, locals_kind, filters = late.filters_of(arch)
        if locals_kind not in ("centralised", "hierarchical", "single"):
            return None
        centre = late.centre_model() if locals_kind == "centralised" else None
        model, slots, coef = (late.stacked, late.slots, None) if centre is None else centre[:3]
        mask = late.stacked_mask(present, filters, None if arrive is None else arrive[0], centre)
        zs = np.where(mask, stacked_readings(z[0], slots, coef), np.nan)
        got = replay_estimates(model, [arch], zs[None], criterion)
        if got is None:
            return None
        e = got[arch]
        out[arch] = Estimate(
            np.ascontiguousarray(e.mean[..., :n]), np.ascontiguousarray(e.cov[..., :n, :n])
        )
    return out
