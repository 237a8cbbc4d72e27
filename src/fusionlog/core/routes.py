"""Which route computes a result where there are several, decided in one place.

The exact analysis of an evaluation (Section IV's expected MSE, NEES and DM) has three routes:

* ``per-run``: runs whose measurement patterns differ (dropouts): each run's exact values given
  its pattern, summed block by block (`exact.ConditionalExpected`) and averaged;
* ``one-log``: one recorded run whose truth is the filters' model: the error covariances the
  filters already compute (`exact_replay.replay_expected`), where that path covers the
  architecture, the plans' analysis for the others;
* ``plans``: the plan of the shared pattern analysed once (`exact.analyse`, eq. 35's joint
  covariance propagated through the plan's maps).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from .reference import reference_paths

if TYPE_CHECKING:
    import numpy as np

    from .model import System

__all__ = ["exact_route", "shared_expected"]


def exact_route(per_run: bool, runs: int, recorded: bool) -> str:
    """The route of an evaluation's exact analysis: ``per-run`` when the runs' patterns differ,
    ``one-log`` for one recorded run (unless the reference paths are forced), else ``plans``."""
    if per_run:
        return "per-run"
    if runs == 1 and recorded and not reference_paths():
        return "one-log"
    return "plans"


def shared_expected(
    route: str,
    model: System,
    truth: System,
    archs: Sequence[str],
    present: np.ndarray | None,
    steps: int,
    criterion: str,
    plan_of: Callable[[str], object],
) -> Callable[[str], object]:
    """For a shared pattern `present` (K+1, m) (None: complete), the exact expected values of
    an architecture (`exact.Expected`) by `route` (``one-log`` or ``plans``): a function of the
    architecture's name, each computed on first use (`plan_of(arch)` its plan with that mask,
    built only where the plans' analysis is needed)."""
    from .exact import analyse
    from .late_policy import is_late

    fast: dict[str, object] = {}
    # without plans where the truth is the model; not with late sensors, whose filters are
    # the late plans' (the one-log path's covariances are of the readings fused on time)
    if route == "one-log" and not is_late(model):
        from .exact_replay import replay_expected

        fast = replay_expected(model, truth, archs, present, steps, criterion)

    def expected(arch: str) -> object:
        return fast[arch] if arch in fast else analyse(plan_of(arch), truth)

    return expected
