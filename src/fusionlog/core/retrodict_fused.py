"""Retrodiction where the late sensor is fused by more than one filter: the hierarchical filter's
centre and the track-to-track locals (DESIGN.md "Late measurements"; Al1 itself: `retrodict`).

*HKF.* Each local filter of the hierarchical KF restarts from the fused prediction and hands
the centre its equivalent measurement P_j^-1 x_j - P^-1 x = H_j^T R_j^-1 z_j, information
H_j^T R_j^-1 H_j (eqs. 36-37): whatever prediction it restarted from, it is sensor j's
reading in information form. A late reading reaches the centre as that pair, stamped with its
time, and the centre retrodicts it with Al1 in information form: with C = cov(x_k, x_d) and
P(d|k) as in Al1, x(k|d) = x(k|k) + C (I + I_d P(d|k))^-1 (i_d - I_d x(d|k)), I_d, i_d the
sum over the sensors of instant d. Since H^T (H P H^T + R)^-1 = (I + H^T R^-1 H P)^-1 H^T R^-1,
that is Al1 on the readings with the noise HKF believes, block-diagonal R (its on-time form is
the CKF on that R as well): the plan is the retrodicting filter on every sensor with R's
cross-sensor blocks removed.

*Track to track.* Each local filter applies Al1 to its own sensor's late readings
(`retrodict_maps` on that sensor); the registered rule (`track_to_track.build_rule`'s
`definition.Rule`) fuses the locals' estimates of x_k at every output instant, with their
reported covariances. A rule that reads the locals' joint error covariance J (MSC-GMF, AVG)
gets it from the plans' affine maps: y_k = [x_k; s_k] (s the locals' states) follows

    y_k = A_k y_{k-1} + B_k w_k + [0; U_k] v_k,   A = [[F, 0], [U H F, T]],  B = [I; U H],

so cov(y_k) = A cov(y_{k-1}) A^T + B Q B^T + [0; U] R [0; U]^T (R with its cross-sensor
blocks: eq. 35's K_i R_ij K_j^T), and J = E cov(y) E^T for the errors e_j = x_k - O_j s_j;
computed on [x_k; s_k - D_k x_k] (D the locals' error forms, `retrodict._error_form`), whose
terms stay of the size of the errors where x's grow like q k^3.
Over several updates Al1 is an approximation, so J's diagonal blocks are the locals' true error
covariances, not the ones they report. The locals keep one copy of the last W readings.
J's recursion needs only cov([x_{k-1}; zeta_{k-1}]) and D_{k-1}: `FusedSteps` keeps them from
call to call, so a long log's steps are made block by block (`core.retrodict_blocks`).
"""

from __future__ import annotations

import numpy as np

from .architectures import Plan, StepMap, definition
from .architectures.hkf import independent_noise
from .linalg import mT, sym
from .model import System
from .moments import step_moments
from .retrodict import retrodict_maps, retrodict_plan

__all__ = ["FusedSteps", "late_retrodict_plan"]


def late_retrodict_plan(
    system: System,
    arch: str,
    base: str,
    present: np.ndarray,
    arrive: np.ndarray,
    filters: list[list[int]],
    lags: list[np.ndarray],
    criterion: str = "trace",
) -> Plan:
    """Architecture `arch` (registered as `base`) retrodicting its late readings: one filter on
    `filters[0]` (CKF, SKF), the hierarchical centre, or one local per sensor and the rule.
    `lags[j]`: the lags sensor j's readings arrive with; each filter keeps the window of its
    own sensors' largest lag."""
    locals_kind = definition(base).locals
    if locals_kind == "per-sensor":
        return _fused(system, arch, base, present, arrive, lags, criterion)
    W = max(int(lags[j].max()) for j in filters[0])
    if locals_kind == "hierarchical":
        return retrodict_plan(independent_noise(system), arch, present, arrive, filters[0], W)
    return retrodict_plan(system, arch, present, arrive, filters[0], W)


def _fused(
    system: System,
    arch: str,
    base: str,
    present: np.ndarray,
    arrive: np.ndarray,
    lags: list[np.ndarray],
    criterion: str,
) -> Plan:
    """The locals (one retrodicting filter per sensor, local j keeping the window W_j of its
    sensor's largest lag) and the rule as one plan (`FusedSteps` over the whole horizon)."""
    S = len(system.sensors)
    Ws = [int(lj.max()) for lj in lags]
    locs = [retrodict_maps(system, present, arrive, [j], Ws[j]) for j in range(S)]
    per_run = any(pr for _, pr in locs)
    maps = [mk for mk, _ in locs]
    if per_run:  # every local's maps per run
        M = max(mk[0][0].shape[0] for mk, pr in locs if pr)
        maps = [
            mk if pr else [tuple(np.broadcast_to(f, (M,) + f.shape) for f in st) for st in mk]
            for mk, pr in locs
        ]
    fuser = FusedSteps(system, base, Ws, criterion)
    steps, omegas = fuser.steps(maps)
    omega = None
    if any(w is not None for w in omegas):
        batch = steps[0].T.shape[:-2]
        omega = np.stack([np.broadcast_to(w, batch + (S,)) for w in omegas], axis=-2)
    plan = Plan(arch, fuser.s0, steps, per_run=per_run, D0=fuser.D0, complete=False)
    # plan.system stays None: the exact analysis keeps the true state's terms
    # (`moments.coupling`), so it is exact with any D; D (`retrodict._error_form`) only keeps
    # s - D x of the size of the errors
    plan.omega = omega
    return plan


