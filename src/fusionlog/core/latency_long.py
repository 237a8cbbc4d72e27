"""A long one-run log with late sensors in blocks of time (issues 30 and 34): the late plans of
a short horizon standing for the whole log (`architectures.long_log.SteadyLog`).

With fixed latencies the plans of every policy are plans on the measurements as taken
(`core.latency`): reprocess and neglect are filters on the state stacked over the latency
window, wrapped to keep the last W readings; retrodiction keeps its current estimate, the
estimates stored over the window and the last W readings (`core.retrodict`). So each plan's
internal state s_k already holds everything that crosses a block edge -- the stacked state
(the instants a reprocess rewinds to), the stored estimates Al1 retrodicts from, and the
readings taken but not yet arrived -- and carrying s_{k0-1} from block to block
(`SteadyLog.forward`) is the whole log's recursion.

Past the latency window the same lags arrive at every instant, so the maps become steady:
reprocess and neglect by `filters.constant_tail` (the shortcut repeats one map object),
retrodiction once its Riccati recursion repeats to the last bit (`_repeats_shared`: a step
equal bit for bit to the one before is that object, so nothing changes numerically). The
steadiness the long path needs is then `long_log`'s own check at the horizon's middle.

Retrodiction with the rules that read the locals' joint covariance (MSC-GMF, AVG) is here
too: J is propagated from the covariance of [x_k; s_k - D_k x_k] (`retrodict_fused.
_error_moments`, D the plans' error form), which stays of the size of the errors and, with
the locals' recursions, reaches its fixed point to the last bit past the latency window
(pipeline/latency.toml retrodicted: every step from the 47th the same), so the rule's maps
become steady and the short plans stand for the log (`tests/test_long_late_more.py`). Where
D is 0 (a transition over the window ill-conditioned, `retrodict.Transitions.back`) J carries
the truth's covariance: where that grows, J never repeats and `steady_log` finds no steady
middle; such a log (None here) is retrodicted in blocks by `core.retrodict_blocks`, which
needs nothing to repeat: each block's plans from the gain recursions carried.

Not here: random delays and recorded arrivals (the plans differ per arrival pattern) and
missing readings go to the plan-free stacked filters carried block to block
(`core.latency_blocks`: CKF, HKF, SKF and the per-sensor rules under reprocess and neglect)
and, retrodicted, to the plans of each block with the state of the block before
(`core.retrodict_blocks`: every architecture but FBS). Nonlinear late
sensors need no plans: the EKF/UKF lanes carry their late state from block to block
themselves (`nonlinear.late_feed`, `nonlinear.long_log`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .architectures import Plan, build_plan, definition, long_log, parse_arch
from .architectures.long_log import SteadyLog, steady_log
from .late_policy import is_late, random_delays
from .latency import LateModel
from .model import System
from .retrodict import Transitions

__all__ = ["analysis_rtol", "late_steady_log"]

_FIELDS = ("T", "U", "O", "P", "D")


def _repeats_shared(plan: Plan) -> Plan:
    """`plan` with each step that equals the step before bit for bit replaced by that step's
    object (the identity the steady shortcut and `SteadyLog` look for), in place."""
    steps = plan.steps
    for k in range(1, len(steps)):
        a, b = steps[k - 1], steps[k]
        if a is not b and all(np.array_equal(getattr(a, f), getattr(b, f)) for f in _FIELDS):
            steps[k] = a
    return plan


def late_steady_log(
    system: System,
    archs: Sequence[str],
    steps: int,
    criterion: str = "trace",
    times: np.ndarray | None = None,
) -> SteadyLog | None:
    """The late plans of a short horizon standing for a one-run log of instants 0..`steps`
    whose readings are all present (`SteadyLog`, its plans built by `LateModel.build` on the
    horizon's first instants of `times`, default k dt), or None where they do not stand for
    it: no late sensor, delays that differ per reading, a model that is not time-invariant,
    per-message R, or plans not steady (module docstring)."""
    if not is_late(system) or random_delays(system) or system.Rs is not None:
        return None
    if not (system.linear and system.time_invariant):
        return None
    if steps + 1 > long_log.HORIZONS[-1] and _j_without_error_form(system, archs):
        return None
    models: dict[int, LateModel] = {}

    def build(arch: str, K: int) -> Plan:
        late = models.get(K)
        if late is None:
            clock = None if times is None else np.asarray(times[: K + 1], float)
            late = models[K] = LateModel.of(system, K, clock)
            assert late is not None
        plan = late.build(build_plan, arch, None, criterion=criterion)
        return _repeats_shared(plan) if system.late == "retrodict" else plan

    return steady_log(system, archs, steps, criterion, build=build)


def _j_without_error_form(system: System, archs: Sequence[str]) -> bool:
    """Whether a rule reading J (MSC-GMF, AVG) retrodicts where the error form has a zero block
    (a transition over the latency window ill-conditioned, `retrodict.Transitions.back`): J
    then carries the truth's covariance, which grows with an unstable model, and never repeats,
    so the plans of every horizon (up to 65 536 instants, ~1 GB of maps) would be built to
    find no steady middle; the log goes to `core.retrodict_blocks` without them (a stable one
    too: the same numbers as its steady plans', to rounding)."""
    if system.late != "retrodict":
        return False
    names = [s.name for s in system.sensors]
    if not any(definition(parse_arch(a, names)[0]).joint for a in archs):
        return False
    late = LateModel.of(system, 64, None)
    assert late is not None
    back = Transitions(system).back
    return any(not back(0, q)[0].any() for q in range(1, late.window + 1))


def analysis_rtol(truth: System, plans: SteadyLog, mse: float) -> float:
    """How closely the exact analysis of late plans can repeat at the horizon's middle c
    (`long_log.converged`'s rtol). The late plans carry an error form D (reprocess and
    neglect: `latency_stacked.wrap`, `latency_joint`; retrodict: `retrodict`), with which the
    analysis's values stay of the size of the errors; but where F is singular or
    ill-conditioned (cond > 1e8), varies per step (`wrap`) or a sensor is nonlinear, D is 0
    (in the retrodict plans, the blocks whose transition is ill-conditioned), and the
    analysis's values (of size `mse`) are then differences of numbers of the size of the
    truth's covariance at c. The bound covers that case: 64 roundings of that covariance's
    largest entry, relative to `mse` (at least 1e-9, the on-time plans' rtol)."""
    prior = truth.initial if truth.initial is not None else truth.prior
    if prior is None:
        return 1e-9
    P, F, Q = prior.cov, truth.F, truth.GQG
    for _ in range(plans.c):
        P = F @ P @ F.T + Q
    scale = float(np.abs(P).max())
    return max(1e-9, 64 * float(np.finfo(float).eps) * scale / max(mse, 1e-300))
