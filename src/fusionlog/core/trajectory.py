"""Trajectory metrics: the absolute and relative position errors after an alignment.

The estimate's and the truth's positions are compared at the *matched* instants (both finite).
Before comparing, the estimate may be moved onto the truth (`align`):

* ``none``: as estimated;
* ``origin``: translated so that the first matched positions coincide;
* ``rigid``: the rotation and translation minimising the squared distances (Umeyama 1991,
  "Least-squares estimation of transformation parameters between two point patterns", IEEE
  PAMI 13(4), eqs. 34-43 with c = 1);
* ``similarity``: and the scale (eq. 42).

The fit uses the first `first` matched instants (all by default). Then, with p̃ the aligned
estimate and g the truth (evo's definitions for positions, Grupp 2017):

* APE_k = ‖p̃_k − g_k‖ at every matched instant;
* RPE_(i,j) = ‖(p̃_j − p̃_i) − (g_j − g_i)‖ on consecutive pairs of the matched sequence:
  ``frames``: the instants 0, δ, 2δ, ... of the matched sequence; ``m``: evo's path rule (an
  instant is taken when the aligned estimate has travelled δ metres along its path since the
  last one taken, starting with the first matched instant); ``s``: from the first matched
  instant, the first later instant at least δ seconds on (1 ns tolerance: the clock's
  resolution), and so on. Each pair's error is attributed to its later instant j.

Statistics of a run's errors: rmse, mean, median, std (population), min, max. Over M runs
(simulations) every run is aligned and measured on its own; the summary is the mean over runs of
each run's statistic, except rmse (the root of the mean of the runs' squared rmse, i.e. the RMS
over runs and instants when every run is matched at the same instants), min and max (the
extremes over runs). Everything here computes on arrays; nothing reads or writes a file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "ALIGNMENTS",
    "RPE_UNITS",
    "STATISTICS",
    "Alignment",
    "AlignmentError",
    "RunTrajectory",
    "TrajectorySettings",
    "TrajectorySums",
    "align",
    "block_sums",
    "error_statistics",
    "rotation_angles",
    "rpe_pairs",
    "run_trajectory",
    "umeyama",
]

ALIGNMENTS = ("none", "origin", "rigid", "similarity")
RPE_UNITS = ("frames", "m", "s")
STATISTICS = ("rmse", "mean", "median", "std", "min", "max")
#: An alignment fitted by least squares needs this many matched instants.
MIN_FIT = 3
#: Tolerance of the seconds rule of the RPE pairs: the recording's clock is in nanoseconds.
TIME_TOL = 1e-9


class AlignmentError(ValueError):
    """The matched positions cannot be aligned (too few, degenerate); the caller adds the file,
    architecture and run."""


@dataclass(frozen=True)
class TrajectorySettings:
    """``[evaluate]`` position_states (their indices in the state), align, align_first (None:
    all matched instants), rpe_delta and rpe_unit."""

    positions: tuple[int, ...]
    align: str = "none"
    align_first: int | None = None
    rpe_delta: float = 1
    rpe_unit: str = "frames"


@dataclass(frozen=True)
class Alignment:
    """p ↦ scale · rotation · p + translation."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0

    @classmethod
    def identity(cls, m: int) -> Alignment:
        return cls(np.eye(m), np.zeros(m), 1.0)

    def apply(self, p: np.ndarray) -> np.ndarray:
        """The aligned positions of p (..., m)."""
        return self.scale * (p @ self.rotation.T) + self.translation


