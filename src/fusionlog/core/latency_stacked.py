"""The stacked model of late measurements and its plans (see `core.latency`).

`stacked_system` is the model on the state stacked over the latency window, whose sensors
measure the blocks their readings arrive late from; `wrap` turns a plan of it into a plan on
the measurements as taken (keeping the last W readings in the plan's state);
`fused_plan` builds a track-to-track architecture on it whose fusion rule takes the locals'
current blocks only (their estimates of x_k, the marginals of the stacked ones).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .architectures import BlockDiagonal, BuildRequest, Plan, StepMap, definition
from .architectures.definition import Architecture
from .architectures.registry import group_by_history
from .architectures.track_to_track import build_rule
from .linalg import numerical_errors
from .model import Prior, System
from .models import LinearSensor

__all__ = ["current_block_rule", "fused_plan", "stacked_noise", "stacked_system", "wrap"]


def stacked_system(system: System, lags: list[np.ndarray]) -> System:
    """The model on the state stacked over the last W instants, X_k = [x_k; ...; x_{k-W}]
    (W the largest lag), whose sensor j measures H_j x_{k-l} for each of its lags l (its
    readings arriving l instants late): one block of rows per lag, the noises of one instant
    correlated as before, of different instants independent.

    The blocks of the instants before 0 are never measured: the prior makes them independent
    copies of x_0's distribution, which keeps the stacked covariance invertible (HKF fuses in
    information form) and changes no estimate of a real instant."""
    n, W = system.n, max(int(l.max()) for l in lags)
    N = (W + 1) * n

    def stacked_F(F: np.ndarray) -> np.ndarray:
        out = np.zeros((N, N))
        out[:n, :n] = F
        out[n:, :-n] = np.eye(W * n)
        return out

    def stacked_Q(Q: np.ndarray) -> np.ndarray:
        out = np.zeros((N, N))
        out[:n, :n] = Q
        return out

    sensors = []
    for sen, lj in zip(system.sensors, lags, strict=True):
        H = np.zeros((len(lj) * sen.dim, N))
        for q, lag in enumerate(lj):
            H[q * sen.dim : (q + 1) * sen.dim, lag * n : (lag + 1) * n] = sen.H
        sensors.append(LinearSensor(sen.name, H, np.kron(np.eye(len(lj)), sen.R)))
    cross = {}
    for (i, j), Rij in system.cross_R.items():
        C = np.zeros((len(lags[i]) * Rij.shape[0], len(lags[j]) * Rij.shape[1]))
        for qi, li in enumerate(lags[i]):
            for qj, lj_ in enumerate(lags[j]):
                if li == lj_:  # readings of one instant
                    a, b = Rij.shape
                    C[qi * a : (qi + 1) * a, qj * b : (qj + 1) * b] = Rij
        cross[(i, j)] = C

    def stacked_prior(p: Prior | None) -> Prior | None:
        if p is None:
            return None
        return Prior(np.tile(p.mean, W + 1), np.kron(np.eye(W + 1), p.cov))

    names = tuple(f"{s}[k-{b}]" if b else s for b in range(W + 1) for s in system.state_names)
    return dataclasses.replace(
        system,
        F=stacked_F(system.F),
        Q=stacked_Q(system.GQG),
        G=None,
        sensors=tuple(sensors),
        cross_R=cross,
        prior=stacked_prior(system.prior),
        initial=stacked_prior(system.initial),
        state_names=names,
        continuous=None,
        Fs=None if system.Fs is None else np.stack([stacked_F(F) for F in system.Fs]),
        Qs=None if system.Qs is None else np.stack([stacked_Q(Q) for Q in system.Qs]),
        Rs=None,
        late="reprocess",
    )


def stacked_noise(
    Rs: np.ndarray, R: np.ndarray, slots: np.ndarray, coef: np.ndarray | None, before: int
) -> np.ndarray:
    """The stacked model's noise covariance (w, m~, m~) at w instants where each reading
    carries its own R (a recorded log's per-message covariances, `System.Rs`, eq. 31): slot c
    (sensor, lag l, component o) read at k is the reading of instant k - l (`coef[c]`: its
    combination of that instant's readings, `latency_corr`; default component o), so

        R~_k[c, c'] = coef_c R_{k-l} coef_c'^T  where l_c = l_c',   0 otherwise

    (readings of different instants are independent: `stacked_system`'s R, instant by
    instant). `Rs` (before + w, m, m): the raw R of the instants k0 - before..k1-1; an
    instant before its first row (before the log: never measured, masked) takes `R`."""
    w, mt = len(Rs) - before, len(slots)
    out = np.zeros((w, mt, mt))
    for lag in np.unique(slots[:, 1]).tolist():
        cols = np.flatnonzero(slots[:, 1] == lag)
        src = np.arange(w) + before - lag  # the rows of the readings' own instants
        Rl = Rs[np.maximum(src, 0)]
        Rl[src < 0] = R
        if coef is None:
            o = slots[cols, 2]
            out[:, cols[:, None], cols] = Rl[:, o[:, None], o]
        else:
            C = coef[cols]
            out[:, cols[:, None], cols] = C @ Rl @ C.T
    return out


def _dense(A):
    return A.dense() if isinstance(A, BlockDiagonal) else A


def back_propagation(system: System | None, W: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The noise-free past of x_k: S ((W+1) n, n) with X_k = [x_k; ...; x_{k-W}] = S x_k
    (x_{k-l} = F^-l x_k), and Hb (W+1 blocks of m rows) with z_{k-l} = H F^-l x_k; None
    when the model has no single invertible F (per-step F, a singular or ill-conditioned F,
    a nonlinear sensor): the wrapped plan then keeps D = 0."""
    if system is None or system.Fs is not None or not all(s.linear for s in system.sensors):
        return None
    F = system.F
    if not np.isfinite(F).all() or np.linalg.cond(F) > 1e8:  # F^-W would amplify rounding
        return None
    Finv = np.linalg.inv(F)
    powers = [np.eye(system.n)]
    for _ in range(W):
        powers.append(Finv @ powers[-1])
    H = system.linear_measurement()
    return np.vstack(powers), np.vstack([H @ Fl for Fl in powers])


def wrap(
    inner: Plan,
    slots: np.ndarray,
    m: int,
    W: int,
    n: int,
    coef: np.ndarray | None = None,
    system: System | None = None,
) -> Plan:
    """The plan `inner` of the stacked model as a plan on z as taken (see the module's
    docstring): s_k = [s~_k; b_k], b_k = [z_k; ...; z_{k-W+1}], the reading of slot (j, l, o)
    taken from z_k (l = 0) or from block l - 1 of b_{k-1}; x_hat = the first block of
    the stacked estimate, P its covariance. `coef` (m~, m): each slot's reading as a
    combination of the readings of its instant (`latency_corr`; default component o).

    `system` (the model on x, not the stacked one) gives the error form D of the wrapped
    state (`StepMap.D`): without noise X_k = S x_k and z_{k-l} = H F^-l x_k
    (`back_propagation`), so D_k = [D~_k S; H; H F^-1; ...; H F^-(W-1)] (D~ the inner's, on
    X_k) and D_0 = [D~_0 S; H F^-1; ...; H F^-W] (s0 stands before step 0, whose F the
    analysis takes as I). s - D x is then of the size of the errors, where with D = 0 the
    exact analysis (`core.exact`) subtracts numbers of the size of the truth's covariance,
    which grows without bound (q k^3 for constant velocity). The analysis is exact with any
    D (the wrapped plan keeps x in its moments, `moments.coupling`): D only conditions it."""
    B = W * m
    back = back_propagation(system, W)
    N = None if back is None else back[0].shape[0]

    def error_form(Dt: np.ndarray, buffer: np.ndarray, batch: tuple) -> np.ndarray:
        """[D~ S; buffer], batch + (d + B, n)."""
        top = Dt @ back[0]
        out = np.zeros(np.broadcast_shapes(batch, top.shape[:-2]) + (top.shape[-2] + B, n))
        out[..., : top.shape[-2], :] = top
        out[..., top.shape[-2] :, :] = buffer
        return out

    def usable(Dt: np.ndarray | None) -> bool:
        """Whether the inner map has an error form on X_k (and F is usable)."""
        return back is not None and Dt is not None and Dt.shape[-1] == N

    # Sel (m~, m + W m): slot c's columns among [z_k, b_{k-1}] (block l of l m columns)
    Sel = np.zeros((len(slots), m + B))
    if coef is None:
        col = np.where(slots[:, 1] == 0, slots[:, 2], m + (slots[:, 1] - 1) * m + slots[:, 2])
        Sel[np.arange(len(slots)), col] = 1.0
    else:
        cols = slots[:, 1, None] * m + np.arange(m)
        Sel[np.arange(len(slots))[:, None], cols] = coef
    shift = np.eye(B - m) if B > m else np.zeros((0, 0))
    done: dict[int, StepMap] = {}

    def step(st: StepMap) -> StepMap:
        if id(st) in done:
            return done[id(st)]
        T, U = _dense(st.T), st.U
        G = U @ Sel  # (..., d, m + B)
        batch = np.broadcast_shapes(T.shape[:-2], G.shape[:-2])
        d, dp = T.shape[-2:]
        Tw = np.zeros(batch + (d + B, dp + B))
        Tw[..., :d, :dp] = T
        Tw[..., :d, dp:] = G[..., m:]
        Tw[..., d + m :, dp : dp + B - m] = shift
        Uw = np.zeros(batch + (d + B, m))
        Uw[..., :d, :] = G[..., :m]
        Uw[..., d : d + m, :] = np.eye(m)
        O = st.O[..., :n, :]
        Ow = np.concatenate([O, np.zeros(O.shape[:-1] + (B,))], axis=-1)
        P = np.ascontiguousarray(st.P[..., :n, :n])
        if usable(st.D):
            D = error_form(st.D, back[1][: W * m], batch)
        else:
            D = np.zeros(batch + (d + B, n))
        out = done[id(st)] = StepMap(Tw, Uw, Ow, P, D)
        return out

    steps = [step(st) for st in inner.steps]
    d0 = len(inner.s0)
    D0 = error_form(inner.D0, back[1][m:], ()) if usable(inner.D0) else np.zeros((d0 + B, n))
    return dataclasses.replace(
        inner,
        s0=np.concatenate([inner.s0, np.zeros(B)]),
        steps=steps,
        D0=D0,
        complete=False,
        dense=None,
        omega=None,
    )


def first_blocks(rule, n: int, N: int):
    """The fusion rule `rule` (`definition.Rule`) of the locals' current blocks: P (..., S, N,
    N) and J (..., S N, S N) of the stacked locals cut to their first n rows and columns,
    the weights C put back on the stacked locals' first blocks (C~ (..., N, S N), zero
    elsewhere) and P~ = blockdiag(P_fused, I) (only its first block is read: `wrap`)."""

    def fused(P: np.ndarray, J: np.ndarray | None, criterion: str):
        S = P.shape[-3]
        idx = (np.arange(S)[:, None] * N + np.arange(n)).ravel()
        Jn = None if J is None else J[..., idx[:, None], idx]
        C, Pf = rule(np.ascontiguousarray(P[..., :n, :n]), Jn, criterion)
        batch = Pf.shape[:-2]
        Cw = np.zeros(batch + (N, S * N))
        Cw[..., :n, idx] = C
        Pw = np.zeros(batch + (N, N))
        Pw[..., :, :] = np.eye(N)
        Pw[..., :n, :n] = Pf
        return Cw, Pw

    return fused


def current_block_rule(arch: str, n: int, N: int) -> Architecture:
    """The per-sensor architecture `arch` on locals of the stacked model (N states): its
    registered rule applied to their current blocks (`first_blocks`, x_k's n states), taken
    by the plans (`fused_plan`) and the plan-free blocks of time (`latency_blocks`) alike."""
    base = definition(arch)
    # `first_blocks` hands the rule mean-form covariances only: late sensors need a prior, so
    # the locals never start in information form here (information=False).
    return dataclasses.replace(
        base, rule=first_blocks(base.rule, n, N), build=None, color=None, information=False
    )


def fused_plan(
    system: System,
    arch: str,
    present: np.ndarray,
    criterion: str,
    n: int,
    history_nodes: bool = False,
) -> Plan:
    """The track-to-track architecture `arch` on the stacked `system`: its local filters (one
    per sensor) and its registered rule applied to their current blocks (`first_blocks`),
    by the generic rule builder (`track_to_track.build_rule`)."""
    stacked = current_block_rule(arch, n, system.n)
    request = BuildRequest(system, arch, present, None, criterion)
    if present.ndim == 3:
        request.nodes = group_by_history(present)

    def where() -> str:
        step = "" if request.step is None else f", step {request.step}"
        return f"architecture {arch}{step}"

    with numerical_errors(where):
        plan = build_rule(request, stacked)
    plan.system = system
    plan.complete = bool(present.all())
    return plan if history_nodes else plan.per_run_maps()
