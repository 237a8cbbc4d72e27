"""The posterior Cramér-Rao bound (Tichavský, Muravchik, Nehorai, "Posterior Cramér-Rao bounds for
discrete-time nonlinear filtering", IEEE Trans. Signal Processing 46(5), 1998), per instant.

For x_k = f(x_{k-1}) + w, w ~ N(0, Q), and z_k = h(x_k) + v, v ~ N(0, R), the information
J_k (E[(x_hat - x)(x_hat - x)^T] >= J_k^-1 for any estimator) follows

    J_0 = P_0^-1 + D_z(0),
    J_k = D22 - D21 (J_{k-1} + D11)^-1 D12 + D_z(k),
    D11 = E[F~^T Q^-1 F~],  D12 = D21^T = -E[F~^T] Q^-1,  D22 = Q^-1,   F~ = df/dx at x_{k-1},
    D_z(k) = E[sum_j H~_j^T R_j^-1 H~_j]  over the sensors that measure at k, H~_j = dh_j/dx at x_k,

which for linear motion (F~ = F) is J_k = (Q + F J_{k-1}^-1 F^T)^-1 + D_z(k), the form used then
(it needs no Q^-1). The expectations are averages over the simulated runs: their true states, and
which measurements each made (a lost or unscheduled one adds no information to that run). With
linear sensors and a shared pattern, J_k^-1 is the CKF's covariance exactly.

P_0 is the covariance the true x_0 is drawn from (the prior's unless [truth] says otherwise).
Where it is singular (a known initial state, or known components: [truth] initial_cov zero in
them) J_0 is infinite there and the recursion starts in covariance form: J_0^-1 = (P_0^-1 +
D_z(0))^-1 is the Kalman update of P_0 by a measurement with H = U, R = I, U^T U = D_z(0),
and (J_{k-1} + D11)^-1 likewise while J_{k-1}^-1 stays singular; the information form resumes
where the bound is positive definite. A linear model's bound from P_0 = 0 is then the Kalman
filter's covariance started from P = 0.
The accumulator takes blocks of runs, so the bound of 10^6 runs needs no more memory than one.
"""

from __future__ import annotations

import numpy as np

from ..kalman import gain, joseph
from ..linalg import definite, mT, spd_inv, sym
from ..model import System
from .local import transition


class PcrbAccumulator:
    """Sums over runs of the expectations above, block by block; `bound()` runs the recursion."""

    def __init__(self, system: System, times: np.ndarray) -> None:
        self.system = system = system.on_times(times)
        self.runs = 0
        self.linear_motion = system.motion.linear
        # sums of D_z(k) and, at k, of F~^T Q^-1 F~ over x_{k-1} and of F~ (K+1, n, n), made
        # when the first block comes (a long log in blocks of time never makes them)
        self.info = self.FtQF = self.F = 0.0

    def add(self, truth: np.ndarray, present: np.ndarray) -> None:
        """A block: true states (M, K+1, n) and which sensor measured in which run at which
        instant (M, K+1, S)."""
        self.runs += truth.shape[0]
        sums = _sums(self.system, truth, present, 0, None)
        self.info = self.info + sums[0]
        if not self.linear_motion:
            self.FtQF = self.FtQF + sums[1]
            self.F = self.F + sums[2]

    def bound(self) -> np.ndarray:
        """J_k^-1 for every instant (K+1, n, n): the bound on each state's MSE is its diagonal."""
        M = self.runs
        motion = None if self.linear_motion else (self.FtQF / M, self.F / M)
        return _recursion(self.system, self.info / M, motion, 0, None)[0]


class PcrbBlocks:
    """The bound of one run handed over in blocks of time, in order (issue 34: a long log in
    memory that does not grow with its instants): the recursion's state (J, or J^-1 while it is
    singular) and the last true state carried from block to block; `add` gives the block's
    bound, the same numbers as `PcrbAccumulator.bound` of the whole run."""

    def __init__(self, system: System, times: np.ndarray) -> None:
        self.system = system.on_times(times)
        self.carried: tuple | None = None
        self.x_last: np.ndarray | None = None  # the true state before the block, (1, n)

    def add(self, k0: int, truth: np.ndarray, present: np.ndarray) -> np.ndarray:
        """J_k^-1 (w, n, n) at the instants k0..k0+w-1 from their true states (1, w, n) and
        which sensor measured then (1, w, S)."""
        info, FtQF, F = _sums(self.system, truth, present, k0, self.x_last)
        motion = None if self.system.motion.linear else (FtQF, F)
        out, self.carried = _recursion(self.system, info, motion, k0, self.carried)
        self.x_last = truth[:, -1]
        return out