def umeyama(est: np.ndarray, truth: np.ndarray, with_scale: bool) -> Alignment:
    """The similarity (c, R, t) minimising Σ‖g_k − (c R p_k + t)‖² over the pairs (p_k, g_k) of
    est (N, m) and truth (N, m): Umeyama 1991, means (34, 35), variance of p (36), covariance
    Σ = (1/N) Σ (g − μ_g)(p − μ_p)ᵀ (38), Σ = U D Vᵀ, S = diag(1, ..., 1, det U det V) (43),
    R = U S Vᵀ (40), c = tr(D S) / σ_p² (42) or 1, t = μ_g − c R μ_p (41).

    The solution is unique when rank Σ ≥ m − 1 (Umeyama's condition; in 3-D: the positions
    are not collinear); otherwise AlignmentError. Singular values below max(N, m) ε times the
    largest count as zero (the rank rule of numpy's matrix_rank)."""
    n, m = est.shape
    mu_p, mu_g = est.mean(axis=0), truth.mean(axis=0)
    dp, dg = est - mu_p, truth - mu_g
    var_p = float(np.einsum("ij,ij->", dp, dp)) / n
    sigma = dg.T @ dp / n
    u, d, vt = np.linalg.svd(sigma)
    tol = d[0] * max(n, m) * np.finfo(float).eps if d.size else 0.0
    rank = int(np.count_nonzero(d > tol))
    if d[0] == 0.0 or rank < m - 1:
        what = "collinear" if m == 3 and rank == 1 else "degenerate"
        raise AlignmentError(
            f"the matched positions are {what} (rank {rank} of {m}): a rotation cannot be fitted"
        )
    s = np.ones(m)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s[-1] = -1.0  # a proper rotation, not a reflection (eq. 43)
    r = (u * s) @ vt
    c = float(np.dot(d, s)) / var_p if with_scale else 1.0
    return Alignment(r, mu_g - c * (r @ mu_p), c)


def align(est: np.ndarray, truth: np.ndarray, mode: str, first: int | None = None) -> Alignment:
    """The alignment `mode` of the matched positions est (N, m) onto truth (N, m), fitted on
    the first `first` of them (None: all)."""
    n, m = est.shape
    if mode == "none":
        return Alignment.identity(m)
    if n == 0:
        raise AlignmentError("no matched instant to align")
    if mode == "origin":
        return Alignment(np.eye(m), truth[0] - est[0], 1.0)
    k = n if first is None else min(first, n)
    if k < MIN_FIT:
        raise AlignmentError(
            f"{k} matched instant(s) to fit a {mode} alignment, at least {MIN_FIT} needed"
        )
    return umeyama(est[:k], truth[:k], mode == "similarity")


