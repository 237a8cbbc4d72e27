"""What an architecture compiles to: a plan of per-step affine maps, and what it is built from.

For every step k the estimator's internal state s (the mean of each filter, or the information
vector y = P^-1 x of a filter that has no covariance yet) follows

    s_k = T_k s_{k-1} + U_k z_k,        x_hat_k = O_k s_k,        P_k (the covariance it reports)

with z_k the stacked measurement of eq. (30). The smoother (FBS) adds a backward information
filter and a forward/backward fusion, eqs. (25)-(28) (`SmootherMaps`). Maps carry a leading run
dimension when runs differ in which measurements are present (`Plan.per_run`); there, the
transition of a stack of local filters is kept as its diagonal blocks (`BlockDiagonal`), and
the maps of a step are built once per distinct measurement history (`HistoryNodes`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..linalg import stack_diag, take_runs
from ..model import System


@dataclass
class HistoryNodes:
    """Runs grouped by their measurement history, the per-run path's unit of work.

    Gains and covariances at step k depend only on which measurements were present at steps
    0..k, so the runs whose presence masks agree at every step <= k share them: one *node* of
    step k stands for all of them. With 10 % of the measurements of three sensors missing at
    random, 10^4 runs over 21 steps make about 118 000 nodes instead of 210 000 run-steps, most
    of the saving in the first steps, where few histories exist.

    `index[k]` (M,) is each run's node at step k, `parent[k]` (U_k,) each node's node at step
    k - 1 (the single root, 0, at k = 0) and `present[k]` (U_k, m) each node's mask at k.
    """

    index: list[np.ndarray]
    parent: list[np.ndarray]
    present: list[np.ndarray]

    @classmethod
    def of(cls, present: np.ndarray) -> HistoryNodes:
        """The nodes of the per-run mask `present` (M, K+1, m)."""
        M, K1, m = present.shape
        index, parent, masks = [], [], []
        ids, count = np.zeros(M, dtype=np.intp), 1
        if m <= 4:  # every step's masks as numbers 0..2^m - 1 at once
            u = present.view(np.uint8)
            all_codes = u[..., 0].astype(np.intp)
            for j in range(1, m):
                all_codes |= u[..., j].astype(np.intp) << j
            bits = (np.arange(1 << m)[:, None] >> np.arange(m) & 1).astype(bool)
        for k in range(K1):
            if m <= 4:
                codes, patterns = all_codes[:, k], bits
            else:
                codes, patterns = _mask_codes(present[:, k, :])  # the distinct masks (P, m)
            P = len(patterns)
            # (parent, mask) pairs numbered in order through a table of all pairs (no sort)
            # while that table is small.
            key = ids * P + codes
            if count * P <= 1 << 22:
                seen = np.zeros(count * P, dtype=bool)
                seen[key] = True
                keys = np.flatnonzero(seen)
                number = np.empty(count * P, dtype=np.intp)
                number[keys] = np.arange(len(keys))
                ids = number[key]
            else:
                keys, ids = np.unique(key, return_inverse=True)
            count = len(keys)
            index.append(ids)
            parent.append(keys // P)
            masks.append(np.take(patterns, keys % P, axis=0))
        return cls(index, parent, masks)

    @property
    def count(self) -> int:
        """The number of nodes over all steps."""
        return sum(len(p) for p in self.parent)


def _mask_codes(pk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each run's mask (M, m) as a number 0..P-1, equal numbers for equal masks, and the P
    distinct masks (P, m)."""
    M, m = pk.shape
    if m <= 16:
        u = pk.view(np.uint8)
        code = u[:, 0].astype(np.intp)
        for j in range(1, m):
            code |= u[:, j].astype(np.intp) << j
        seen = np.zeros(1 << m, dtype=bool)
        seen[code] = True
        used = np.flatnonzero(seen)
        number = np.empty(1 << m, dtype=np.intp)
        number[used] = np.arange(len(used))
        return number[code], (used[:, None] >> np.arange(m) & 1).astype(bool)
    packed = np.packbits(pk, axis=1)
    raw = np.ascontiguousarray(packed).view(np.dtype((np.void, packed.shape[1]))).ravel()
    _, first, codes = np.unique(raw, return_index=True, return_inverse=True)
    return codes, pk[first]


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
    #: Per run, when the steps' maps were built per measurement history: each run's node at
    #: every step (`HistoryNodes.index`); the maps of step k then have a leading node axis
    #: instead of the run axis (the smoother's maps stay per run). See `per_run_maps`.
    nodes: list[np.ndarray] | None = None

    def per_run_maps(self) -> Plan:
        """The plan with a leading run axis on every per-run map (the maps of each run's node
        gathered), as consumers that index maps by run expect; itself if it has that."""
        if self.nodes is None:
            return self
        steps = [
            StepMap(*(take_map(getattr(st, f), idx) for f in ("T", "U", "O", "P", "D")))
            for st, idx in zip(self.steps, self.nodes, strict=True)
        ]
        return dataclasses.replace(self, steps=steps, nodes=None, dense=None)

    @property
    def reported_cov(self) -> np.ndarray:
        """(K+1, n, n) shared or (M, K+1, n, n) per run; NaN where the estimate is undefined."""
        if self.smoother is not None:
            return np.stack(self.smoother.P, axis=-3)
        if self.nodes is None:
            return np.stack([st.P for st in self.steps], axis=-3)
        P0 = self.steps[0].P
        out = np.empty((len(self.nodes[0]), len(self.steps)) + P0.shape[-2:])
        for k, (st, idx) in enumerate(zip(self.steps, self.nodes, strict=True)):
            out[:, k] = take_runs(st.P, idx) if st.P.ndim > 2 else st.P
        return out

    @property
    def steady_from(self) -> int:
        """First k from which every step is the same map (the steady state, see `Steady`)."""
        steps = self.steps
        k = len(steps) - 1
        while k > 0 and steps[k - 1] is steps[-1]:
            k -= 1
        return k


