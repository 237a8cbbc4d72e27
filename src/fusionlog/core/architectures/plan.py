"""What an architecture compiles to: a plan of per-step affine maps, and what it is built from.

For every step k the estimator's internal state s (the mean of each filter, or the information
vector y = P^-1 x of a filter that has no covariance yet) follows

    s_k = T_k s_{k-1} + U_k z_k,        x_hat_k = O_k s_k,        P_k (the covariance it reports)

with z_k the stacked measurement of eq. (30). The smoother (FBS) adds a backward information
filter and a forward/backward fusion, eqs. (25)-(28) (`SmootherMaps`). Maps carry a leading run
dimension when runs differ in which measurements are present (`Plan.per_run`); there, the
transition of a stack of local filters is kept as its diagonal blocks (`BlockDiagonal`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..linalg import stack_diag
from ..model import System


@dataclass
class BlockDiagonal:
    """The matrix blockdiag(B_1, ..., B_S) of blocks (..., S, a, b), kept as the blocks.

    A per-run plan of S local filters has a transition T that is block-diagonal in every run:
    dense, (M, S a, S b) would be mostly zeros, and writing them out costs more than the
    recursion that produced them. Shared plans keep dense maps (the exact analysis uses them).
    """

    blocks: np.ndarray

    @property
    def shape(self) -> tuple[int, ...]:
        *lead, S, a, b = self.blocks.shape
        return (*lead, S * a, S * b)

    @property
    def ndim(self) -> int:
        return self.blocks.ndim - 1

    def dense(self) -> np.ndarray:
        """The matrix itself, (..., S a, S b)."""
        return stack_diag(self.blocks)


@dataclass
class StepMap:
    """Affine map of one step: s_k = T s_{k-1} + U z_k, x_hat = O s_k, reported covariance P."""

    T: np.ndarray | BlockDiagonal  # (..., d, d_prev)
    U: np.ndarray  # (..., d, m)
    O: np.ndarray  # (..., n, d)
    P: np.ndarray  # (..., n, n)
    # s = D x when the estimator knows the state exactly (I for a mean, Y for an information
    # vector): lets the exact analysis work with s - D x, which stays small when x grows.
    D: np.ndarray | None = None  # (..., d, n)


@dataclass
class SmootherMaps:
    """Backward information filter and forward/backward fusion of FBS, eqs. (25)-(28).

    y_b[K] = 0;  y_b[k] = L[k] (y_b[k+1] + V[k+1] z[k+1]);  x_hat[k] = A[k] s_f[k] + B[k] y_b[k].
    """

    L: list[np.ndarray]  # k = 0..K-1
    V: list[np.ndarray]  # k = 0..K (V[0] unused)
    A: list[np.ndarray]
    B: list[np.ndarray]
    P: list[np.ndarray]


@dataclass
class DenseMap:
    """A shared plan over a short horizon as one affine map of the whole measurement history:
    vec(x_hat) = vec(z) W + c, W ((K+1) m, (K+1) n), c ((K+1) n,). Filled by `run_plan`."""

    W: np.ndarray
    c: np.ndarray


@dataclass
class Plan:
    """A compiled architecture: initial internal state and the per-step maps.

    Steps that repeat a steady-state map are the same `StepMap` object (so are the smoother's
    maps), which the executor and the exact analysis use to do the work once.
    """

    name: str
    s0: np.ndarray  # (d0,)
    steps: list[StepMap]
    smoother: SmootherMaps | None = None
    per_run: bool = False
    D0: np.ndarray | None = None  # (d0, n): D of the initial state s0
    system: System | None = None  # the model the plan was built for
    #: Whether the plan's mask has every measurement component present at every step.
    complete: bool = True
    #: Covariance intersection's weights, batch + (K+1, S) (NaN at steps without a fusion);
    #: None for the other architectures.
    omega: np.ndarray | None = None
    #: The dense form of a shared plan, computed by `run_plan` on first use.
    dense: DenseMap | None = field(default=None, repr=False)

    @property
    def reported_cov(self) -> np.ndarray:
        """(K+1, n, n) shared or (M, K+1, n, n) per run; NaN where the estimate is undefined."""
        Ps = self.smoother.P if self.smoother is not None else [st.P for st in self.steps]
        return np.stack(Ps, axis=-3)

    @property
    def steady_from(self) -> int:
        """First k from which every step is the same map (the steady state, see `Steady`)."""
        steps = self.steps
        k = len(steps) - 1
        while k > 0 and steps[k - 1] is steps[-1]:
            k -= 1
        return k


@dataclass
class Estimate:
    """An architecture's output for M runs: mean (M, K+1, n); cov (K+1, n, n) or (M, K+1, n, n)."""

    mean: np.ndarray
    cov: np.ndarray

    @property
    def shared_cov(self) -> bool:
        return self.cov.ndim == 3


@dataclass
class BuildRequest:
    """What a builder compiles: `name` (as asked, e.g. "SKF:s2") on `system` for the presence
    mask `present` ((K+1, m) shared or (M, K+1, m) per run), with `sensor` the sensor an SKF
    uses and `criterion` covariance intersection's cost.

    `step` is the step being built, kept up to date by the builders so that a numerical
    failure can name it (None before the first step and while the whole horizon is processed
    at once).
    """

    system: System
    name: str
    present: np.ndarray
    sensor: str | None = None
    criterion: str = "trace"
    step: int | None = None

    @property
    def batch(self) -> tuple[int, ...]:
        """() for a shared mask, (M,) for one per run."""
        return self.present.shape[:-2]

    @property
    def horizon(self) -> int:
        """K + 1, the number of instants."""
        return self.present.shape[-2]
