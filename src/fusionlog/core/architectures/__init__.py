"""The fusion architectures of Ajgl-Simandl-Dunik (Sec. V) as per-step linear maps.

Every architecture here is linear in the data once its gains are fixed, and its gains depend only
on the model and on which measurements are present, not on the measured values. So each one is
compiled into a *plan*: for every step k an affine map on the estimator's internal state s,

    s_k = T_k s_{k-1} + U_k z_k,        x_hat_k = O_k s_k,        P_k (the covariance it reports)

where z_k is the stacked measurement of eq. (30). Applying a plan to M runs is one matrix product
per step (the shared-gain fast path). When runs differ in which measurements are present (NaN =
missing), the same code builds the maps with a leading run dimension (the per-run path: the batch
kernels of `core.linalg`, the runs grouped by measurement history, `HistoryNodes`). And because
the maps are explicit, `core.exact` propagates the true error covariance through them exactly.

The internal state s is the mean of each filter, or, while a filter started without a prior has not
yet gathered enough information for a covariance to exist, its information vector y = P^-1 x.

Modules: `plan` (the plan types), `definition` (what an architecture is: its local filters
and fusion rule), `registry` (the registered definitions, `register`, `build_plan`), `rules`
(the paper's fusion rules as functions of the locals' covariances, each written once), `ici`
(ICI's definition), `executor` (`run_plan`),
`estimates` (`estimate`: one architecture on some runs, no cache; a block of runs with the
plan cache is the driver's, `fusionlog.driver.estimate_block`), the builders by family:
`filters` (the Kalman-filter machinery), `single` (CKF, SKF), `hkf`, `track_to_track` (the
local filters and `build_rule`, which compiles every registered rule), `fbs`; and
`replay` with `replay_filters`: one run of a recorded log estimated without plans (the same
numbers to rounding, no maps for the exact analysis), which `estimate` and the driver take
for one run.
"""

from .definition import LOCALS, Architecture, Rule
from .estimates import estimate, shared_pattern
from .executor import DENSE_MAX_STEPS, STEADY_BLOCK, run_plan
from .plan import (
    BlockDiagonal,
    BuildRequest,
    DenseMap,
    Estimate,
    HistoryNodes,
    Plan,
    SmootherMaps,
    StepMap,
)
from .registry import (
    REGISTRY,
    STATE_ARCHITECTURES,
    build_plan,
    definition,
    parse_arch,
    register,
    unregister,
)

__all__ = [
    "DENSE_MAX_STEPS",
    "REGISTRY",
    "STATE_ARCHITECTURES",
    "STEADY_BLOCK",
    "Architecture",
    "LOCALS",
    "Rule",
    "BlockDiagonal",
    "BuildRequest",
    "DenseMap",
    "Estimate",
    "HistoryNodes",
    "Plan",
    "SmootherMaps",
    "StepMap",
    "build_plan",
    "definition",
    "estimate",
    "parse_arch",
    "register",
    "run_plan",
    "shared_pattern",
    "unregister",
]