def rpe_pairs(
    positions: np.ndarray, times: np.ndarray, delta: float, unit: str
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i, j) of the consecutive RPE pairs of a matched sequence: positions (N, m) (the
    aligned estimate, whose path the ``m`` rule follows), times (N,) s (see the module)."""
    n = positions.shape[0]
    if unit == "frames":
        ids = np.arange(0, n, int(delta))
    elif unit == "m":
        step = np.zeros(n)
        if n > 1:
            step[1:] = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        taken, path = [0] if n else [], 0.0
        for k in range(1, n):  # a running sum reset at each instant taken: sequential by nature
            path += step[k]
            if path >= delta:
                taken.append(k)
                path = 0.0
        ids = np.array(taken, dtype=int)
    elif unit == "s":
        taken, k = [], 0
        while k < n:
            taken.append(k)
            k = int(np.searchsorted(times, times[k] + delta - TIME_TOL, side="left"))
            k = max(k, taken[-1] + 1)
        ids = np.array(taken, dtype=int)
    else:
        raise ValueError(f"unknown RPE unit {unit!r}")
    return ids[:-1], ids[1:]


def error_statistics(e: np.ndarray) -> dict[str, float]:
    """rmse, mean, median, std (population), min, max of the errors e (NaN for none)."""
    if e.size == 0:
        return dict.fromkeys(STATISTICS, math.nan)
    return {
        "rmse": math.sqrt(float(np.mean(e * e))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
    }


def rotation_angles(r: np.ndarray) -> tuple[float, np.ndarray | None]:
    """The rotation's angle in degrees and, in 3-D, its unit axis (None in 1-D and 2-D; a 2-D
    angle is signed, counter-clockwise)."""
    m = r.shape[0]
    if m == 2:
        return math.degrees(math.atan2(r[1, 0], r[0, 0])), None
    if m != 3:
        return 0.0, None
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0)))
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    norm = float(np.linalg.norm(axis))
    if norm == 0.0:  # the identity (any axis) or a half turn (axis from R + I)
        if angle == 0.0:
            return 0.0, np.array([0.0, 0.0, 1.0])
        col = (r + np.eye(3))[:, int(np.argmax(np.diag(r)))]
        return 180.0, col / np.linalg.norm(col)
    return math.degrees(angle), axis / norm


@dataclass
class RunTrajectory:
    """One run's trajectory metrics: the alignment, the aligned positions (K+1, m; NaN where
    not matched), APE at the matched instants `matched` (indices of the K+1), RPE of each pair
    and the instant (of the K+1) it is attributed to."""

    alignment: Alignment
    aligned: np.ndarray
    matched: np.ndarray
    ape: np.ndarray
    rpe: np.ndarray
    rpe_at: np.ndarray


def run_trajectory(
    est: np.ndarray, truth: np.ndarray, times: np.ndarray, s: TrajectorySettings
) -> RunTrajectory:
    """The metrics of one run: est and truth (K+1, n) full states, times (K+1,) s."""
    p, g = est[:, s.positions], truth[:, s.positions]
    matched = np.flatnonzero(np.isfinite(p).all(axis=1) & np.isfinite(g).all(axis=1))
    pm, gm = p[matched], g[matched]
    a = align(pm, gm, s.align, s.align_first)
    aligned_m = a.apply(pm)
    aligned = np.full(p.shape, np.nan)
    aligned[matched] = aligned_m
    ape = np.linalg.norm(aligned_m - gm, axis=1)
    i, j = rpe_pairs(aligned_m, times[matched], s.rpe_delta, s.rpe_unit)
    rpe = np.linalg.norm((aligned_m[j] - aligned_m[i]) - (gm[j] - gm[i]), axis=1)
    return RunTrajectory(a, aligned, matched, ape, rpe, matched[j])


@dataclass
class _StatSums:
    """Sums over runs of one error's per-run statistics (runs without an error are skipped)."""

    runs: int = 0
    rmse2: float = 0.0
    mean: float = 0.0
    median: float = 0.0
    std: float = 0.0
    min: float = math.inf
    max: float = -math.inf
    count: int = 0  # errors (pairs for the RPE) over all runs

    def add(self, e: np.ndarray) -> None:
        self.count += e.size
        if e.size == 0:
            return
        st = error_statistics(e)
        self.runs += 1
        self.rmse2 += st["rmse"] ** 2
        self.mean += st["mean"]
        self.median += st["median"]
        self.std += st["std"]
        self.min = min(self.min, st["min"])
        self.max = max(self.max, st["max"])

    def merge(self, o: _StatSums) -> None:
        self.runs += o.runs
        self.count += o.count
        for k in ("rmse2", "mean", "median", "std"):
            setattr(self, k, getattr(self, k) + getattr(o, k))
        self.min, self.max = min(self.min, o.min), max(self.max, o.max)

    def result(self) -> dict[str, float]:
        if self.runs == 0:
            return dict.fromkeys(STATISTICS, math.nan)
        r = self.runs
        return {
            "rmse": math.sqrt(self.rmse2 / r),
            "mean": self.mean / r,
            "median": self.median / r,
            "std": self.std / r,
            "min": self.min,
            "max": self.max,
        }


