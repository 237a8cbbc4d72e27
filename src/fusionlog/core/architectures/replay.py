"""A single replayed log through the architectures without plans: the same estimates as
`build_plan` + `run_plan`, computed for one run (issue 22, "a single replayed log at least as
fast as FilterPy's KF loop").

A plan is what many runs and the exact analysis need: per step the affine maps T, U, O of
every architecture on its own. One run of a recorded log (every interval distinct, a
covariance per message: no steady state to repeat) needs none of it, and building the maps
step by step costs ~30 numpy calls per filter and step. Here:

1. the sequential recursions run once for all architectures, with a fixed number of numpy
   calls per instant (`replay_filters.run_bank`): the centralised KF (CKF, and FBS's forward
   filter), one local KF per sensor (shared by SKF and every per-sensor architecture, which
   run the same filters), HKF's fused filter with its local updates; then the joint error
   covariance of eq. (35) (for a rule that reads it) and FBS's backward information filter;
2. everything that does not feed back into a recursion is computed for all instants at once,
   with the instants as the batch of the batched kernels: the mean recursions' maps, each
   per-sensor architecture's fusion rule as its definition writes it (`definition.Rule`,
   `rules`), the smoother's fusion, eqs. (26)-(28);
3. the means follow x_k = A_k x_{k-1} + b_k, all filters as one stack (two numpy calls per
   instant).

Same formulas as the plans (Joseph form, eqs. 14-18; HKF eqs. 36-40; FBS eqs. 25-28), so the
estimates agree with the plan path to rounding (tests/test_replay_fast.py). It applies to one
run of a linear model with a prior whose plans would not reach a steady state (a log with
irregular instants, per-message R or missing components); anything else, or a number that
leaves the float range, goes to the plans, which also name the step of a numerical failure.
Memory: what is kept per instant (~13 kB with every architecture on replay_robot's 4 states
and 3 sensors) peaks below the plans' (~16 kB), and none of it stays after the estimates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ...errors import NumericalError
from ..linalg import NUMERICAL_FAILURES, all_finite, solve
from ..model import System
from .definition import Architecture
from .filters import wide_range
from .plan import Estimate
from .registry import definition, parse_arch
from .replay_filters import (
    Slots,
    affine_recursion,
    backward_information,
    backward_means,
    information,
    joint_recursion,
    masked_rows,
    run_bank,
)

#: Each slot's masked H and R at every instant are kept at most this large (bytes): many
#: sensors (their slots and rows both grow) on a long log go to the plans, which mask one
#: instant at a time.
MASKED_BYTES_AT_MOST = 1 << 28

#: The filters each kind of architecture (`definition.LOCALS`) reads here.
_CENTRAL = {"centralised", "smoother"}
_LOCALS = {"per-sensor", "single"}


def applies(system: System, z: np.ndarray) -> bool:
    """Whether `replay_estimates` takes the block z (runs, K+1, m): one run of a linear model
    with a prior, not a steady Riccati recursion (which the plans repeat in one map)."""
    if z.shape[0] != 1 or z.shape[1] < 2:
        return False
    if system.prior is None or system.motion_model is not None or not system.linear:
        return False
    return not (system.time_invariant and not np.isnan(z).any())


def replay_estimates(
    system: System, archs: Sequence[str], z: np.ndarray, criterion: str | None = None
) -> dict[str, Estimate] | None:
    """Each architecture's estimate of the one run z (1, K+1, m) (NaN: missing), as the plans
    give it; None where the plans must do it: what `applies` refuses, HKF on noise levels
    spanning more than 1e8 (the plans' scaled inverses, `filters.wide_range`), many sensors
    on a long log (`MASKED_BYTES_AT_MOST`), numbers beyond the float range."""
    if not applies(system, z):
        return None
    bases = _bases(system, archs)
    if bases is None or any(_hkf_wide(system, b) for b, _ in bases):
        return None
    criterion = criterion or system.ci_criterion
    out = _computed(system, z[0], bases, criterion, lambda r: r.estimates(archs, bases))
    if out is None or not all(all_finite(e.mean) and all_finite(e.cov) for e in out.values()):
        return None
    return out


def _bases(system: System, archs: Sequence[str]) -> list[tuple[Architecture, str | None]] | None:
    """Each architecture's (definition, sensor) (`parse_arch`); None for a name no definition
    has (the plans refuse it)."""
    names = [s.name for s in system.sensors]
    try:
        return [(definition(a), parse_arch(a, names)[1]) for a in archs]
    except ValueError:
        return None


def _hkf_wide(system: System, arch: Architecture) -> bool:
    """HKF on noise levels spanning more than 1e8: the plans' scaled inverses do it."""
    return arch.locals == "hierarchical" and wide_range(system)


def _computed(system: System, z: np.ndarray, bases, criterion: str, what):
    """what(_Replay(...)) for the run z (K+1, m) and the architectures `bases`; None where
    their slots' masked H and R would pass `MASKED_BYTES_AT_MOST` or a number fails."""
    need = {b.locals for b, _ in bases}
    S, m, n = len(system.sensors), system.m, system.n
    slots = bool(need & _CENTRAL) + S * bool(need & _LOCALS) + (S + 1) * ("hierarchical" in need)
    if z.shape[0] * slots * m * (m + n) * 8 > MASKED_BYTES_AT_MOST:
        return None
    try:
        with np.errstate(all="ignore"):
            return what(_Replay(system, z, need, criterion))
    except (NumericalError, *NUMERICAL_FAILURES):
        return None


def replay_error_covariances(
    system: System, archs: Sequence[str], present: np.ndarray, criterion: str | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """Each architecture's true error covariance E[e_k e_k^T] and reported covariance P_k
    (K+1, n, n) on one run with the measurement mask `present` (K+1, m), when the truth is
    `system` itself (the caller checks it; the error means are then zero); None where the
    plans must do it (as `replay_estimates`; HKF on noise levels spanning more than 1e8 is
    left out).

    Under the model the Joseph form's P of eq. (18) is the error covariance of any gain, so
    a Kalman filter's (CKF, SKF) is its P. The smoother's, eqs. (25)-(28): e_s = (I - K_s)
    e_f - P_s eta with eta = y_b - S x independent of e_f, cov S, so E = P_s Pf^-1 P_s +
    P_s S P_s = P_s. A fusion x = sum_j O_j x_j with sum_j O_j = I has the error O e_loc, so
    E = O J O^T with J the local filters' joint error covariance, eq. (35). HKF's fused P is
    not its error covariance: it has its own recursion (`_hkf_error`).
    """
    z = np.where(present, 0.0, np.nan)[None]  # the covariances need only the pattern
    if not applies(system, z):
        return None
    bases = _bases(system, archs)
    if bases is None:
        return None
    keep = [not _hkf_wide(system, b[0]) for b in bases]
    archs = [a for a, k in zip(archs, keep, strict=True) if k]
    bases = [b for b, k in zip(bases, keep, strict=True) if k]
    criterion = criterion or system.ci_criterion
    out = _computed(system, z[0], bases, criterion, lambda r: r.error_covariances(archs, bases))
    if out is None or not all(all_finite(E) and all_finite(P) for E, P in out.values()):
        return None
    return out


@dataclass
class Carried:
    """What the recursions of `_Replay` carry from the last instant of a block of time to the
    next block (`replay_blocks`): the slots' covariances (C, n, n), every filter's mean (f, n),
    eq. (35)'s joint J and HKF's error covariance where they were computed (else None)."""

    P: np.ndarray
    x: np.ndarray | None
    J: np.ndarray | None = None
    E: np.ndarray | None = None


class _Replay:
    """The recursions of the architectures `need` on one run's measurements z (K+1, m); from
    the prior, or (`start`) from the state carried from the block of time before, the system's
    Fs, Qs then into every instant of z (the first's too). `backward`: FBS's backward vectors
    and S at these instants where they come from elsewhere (a block of time)."""

    def __init__(
        self,
        system: System,
        z: np.ndarray,
        need: set[str],
        criterion: str,
        start: Carried | None = None,
        backward: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        n, m = system.n, system.m
        K1 = len(z)
        S = len(system.sensors)
        self.system, self.criterion, self.n, self.S, self.K1 = system, criterion, n, S, K1
        self.start, self.backward = start, backward
        self.present = present = ~np.isnan(z)
        self.z = np.where(present, z, 0.0)
        self.H = system.linear_measurement()
        self.R = system.Rs if system.Rs is not None else np.broadcast_to(system.R, (K1, m, m))
        K = K1 - 1 if start is None else K1
        self.p0 = K1 - K  # the first instant with a prediction
        self.Fs, self.Qs = system.transitions(0, K)
        rows = np.zeros((S, m), dtype=bool)
        for j, sl in enumerate(system.sensor_slices):
            rows[j, sl] = True
        use, src, carried = [], [], 0
        self.ckf = self.loc = self.hkf = None
        if need & _CENTRAL:
            self.ckf = len(use)
            use.append(np.ones(m, dtype=bool))
            src.append(carried)
            carried += 1
        if need & _LOCALS:
            self.loc = len(use)
            use.extend(rows)
            src.extend(range(carried, carried + S))
            carried += S
        if "hierarchical" in need:
            self.hkf = len(use)
            use.extend([np.zeros(m, dtype=bool), *rows])  # the fused prediction, then locals
            src.extend([carried] * (S + 1))
            carried += 1
        slots = Slots(np.array(use), np.array(src), carried, self.hkf)
        self.bank_carried = carried
        Hm, Rm = masked_rows(self.H, self.R, present[:, None, :] & slots.use[None])
        self.Hm, self.Rm = Hm, Rm
        P0 = system.prior.cov if start is None else start.P
        self.bank = run_bank(slots, P0, self.Fs, self.Qs, Hm, Rm, start is not None)
        self.x_last: np.ndarray | None = None  # the means' last instant, once computed
        self._J: np.ndarray | None = None  # eq. (35), when an architecture needs it
        self._E: np.ndarray | None = None  # HKF's error covariance, when asked for

    def carried(self) -> Carried:
        """The state of the last instant, which the next block of time starts from."""
        J = None if self._J is None else self._J[-1].copy()
        E = None if self._E is None else self._E[-1].copy()
        return Carried(self.bank.P[-1][: self.bank_carried].copy(), self.x_last, J, E)

    # -- the mean recursions ------------------------------------------------------------------

    @cached_property
    def means(self) -> dict[str, np.ndarray]:
        """Every filter's means (K+1, n): x_k = (I - K H) F x_{k-1} + K z_k for the KFs
        (eq. 14), x_k = P (Tacc F x_{k-1} + U z_k) for HKF (eqs. 38-40), all as one stack.
        Computed where asked for: the error covariances need none (`carried` then carries
        no means, and the blocks after compute none either)."""
        b, n, S = self.bank, self.n, self.S
        F = self.Fs  # into every instant; the log's instant 0 has none:
        if self.p0:
            F = np.concatenate([np.eye(self.n)[None], self.Fs])
        parts: list[tuple[str, int, np.ndarray, np.ndarray]] = []  # name, filters, A, b
        for name, first, count in (("ckf", self.ckf, 1), ("loc", self.loc, S)):
            if first is not None:
                kf = slice(first, first + count)
                Ab = np.einsum("kfij,kj->kfi", b.K[:, kf], self.z)
                parts.append((name, count, b.IKH[:, kf] @ F[:, None], Ab))
        if self.hkf is not None:
            M, B = self._hkf_maps()
            parts.append(("hkf", 1, (M @ F)[:, None], np.einsum("kij,kj->ki", B, self.z)[:, None]))
        if not parts:
            self.x_last = np.zeros((0, n))
            return {}
        x0 = np.broadcast_to(self.system.prior.mean, (sum(p[1] for p in parts), n))
        if self.start is not None:
            if self.start.x is None:
                raise ValueError("the block of time before carried no means")
            x0 = self.start.x
        A = np.concatenate([p[2] for p in parts], axis=1)
        X = affine_recursion(A, np.concatenate([p[3] for p in parts], axis=1), x0)
        self.x_last = X[-1].copy()
        out, at = {}, 0
        for name, count, _, _ in parts:
            out[name] = X[:, at] if name != "loc" else X[:, at : at + count]
            at += count
        return out

    def _hkf_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """HKF's x_k = M_k F x_{k-1} + B_k z_k (eqs. 38-40): M = P Tacc, B = P U (K+1, ...)."""
        b, S, h = self.bank, self.S, self.hkf + 1
        Y = b.Y_hkf  # (K+1, S+1, n, n): Y_pred, Y_1..Y_S
        # (1 - S) Y_pred + sum_j Y_j (I - K_j H_j), summed in that order as the plans do
        Tacc = np.concatenate([(1.0 - S) * Y[:, :1], Y[:, 1:] @ b.IKH[:, h:]], axis=1)
        U = (Y[:, 1:] @ b.K[:, h:]).sum(axis=1)
        return b.P_hkf @ Tacc.sum(axis=1), b.P_hkf @ U

    def _hkf_error(self) -> np.ndarray:
        """HKF's error covariance under the model: M + B H = I (K_j H = K_j H_j, so Tacc + U H
        is the fused information P^-1), so e_k = M_k (F_k e_{k-1} + w_k) - B_k v_k and E_k =
        sym(M F E_{k-1} F' M' + M Q M' + B R B') from the prior's covariance (no F, no w at
        k = 0), as `joint_recursion` takes it."""
        M, B = self._hkf_maps()
        A, p = M.copy(), self.p0
        A[p:] = M[p:] @ self.Fs
        C = B @ self._masked_R() @ B.swapaxes(-1, -2)
        C[p:] += M[p:] @ self.Qs @ M[p:].swapaxes(-1, -2)
        E0 = self.system.prior.cov if self.start is None else self.start.E
        self._E = joint_recursion(A, C, E0)
        return self._E

    # -- the architectures --------------------------------------------------------------------

    def estimates(self, archs: Sequence[str], bases) -> dict[str, Estimate]:
        """Each architecture's estimate (`bases`: its (definition, sensor) from `_bases`)."""
        out = {}
        for a, (arch, sensor) in zip(archs, bases, strict=True):
            mean, cov = self._KINDS[arch.locals](self, arch, sensor)
            out[a] = Estimate(mean[None], cov)
        return out

    def error_covariances(self, archs: Sequence[str], bases) -> dict[str, tuple]:
        """Each architecture's (E[e e^T], P) under the model (`replay_error_covariances`)."""
        out = {}
        for a, (arch, sensor) in zip(archs, bases, strict=True):
            if arch.locals == "hierarchical":
                out[a] = (self._hkf_error(), self.bank.P_hkf)
                continue
            if not arch.fuses_locals:  # a filter's or the smoother's own P
                P = self._own_cov(arch.locals, sensor)
                out[a] = (P, P)
                continue
            O, P = self._weights(arch)
            J = self._joint()
            out[a] = (_sym(O @ J @ O.swapaxes(-1, -2)), P)
        return out

    def _own_cov(self, kind: str, sensor: str | None) -> np.ndarray:
        """The covariance (K+1, n, n) of a filter (CKF, SKF) or of the smoother, no means."""
        if kind == "centralised":
            return self.bank.P[:, self.ckf]
        if kind == "single":
            return self.bank.P[:, self.loc + self.system.sensor_index(sensor)]
        return self._smoothing[1]

    def _ckf(self, arch, sensor):
        return self.means["ckf"], self._own_cov("centralised", sensor)

    def _skf(self, arch, sensor):
        j = self.system.sensor_index(sensor)
        return self.means["loc"][:, j], self._own_cov("single", sensor)

    def _hkf(self, arch, sensor):
        return self.means["hkf"], self.bank.P_hkf

    def _weights(self, arch: Architecture) -> tuple[np.ndarray, np.ndarray]:
        """The rule's weights C (K+1, n, S n) and covariance at every instant at once."""
        P = self.bank.P[:, self.loc : self.loc + self.S]
        return arch.rule(P, self._joint() if arch.joint else None, self.criterion)

    def _fused(self, arch, sensor):
        """x = C [x_1; ...; x_S] at every instant, C of the architecture's rule."""
        C, P = self._weights(arch)
        X = self.means["loc"].reshape(self.K1, -1)
        return np.einsum("kij,kj->ki", C, X), P

    def _joint(self) -> np.ndarray:
        """J of eq. (35) at every instant (computed once): J_k = Psi_k (Phi_k J_{k-1} Phi_k' +
        Gam Q_k Gam') Psi_k' + Lam_k R_k Lam_k', Psi = blockdiag(I - K_j H_j), Lam the stacked
        K_j, Phi = blockdiag(F), Gam = [I; ...; I]."""
        if self._J is not None:
            return self._J
        n, S, K1 = self.n, self.S, self.K1
        b, lo = self.bank, self.loc
        IKH = b.IKH[:, lo : lo + S]  # (K+1, S, n, n)
        Lam = b.K[:, lo : lo + S].reshape(K1, S * n, -1)
        C = Lam @ self._masked_R() @ Lam.swapaxes(-1, -2)
        # Psi Gam Q Gam' Psi' = [Psi_i Q Psi_j'] and Psi Phi = blockdiag(Psi_j F), block by block
        p = self.p0
        C[p:] += (IKH[p:] @ self.Qs[:, None]).reshape(K1 - p, S * n, n) @ _rows(IKH[p:]).swapaxes(
            -1, -2
        )
        A = np.zeros((K1, S * n, S * n))
        PsiF = IKH.copy()
        PsiF[p:] = IKH[p:] @ self.Fs[:, None]
        for j in range(S):
            A[:, j * n : (j + 1) * n, j * n : (j + 1) * n] = PsiF[:, j]
        J0 = np.tile(self.system.prior.cov, (S, S)) if self.start is None else self.start.J
        self._J = joint_recursion(A, C, J0)
        return self._J

    def _masked_R(self) -> np.ndarray:
        """The R the plans' error covariances use: every component's, cross-covariances
        included, an absent one's decoupled with unit variance (its gain column is zero)."""
        pf = self.present.astype(float)
        return self.R * (pf[:, :, None] * pf[:, None, :]) + np.eye(pf.shape[1]) * (1 - pf)[:, None]

    @cached_property
    def _backward(self) -> tuple[np.ndarray, np.ndarray]:
        """FBS's backward information filter, eqs. (25)-(28): y_b and S (K+1, ...), run here
        over the whole log or (a block of time) handed over by the backward pass that came
        first from the log's end."""
        if self.backward is not None:
            return self.backward
        c = self.ckf
        W, cz = information(self.Hm[:, c], self.Rm[:, c], self.z)
        L, Smat = backward_information(W, self.Fs, self.Qs)
        return backward_means(L, cz), Smat

    @cached_property
    def _smoothing(self) -> tuple[np.ndarray, np.ndarray]:
        """The fusion of the CKF forward and the backward filter, eqs. (26)-(28): K_s = P S
        (I + P S)^-1 and P_s = (I - K_s) P (K+1, n, n)."""
        Pf = self.bank.P[:, self.ckf]
        eye = np.eye(self.n)
        PS = Pf @ self._backward[1]
        Ks = solve((eye + PS).swapaxes(-1, -2), PS.swapaxes(-1, -2)).swapaxes(-1, -2)
        return Ks, _sym((eye - Ks) @ Pf)

    def _fbs(self, arch, sensor):
        """FBS, eqs. (25)-(28): the CKF forward, the backward information filter, and their
        fusion x_s = (I - K_s) x + P_s y_b (`_smoothing`)."""
        Ks, Ps = self._smoothing
        x, yb = self.means["ckf"], self._backward[0]
        mean = np.einsum("kij,kj->ki", np.eye(self.n) - Ks, x) + np.einsum("kij,kj->ki", Ps, yb)
        return mean, Ps

    #: Each kind of architecture (`definition.LOCALS`) from the recursions above.
    _KINDS = {
        "centralised": _ckf,
        "single": _skf,
        "hierarchical": _hkf,
        "smoother": _fbs,
        "per-sensor": _fused,
    }


def _sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + A.swapaxes(-1, -2))


def _rows(X: np.ndarray) -> np.ndarray:
    """A stack's matrices one above the other, (K, S, a, b) -> (K, S a, b)."""
    K, S, a, b = X.shape
    return X.reshape(K, S * a, b)
