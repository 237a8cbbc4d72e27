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

from .linalg import overflow_is_inf
from .rpe_pairs import RPE_UNITS, RpeTaker

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
    "fit_count",
    "rotation_angles",
    "rpe_pairs",
    "run_trajectory",
    "umeyama",
    "umeyama_batch",
    "umeyama_moments",
    "align_batch",
    "summary_entries",
]

ALIGNMENTS = ("none", "origin", "rigid", "similarity")
STATISTICS = ("rmse", "mean", "median", "std", "min", "max")
#: An alignment fitted by least squares needs this many matched instants.
MIN_FIT = 3


class AlignmentError(ValueError):
    """The matched positions cannot be aligned (too few, degenerate); the caller adds the file,
    architecture and run (`run`: which of a batch's runs, None: every one)."""

    def __init__(self, message: str, run: int | None = None) -> None:
        super().__init__(message)
        self.run = run


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


def umeyama_batch(
    est: np.ndarray, truth: np.ndarray, with_scale: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each run r of est (R, N, m) and truth (R, N, m), the similarity (c, R, t) minimising
    Σ‖g_k − (c R p_k + t)‖²: Umeyama 1991, means (34, 35), variance of p (36), covariance
    Σ = (1/N) Σ (g − μ_g)(p − μ_p)ᵀ (38), Σ = U D Vᵀ, S = diag(1, ..., 1, det U det V) (43),
    R = U S Vᵀ (40), c = tr(D S) / σ_p² (42) or 1, t = μ_g − c R μ_p (41). Returns rotations
    (R, m, m), translations (R, m), scales (R,).

    The solution is unique when rank Σ ≥ m − 1 (Umeyama's condition; in 3-D: the positions
    are not collinear); otherwise AlignmentError naming the first such run (its index in the
    batch). Singular values below max(N, m) ε times the largest count as zero (the rank rule of
    numpy's matrix_rank)."""
    _, n, m = est.shape
    mu_p, mu_g = est.mean(axis=1), truth.mean(axis=1)
    dp, dg = est - mu_p[:, None], truth - mu_g[:, None]
    var_p = np.einsum("rij,rij->r", dp, dp) / n
    sigma = np.einsum("rki,rkj->rij", dg, dp) / n
    return umeyama_moments(mu_p, mu_g, var_p, sigma, n, with_scale)


def umeyama_moments(
    mu_p: np.ndarray,
    mu_g: np.ndarray,
    var_p: np.ndarray,
    sigma: np.ndarray,
    n: int,
    with_scale: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`umeyama_batch` from the moments of its N = `n` positions per run: means mu_p, mu_g
    (R, m), variance var_p (R,), covariance sigma (R, m, m) (eqs. 34-38): what a log handed
    over in blocks of time accumulates (`core.trajectory_blocks`)."""
    m = mu_p.shape[-1]
    big = np.flatnonzero(~(np.isfinite(sigma).all(axis=(1, 2)) & np.isfinite(var_p)))
    if big.size:  # positions near the largest double: their moments overflow
        raise AlignmentError("positions too large to fit an alignment (their moments overflow)",
                             int(big[0]))  # fmt: skip
    u, d, vt = np.linalg.svd(sigma)
    tol = d[:, :1] * max(n, m) * np.finfo(float).eps
    rank = np.count_nonzero(d > tol, axis=1)
    bad = np.flatnonzero((d[:, 0] == 0.0) | (rank < m - 1))
    if bad.size:
        r0, k = int(bad[0]), int(rank[bad[0]])
        what = "collinear" if m == 3 and k == 1 else "degenerate"
        raise AlignmentError(
            f"the matched positions are {what} (rank {k} of {m}): a rotation cannot be fitted", r0
        )
    sgn = np.ones((len(d), m))
    sgn[np.linalg.det(u) * np.linalg.det(vt) < 0.0, -1] = -1.0  # a rotation, not a reflection
    rot = (u * sgn[:, None, :]) @ vt
    c = np.einsum("ri,ri->r", d, sgn) / var_p if with_scale else np.ones(len(d))
    return rot, mu_g - c[:, None] * np.einsum("rij,rj->ri", rot, mu_p), c


def umeyama(est: np.ndarray, truth: np.ndarray, with_scale: bool) -> Alignment:
    """`umeyama_batch` of one run: est (N, m), truth (N, m)."""
    rot, t, c = umeyama_batch(est[None], truth[None], with_scale)
    return Alignment(rot[0], t[0], float(c[0]))


def align_batch(
    est: np.ndarray, truth: np.ndarray, mode: str, first: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The alignment `mode` of each run's matched positions est (R, N, m) onto truth (R, N, m),
    fitted on the first `first` of them (None: all): rotations, translations, scales."""
    runs, n, m = est.shape
    eye = np.broadcast_to(np.eye(m), (runs, m, m))
    if mode == "none":
        return eye, np.zeros((runs, m)), np.ones(runs)
    k = fit_count(n, mode, first)
    if mode == "origin":
        return eye, truth[:, 0] - est[:, 0], np.ones(runs)
    return umeyama_batch(est[:, :k], truth[:, :k], mode == "similarity")


def fit_count(n: int, mode: str, first: int | None) -> int:
    """The matched instants (the first `first` of n) an alignment `mode` other than ``none``
    is fitted on; AlignmentError where there are too few."""
    if n == 0:
        raise AlignmentError("no matched instant to align")
    k = n if first is None else min(first, n)
    if mode != "origin" and k < MIN_FIT:
        raise AlignmentError(
            f"{k} matched instant(s) to fit a {mode} alignment, at least {MIN_FIT} needed"
        )
    return k


def align(est: np.ndarray, truth: np.ndarray, mode: str, first: int | None = None) -> Alignment:
    """`align_batch` of one run: est (N, m) onto truth (N, m)."""
    rot, t, c = align_batch(est[None], truth[None], mode, first)
    return Alignment(rot[0], t[0], float(c[0]))


def rpe_pairs(
    positions: np.ndarray, times: np.ndarray, delta: float, unit: str
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i, j) of the consecutive RPE pairs of a matched sequence: positions (N, m) (the
    aligned estimate, whose path the ``m`` rule follows), times (N,) s (see the module)."""
    ids = RpeTaker(delta, unit).take(positions, times)
    return ids[:-1], ids[1:]


def statistics_batch(e: np.ndarray) -> dict[str, np.ndarray]:
    """Each run's rmse, mean, median, std (population), min, max of its errors e (R, N > 0)."""
    return {
        "rmse": np.sqrt(np.mean(e * e, axis=1)),
        "mean": np.mean(e, axis=1),
        "median": np.median(e, axis=1),
        "std": np.std(e, axis=1),
        "min": np.min(e, axis=1),
        "max": np.max(e, axis=1),
    }


def error_statistics(e: np.ndarray) -> dict[str, float]:
    """rmse, mean, median, std (population), min, max of the errors e (N,) (NaN for none)."""
    if e.size == 0:
        return dict.fromkeys(STATISTICS, math.nan)
    return {k: float(v[0]) for k, v in statistics_batch(e[None]).items()}


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


def _measure(p: np.ndarray, g: np.ndarray, t: np.ndarray, s: TrajectorySettings) -> tuple:
    """Runs matched at the same instants t (N,): positions p, g (R, N, m) -> the alignments
    (rotations, translations, scales), aligned p (R, N, m), APE (R, N), the pairs (i, j) and
    RPE (R, P). The ``m`` rule's pairs follow the first run's path (one run per call there)."""
    rot, tr, c = align_batch(p, g, s.align, s.align_first)
    al = c[:, None, None] * np.einsum("rij,rkj->rki", rot, p) + tr[:, None, :]
    ape = np.linalg.norm(al - g, axis=2)
    i, j = rpe_pairs(al[0] if len(al) else al.reshape(0, p.shape[2]), t, s.rpe_delta, s.rpe_unit)
    rpe = np.linalg.norm((al[:, j] - al[:, i]) - (g[:, j] - g[:, i]), axis=2)
    return rot, tr, c, al, ape, i, j, rpe


def _run_of(out: tuple, r: int, matched: np.ndarray, instants: int) -> RunTrajectory:
    rot, tr, c, al, ape, _, j, rpe = out
    aligned = np.full((instants, al.shape[2]), np.nan)
    aligned[matched] = al[r]
    a = Alignment(rot[r], tr[r], float(c[r]))
    return RunTrajectory(a, aligned, matched, ape[r], rpe[r], matched[j])


@overflow_is_inf  # positions near 1e308: inf errors, reported as non-finite
def run_trajectory(
    est: np.ndarray, truth: np.ndarray, times: np.ndarray, s: TrajectorySettings
) -> RunTrajectory:
    """The metrics of one run: est and truth (K+1, n) full states, times (K+1,) s."""
    p, g = est[:, s.positions], truth[:, s.positions]
    matched = np.flatnonzero(np.isfinite(p).all(axis=1) & np.isfinite(g).all(axis=1))
    out = _measure(p[None, matched], g[None, matched], times[matched], s)
    return _run_of(out, 0, matched, len(times))


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
        """The errors e (R, N) of R runs."""
        self.count += e.size
        if e.size == 0:
            return
        st = statistics_batch(e)
        self.runs += e.shape[0]
        self.rmse2 += float(np.sum(st["rmse"] ** 2))
        for k in ("mean", "median", "std"):
            setattr(self, k, getattr(self, k) + float(np.sum(st[k])))
        self.min = min(self.min, float(st["min"].min()))
        self.max = max(self.max, float(st["max"].max()))

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

    def add(self, matched: np.ndarray, ape: np.ndarray, at: np.ndarray, rpe: np.ndarray) -> None:
        """R runs matched at the instants `matched` (N,) (indices of the K+1, increasing): APE
        (R, N); RPE (R, P) of the pairs ending at the instants `at` (P,)."""
        self.runs += ape.shape[0]
        self.ape.add(ape)
        self.rpe.add(rpe)
        self.ape_at[matched] += ape.sum(axis=0)
        self.ape_n[matched] += ape.shape[0]
        self.rpe_at[at] += rpe.sum(axis=0)
        self.rpe_n[at] += rpe.shape[0]

    def add_run(self, rt: RunTrajectory, first: bool = False) -> None:
        self.add(rt.matched, rt.ape[None], rt.rpe_at, rt.rpe[None])
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

    @overflow_is_inf
    def summary(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """(ape, rpe) of summary.json (`summary_entries`)."""
        a = self.first.alignment if self.first is not None and self.runs == 1 else None
        return summary_entries(self.settings, self.ape.result(), self.rpe.result(),
                               self.rpe.count, a)  # fmt: skip

    def series(self) -> dict[str, np.ndarray]:
        """APE and RPE over time (K+1,): the mean over the runs matched (paired) at each
        instant, NaN where none is."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return {
                "ape": np.where(self.ape_n > 0, self.ape_at / np.maximum(self.ape_n, 1), np.nan),
                "rpe": np.where(self.rpe_n > 0, self.rpe_at / np.maximum(self.rpe_n, 1), np.nan),
            }


def summary_entries(
    s: TrajectorySettings,
    ape_stats: dict[str, float],
    rpe_stats: dict[str, float],
    pairs: int,
    alignment: Alignment | None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(ape, rpe) of summary.json (DESIGN.md "Trajectory metrics") from the errors' statistics
    and `alignment`, the one run's (None: over several runs each has its own, null unless
    none was applied)."""
    ape: dict[str, Any] = dict(ape_stats)
    ape["align"] = s.align
    a = alignment
    if a is not None:
        ape |= {"rotation": a.rotation.tolist(), "translation": a.translation.tolist(),
                "scale": a.scale}  # fmt: skip
    elif s.align == "none":
        m = len(s.positions)
        ape |= {"rotation": np.eye(m).tolist(), "translation": [0.0] * m, "scale": 1.0}
    else:
        ape |= {"rotation": None, "translation": None, "scale": None}
    delta: float = int(s.rpe_delta) if s.rpe_unit == "frames" else float(s.rpe_delta)
    return ape, {"delta": delta, "unit": s.rpe_unit, "pairs": pairs} | rpe_stats


@overflow_is_inf  # positions near 1e308: inf errors, reported as non-finite
def block_sums(
    settings: TrajectorySettings,
    times: np.ndarray,
    truth: np.ndarray,
    means: dict[str, np.ndarray],
    run_offset: int = 0,
    name_runs: bool = True,
) -> dict[str, TrajectorySums]:
    """The trajectory sums of a block of runs: truth (runs, K+1, n), means {arch: (runs, K+1,
    n)}; run `run_offset` is the block's first. Runs matched at the same instants are measured
    together (a simulation's), unless the pairs follow each run's path (``m``); others one by
    one. An AlignmentError names the architecture (and the run when `name_runs`)."""
    out = {}
    s, pos = settings, list(settings.positions)
    for a, mean in means.items():
        sums = TrajectorySums(s, truth.shape[1])
        p, g = mean[..., pos], truth[..., pos]
        ok = np.isfinite(p).all(axis=2) & np.isfinite(g).all(axis=2)
        together = s.rpe_unit != "m" and len(ok) > 0 and bool((ok == ok[0]).all())
        runs = [np.arange(len(ok))] if together else [np.array([r]) for r in range(len(ok))]
        for rr in runs:
            m = np.flatnonzero(ok[rr[0]])
            try:
                res = _measure(p[rr][:, m], g[rr][:, m], times[m], s)
            except AlignmentError as e:
                where = f"{a}: run {run_offset + int(rr[e.run or 0])}" if name_runs else a
                raise AlignmentError(f"{where}: {e}") from None
            sums.add(m, res[4], m[res[6]], res[7])
            if run_offset + rr[0] == 0:
                sums.first = _run_of(res, 0, m, truth.shape[1])
        out[a] = sums
    return out