def take_map(A: np.ndarray | BlockDiagonal | None, idx: np.ndarray | None):
    """A map of a step's nodes for the runs `idx` (a map shared by all, or idx None, as it is)."""
    if A is None or idx is None or A.ndim == 2:
        return A
    if isinstance(A, BlockDiagonal):
        return BlockDiagonal(take_runs(A.blocks, idx)) if A.blocks.ndim > 3 else A
    return take_runs(A, idx)


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
    #: Per run: the runs grouped by history; the builder then works on nodes (`mask`, `parent`).
    nodes: HistoryNodes | None = None

    @property
    def batch(self) -> tuple[int, ...]:
        """() for a shared mask, (M,) for one per run, (1,) -- the root, before step 0 -- when
        the runs are grouped by history (the batch of step k is then its nodes, see `parent`)."""
        return (1,) if self.nodes is not None else self.present.shape[:-2]

    def mask(self, k: int) -> np.ndarray:
        """The presence mask of step k for what is built: (m,) shared, (M, m) per run, or
        (U_k, m) per node."""
        return self.present[..., k, :] if self.nodes is None else self.nodes.present[k]

    def begin(self, k: int) -> np.ndarray | None:
        """Start building step k (a numerical failure names it): its `parent`."""
        self.step = k
        return self.parent(k)

    def parent(self, k: int) -> np.ndarray | None:
        """Per node: the node of step k - 1 of each node of step k, to carry a recursion's
        state from step to step (`linalg.take_runs`); None otherwise."""
        return None if self.nodes is None else self.nodes.parent[k]

    @property
    def node_index(self) -> list[np.ndarray] | None:
        """For `Plan.nodes`."""
        return None if self.nodes is None else self.nodes.index

    @property
    def horizon(self) -> int:
        """K + 1, the number of instants."""
        return self.present.shape[-2]