@dataclass
class TrajectorySums:
    """The trajectory metrics of one architecture summed over runs, merged block by block (in
    block order): the per-run statistics (see the module), per instant the sums and counts of
    APE and RPE (the run averages drawn over time), the first run's alignment and aligned path."""

    settings: TrajectorySettings
    instants: int
    ape: _StatSums = field(default_factory=_StatSums)
    rpe: _StatSums = field(default_factory=_StatSums)
    ape_at: np.ndarray = field(default=None)  # type: ignore[assignment]
    ape_n: np.ndarray = field(default=None)  # type: ignore[assignment]
    rpe_at: np.ndarray = field(default=None)  # type: ignore[assignment]
    rpe_n: np.ndarray = field(default=None)  # type: ignore[assignment]
    runs: int = 0
    first: RunTrajectory | None = None  # run 0's, when it was in a block added here

    def __post_init__(self) -> None:
        for k in ("ape_at", "ape_n", "rpe_at", "rpe_n"):
            if getattr(self, k) is None:
                setattr(self, k, np.zeros(self.instants))

    def add_run(self, rt: RunTrajectory, first: bool = False) -> None:
        self.runs += 1
        self.ape.add(rt.ape)
        self.rpe.add(rt.rpe)
        np.add.at(self.ape_at, rt.matched, rt.ape)
        np.add.at(self.ape_n, rt.matched, 1.0)
        np.add.at(self.rpe_at, rt.rpe_at, rt.rpe)
        np.add.at(self.rpe_n, rt.rpe_at, 1.0)
        if first:
            self.first = rt

    def merge(self, o: TrajectorySums) -> TrajectorySums:
        self.runs += o.runs
        self.ape.merge(o.ape)
        self.rpe.merge(o.rpe)
        for k in ("ape_at", "ape_n", "rpe_at", "rpe_n"):
            getattr(self, k).__iadd__(getattr(o, k))
        if self.first is None:
            self.first = o.first
        return self

    def summary(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """(ape, rpe) of summary.json (DESIGN.md "Trajectory metrics"). The alignment is that
        of the one run; over several runs each has its own: null, unless none was applied."""
        s = self.settings
        ape: dict[str, Any] = dict(self.ape.result())
        ape["align"] = s.align
        a = self.first.alignment if self.first is not None else None
        if self.runs == 1 and a is not None:
            ape |= {"rotation": a.rotation.tolist(), "translation": a.translation.tolist(),
                    "scale": a.scale}  # fmt: skip
        elif s.align == "none":
            m = len(s.positions)
            ape |= {"rotation": np.eye(m).tolist(), "translation": [0.0] * m, "scale": 1.0}
        else:
            ape |= {"rotation": None, "translation": None, "scale": None}
        delta: float = int(s.rpe_delta) if s.rpe_unit == "frames" else float(s.rpe_delta)
        rpe = {"delta": delta, "unit": s.rpe_unit, "pairs": self.rpe.count} | self.rpe.result()
        return ape, rpe

    def series(self) -> dict[str, np.ndarray]:
        """APE and RPE over time (K+1,): the mean over the runs matched (paired) at each
        instant, NaN where none is."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return {
                "ape": np.where(self.ape_n > 0, self.ape_at / np.maximum(self.ape_n, 1), np.nan),
                "rpe": np.where(self.rpe_n > 0, self.rpe_at / np.maximum(self.rpe_n, 1), np.nan),
            }


def block_sums(
    settings: TrajectorySettings,
    times: np.ndarray,
    truth: np.ndarray,
    means: dict[str, np.ndarray],
    run_offset: int = 0,
    name_runs: bool = True,
) -> dict[str, TrajectorySums]:
    """The trajectory sums of a block of runs: truth (runs, K+1, n), means {arch: (runs, K+1,
    n)}; run `run_offset` is the block's first. An AlignmentError names the architecture (and
    the run when `name_runs`)."""
    out = {}
    for a, mean in means.items():
        sums = TrajectorySums(settings, truth.shape[1])
        for r in range(truth.shape[0]):
            try:
                rt = run_trajectory(mean[r], truth[r], times, settings)
            except AlignmentError as e:
                where = f"{a}: run {run_offset + r}" if name_runs else a
                raise AlignmentError(f"{where}: {e}") from None
            sums.add_run(rt, first=run_offset + r == 0)
        out[a] = sums
    return out
