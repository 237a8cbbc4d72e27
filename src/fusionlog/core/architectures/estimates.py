"""One architecture's estimates of measurements z, computed on the spot: the plan of z's
pattern run on z, or, for one run, the replay path without plans (`replay`), or for a nonlinear
model the EKF/UKF lanes (`core.nonlinear`). No cache: a caller estimating many blocks of one
log keeps its plans in the driver above (`fusionlog.driver.PlanCache`)."""

from __future__ import annotations

import numpy as np

from ..reference import reference_paths
from .executor import run_plan
from .plan import Estimate
from .registry import build_plan


def shared_pattern(z: np.ndarray) -> np.ndarray | None:
    """The (K+1, m) mask of present measurements when every run of z (M, K+1, m) has the same
    one, else None.

    A pattern shared by all runs (a sensor at half rate, a gap in every run) keeps the
    shared-gain path: one plan built with that mask serves all runs. The usual case, nothing
    missing, is answered by one pass over z (comparing every run's mask with the first costs
    seven times that).
    """
    missing = np.isnan(z)
    if not missing.any():
        return np.ones(z.shape[1:], dtype=bool)
    present = ~missing
    return present[0] if (present == present[:1]).all() else None


def estimate(system, z: np.ndarray, arch: str, criterion: str | None = None) -> Estimate:
    """Run architecture `arch` on measurements z (M, K+1, m) (NaN: missing) of `system` (on
    its instants, `System.on_times`); `criterion` CI's cost (default the system's)."""
    if not system.linear:  # EKF/UKF: no plans, every run has its own linearisation
        from ..nonlinear.architectures import estimate as nonlinear_estimate

        track = nonlinear_estimate(system, arch, z, None)
        return Estimate(track.mean, track.cov)
    if z.shape[0] == 1 and not reference_paths():
        from .replay import replay_estimates  # on first use: a replay's path

        fast = replay_estimates(system, [arch], z, criterion)
        if fast is not None:
            return fast[arch]
    steps = z.shape[1] - 1
    pattern = shared_pattern(z)
    if pattern is not None:
        mask = None if pattern.all() else pattern
        return run_plan(build_plan(system, arch, steps, mask, criterion), z)
    present = ~np.isnan(z)
    return run_plan(build_plan(system, arch, steps, present, criterion, history_nodes=True), z)