def _sums(
    sys: System, truth: np.ndarray, present: np.ndarray, k0: int, x_before: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Sums over the runs of D_z, F~^T Q^-1 F~ and F~ at the instants k0..k0+w-1 (their true
    states truth (M, w, n), the states before them x_before (M, n), None at k0 = 0)."""
    w, n = truth.shape[1], sys.n
    info = np.zeros((w, n, n))
    for j, (s, sl) in enumerate(zip(sys.sensors, sys.sensor_slices, strict=True)):
        H = s.jacobian(truth)  # (M, w, m, n)
        # R of each instant where the log's messages carry it (`System.Rs`)
        R = s.R if sys.Rs is None else sys.Rs[k0 : k0 + w, sl, sl]
        RiH = np.linalg.solve(R, H)
        info += np.einsum("mkai,mkaj,mk->kij", H, RiH, present[..., j].astype(float))
    if sys.motion.linear:
        return info, None, None
    FtQF, Fsum = np.zeros((w, n, n)), np.zeros((w, n, n))
    for k in range(max(k0, 1), k0 + w):
        motion, dt = transition(sys, k)
        prev = truth[:, k - k0 - 1] if k > k0 else x_before
        F = motion.jacobian(prev, dt)
        QiF = np.linalg.solve(motion.Q(dt), F)
        FtQF[k - k0] += np.einsum("mai,maj->ij", F, QiF)
        Fsum[k - k0] += F.sum(axis=0)
    return info, FtQF, Fsum


def _recursion(
    sys: System,
    Dz: np.ndarray,
    motion: tuple[np.ndarray, np.ndarray] | None,
    k0: int,
    carried: tuple | None,
) -> tuple[np.ndarray, tuple]:
    """J_k^-1 (w, n, n) at the instants k0..k0+w-1 from the mean D_z and (nonlinear motion)
    the means of F~^T Q^-1 F~ and F~ there, and `carried` (J or None, J^-1) of the instant
    before (None at k0 = 0); returns them and what the next instants carry."""
    out = np.empty_like(Dz)
    if carried is None:
        P0 = sys.truth_initial.cov
        J: np.ndarray | None = None  # None while J^-1 is singular (J infinite somewhere)
        if definite(P0, strict=True):
            J = spd_inv(P0, "the initial covariance") + Dz[0]
            out[0] = spd_inv(J, "the Fisher information")
        else:
            out[0] = _inverse_of_sum(P0, Dz[0])
        first, prev = 1, out[0]
    else:
        (J, prev), first = carried, 0
    for i in range(first, len(Dz)):
        motion_k, dt = transition(sys, k0 + i)
        Q = motion_k.Q(dt)
        if motion is None:
            F = motion_k.F(dt)
            P = sym(Q + F @ prev @ F.T)
            # after a definite bound (J known) the information form as it always was, with
            # no test; after a singular one, a test: a singular Q keeps a known state known
            if J is not None or definite(P, strict=True):
                J = spd_inv(P, "Q + F J^-1 F'") + Dz[i]
                out[i] = spd_inv(J, "the Fisher information")
            else:
                out[i] = _inverse_of_sum(P, Dz[i])
            prev = out[i]
            continue
        Qi = spd_inv(Q, "the process noise covariance Q")
        D12 = -mT(motion[1][i]) @ Qi
        D11 = motion[0][i]
        if J is not None:
            J = sym(Qi - mT(D12) @ np.linalg.solve(J + D11, D12)) + Dz[i]
        else:
            J = sym(Qi - mT(D12) @ _inverse_of_sum(prev, D11) @ D12) + Dz[i]
        out[i] = prev = spd_inv(J, "the Fisher information")
    return out, (J, prev)


def _inverse_of_sum(P: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(P^-1 + D)^-1 for a positive semidefinite P that may be singular (infinite information
    in its null space) and D positive semidefinite: the Joseph-form Kalman update of P by a
    measurement with H = U, R = I, where U^T U = D (U from D's eigen-decomposition)."""
    w, V = np.linalg.eigh(sym(D))
    U = (V * np.sqrt(np.clip(w, 0.0, None))).T
    eye = np.eye(len(D))
    return joseph(P, gain(P, U, eye), U, eye)


def pcrb_summary(bound: np.ndarray) -> dict[str, object]:
    """summary.json's "pcrb": mse = mean over instants of tr(J^-1)/n, and per state."""
    per_state = np.diagonal(bound, axis1=-2, axis2=-1)  # (K+1, n)
    return {
        "mse": float(per_state.sum(axis=1).mean() / bound.shape[-1]),
        "mse_per_state": [float(v) for v in per_state.mean(axis=0)],
    }