class FusedSteps:
    """The locals' maps (`retrodict_maps` on each sensor, local j keeping the window W_j of its
    sensor's largest lag) and the rule as the steps of one plan, state [the locals' estimates
    and stored estimates; the last W = max W_j readings, shared]; resumable: J's recursion
    (`_error_moments`) and the error form of the step before are kept from call to call, so
    the log can be taken whole (`_fused`) or block by block (`core.retrodict_blocks`)."""

    def __init__(self, system: System, base: str, Ws: list[int], criterion: str) -> None:
        n, m = system.n, system.m
        S = len(system.sensors)
        self.system, self.Ws, self.criterion = system, Ws, criterion
        self.W = max(Ws)
        self.nbs = [n * (Wj + 2) for Wj in Ws]
        self.at = np.concatenate([[0], np.cumsum(self.nbs)])  # local j's rows: at[j]:at[j+1]
        self.dC = int(self.at[-1]) + self.W * m
        self.arch_def = definition(base)
        self.H = system.linear_measurement()
        prior = system.prior
        assert prior is not None
        self.cov = None  # cov([x_k; zeta_k]) when the rule reads J (`_error_moments`)
        D0 = np.zeros((self.dC, n))  # every local's current estimate is the prior's mean
        s0 = np.zeros(self.dC)
        for j in range(S):
            D0[self.at[j] : self.at[j] + n] = np.eye(n)
            s0[self.at[j] : self.at[j] + n] = prior.mean
        self.s0, self.D0, self.D_prev = s0, D0, D0
        self.next_instant = 0

    def steps(self, locs: list[list[tuple]], k0: int = 0) -> tuple[list[StepMap], list]:
        """The steps k0, k0+1, ... of the locals' maps `locs[j]` (local j's (T, U, O, P, D) of
        each step, all with the same batch shape), and the rule's weights (None where it has
        none)."""
        if k0 != self.next_instant:
            raise ValueError(f"the rule's steps in order: {k0} after {self.next_instant}")
        system, Ws, W, nbs, at, dC = self.system, self.Ws, self.W, self.nbs, self.at, self.dC
        n, m = system.n, system.m
        S = len(Ws)
        steps, omegas = [], []
        for k, maps in enumerate(zip(*locs, strict=True), start=k0):
            batch = maps[0][0].shape[:-2]
            T = np.zeros(batch + (dC, dC))
            U = np.zeros(batch + (dC, m))
            Ol = np.zeros(batch + (S * n, dC))
            D = np.zeros(batch + (dC, n))  # the error form: the locals' and the shared buffer's
            for j, (Tj, Uj, Oj, _, Dj) in enumerate(maps):
                nb, rows, buf = nbs[j], slice(at[j], at[j + 1]), at[-1]
                T[..., rows, rows] = Tj[..., :nb, :nb]
                T[..., rows, buf : buf + Ws[j] * m] = Tj[..., :nb, nb:]  # its newest W_j readings
                U[..., rows, :] = Uj[..., :nb, :]
                Ol[..., j * n : (j + 1) * n, rows] = Oj[..., :, :nb]
                D[..., rows, :] = Dj[..., :nb, :]
            wide = Ws.index(W)  # a local that keeps all W readings: their shift
            nw, buf = nbs[wide], at[-1]
            T[..., buf:, buf:] = maps[wide][0][..., nw:, nw:]
            U[..., buf:, :] = maps[wide][1][..., nw:, :]
            D[..., buf:, :] = maps[wide][4][..., nw:, :]
            Ploc = np.stack([mp[3] for mp in maps], axis=-3)  # batch + (S, n, n)
            st = StepMap(T, U, Ol, Ploc, D)  # the moments read T, U and D
            J = None
            if self.arch_def.joint:
                P0 = system.prior.cov
                self.cov = _error_moments(system, k, st, self.D_prev, self.cov, P0, self.H)
                E = np.zeros(batch + (S * n, n + dC))  # e_j = (I - O_j D_j) x_k - O_j zeta_j
                E[..., :n] = np.tile(np.eye(n), (S, 1)) - Ol @ D
                E[..., n:] = -Ol
                J = sym(E @ self.cov @ mT(E))
            self.D_prev = D
            C, Pf, w = _rule(self.arch_def, Ploc, J, self.criterion)
            omegas.append(w)
            steps.append(StepMap(T, U, C @ Ol, Pf, D))
        self.next_instant = k0 + len(steps)
        return steps, omegas


def _rule(arch_def, P: np.ndarray, J: np.ndarray | None, criterion: str):
    """(C, P_fused, omega or None) of the registered rule on the locals, with a batch axis
    always (the rules' kernels work on batches of problems)."""
    one = P.ndim == 3
    if one:
        P, J = P[None], None if J is None else J[None]
    found: dict[str, np.ndarray] = {}
    if arch_def.information:
        C, Pf = arch_def.rule(P, J, criterion, found=found)
    else:
        C, Pf = arch_def.rule(P, J, criterion)
    w = found.get("omega")
    C = np.broadcast_to(C, Pf.shape[:-2] + C.shape[-2:])
    if one:
        C, Pf, w = C[0], Pf[0], None if w is None else w[0]
    return C, Pf, w


def _error_moments(system, k, st: StepMap, D_prev, cov, P0, H):
    """cov([x_k; zeta_k]), zeta_k = s_k - D_k x_k, from cov([x_{k-1}; zeta_{k-1}]) (the
    module docstring's recursion in the error form of `moments.step_moments`, with the model
    as the truth); at k = 0 from [x_0; s_0 - D_0 x_0] (s_0 known). With D = 0 the recursion
    above subtracts numbers of the size of x's covariance (q k^3 for constant velocity)."""
    n = system.n
    if cov is None:
        Jx = np.concatenate([np.eye(n), -D_prev])
        cov = Jx @ P0 @ Jx.T
    mu = np.zeros(st.T.shape[:-2] + (cov.shape[-1],))
    return step_moments(st, k, mu, cov, D_prev, system, n, H)[1]
