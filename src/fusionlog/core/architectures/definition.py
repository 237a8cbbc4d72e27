"""What an architecture is: one definition that every backend takes (DESIGN.md, "Architectures").

An architecture names the filters it runs and, where it fuses local filters, its fusion rule:

* ``centralised``   one Kalman filter on every sensor (CKF);
* ``single``        one Kalman filter on one sensor (SKF, ``SKF:<sensor>``);
* ``hierarchical``  local filters restarted from the fused prediction, with feedback (HKF);
* ``smoother``      the fixed-interval smoother on the centralised filter (FBS);
* ``per-sensor``    one local filter per sensor, no feedback, and a fusion *rule*.

A rule is written once, as a pure function of the locals at one instant (a batch of them):

    rule(P, J, criterion) -> (C, P_fused),    x_fused = C [x_1; ...; x_S]

with P (..., S, n, n) the locals' covariances, J (..., S n, S n) their joint error covariance
(eq. 35; only when the definition says `joint`, else None) and `criterion` covariance
intersection's cost ("trace" or "det"). The weights C (..., n, S n) depend on covariances only,
never on the measured values, so every rule here is linear in the data and has the exact
analysis (the plans' readout O = C, `core.exact`). The backends apply it: the linear plans and
their exact analysis (`track_to_track.build_rule`, shared and per run), the one-run replay path
and its exact analysis (`replay`, `core.exact_replay`), the EKF/UKF lanes (`core.nonlinear`).

Local filters started without a prior run in information form until their information is
invertible. A rule that can fuse them then (`information`: the paper's, `rules`) is also called
as rule(P, J, criterion, forms=F, found=D), F (S,) the locals' forms: where F[j],
P[..., j, :, :] is local j's information matrix Y_j and its state the information vector
y_j = Y_j x + g_j, J the covariance of the generalised errors g, and C weighs the states
[s_1; ...; s_S]; D a dict into which the rule may put its weights on the locals as "omega",
batch + (S,), which the plan keeps (`Plan.omega`). For any other rule the fused estimate is
undefined (NaN) while a local filter has no mean yet.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .plan import BuildRequest, Plan

#: The kinds of filters an architecture runs.
LOCALS = ("centralised", "single", "hierarchical", "smoother", "per-sensor")

#: A fusion rule: (P (..., S, n, n), J (..., S n, S n) or None, criterion) -> (C, P_fused);
#: with `Architecture.information` also (..., forms=F (S,), found=D).
Rule = Callable[..., tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Architecture:
    """A registered architecture (`registry.register`).

    `name` is what the CLI, topics and summaries use; `locals` one of `LOCALS`; `rule` and
    `joint` (whether the rule reads J) for ``per-sensor``; `information` whether the rule also
    fuses locals still in information form (module docstring); `build` a plan builder of its
    own for the other kinds (a rule's plan is `track_to_track.build_rule`'s); `takes_sensor`
    for ``SKF:<sensor>``; `min_sensors` the fewest sensors it fuses; `default` whether a
    scenario without an `[estimate] architectures` list runs it; `color` its colour in every
    recording (None: one from a hash of the name)."""

    name: str
    summary: str
    locals: str
    rule: Rule | None = None
    joint: bool = False
    information: bool = False
    build: Callable[[BuildRequest], Plan] | None = None
    takes_sensor: bool = False
    min_sensors: int = 0
    default: bool = False
    color: tuple[int, int, int] | None = None

    def __post_init__(self) -> None:
        if not self.name or any(c in self.name for c in ":/ \t\n"):
            raise ValueError(f"architecture name {self.name!r}: no ':', '/' or blanks")
        if self.locals not in LOCALS:
            raise ValueError(f"architecture {self.name}: locals {self.locals!r} not in {LOCALS}")
        if (self.locals == "per-sensor") != (self.rule is not None):
            raise ValueError(f"architecture {self.name}: a rule exactly for per-sensor locals")
        if self.build is not None and self.rule is not None:
            raise ValueError(f"architecture {self.name}: a rule is compiled by build_rule")
        if self.rule is None and self.build is None:
            raise ValueError(f"architecture {self.name}: {self.locals} needs a plan builder")

    @property
    def fuses_locals(self) -> bool:
        """One local filter per sensor, fused by `rule`."""
        return self.locals == "per-sensor"
