"""Monte Carlo evaluation metrics of Section VI (eqs. 44-47), accumulated over blocks of runs.

The accumulator keeps only per-step sums (and per-run averages reduced to sums), so

* memory does not grow with the number of runs M,
* blocks of runs merge by adding sums: the result does not depend on how the runs were split
  (up to floating-point rounding of the additions),
* a run is always handed over whole (all steps of it in one block), which lets us keep the
  per-run average of each metric over steps and hence a Monte Carlo standard error that accounts
  for the correlation of the errors across steps within a run.

Per step k, over the runs m whose estimate is defined at k (finite mean and covariance):

    MSE(x_i,k) = sum_m (x_i,k,m - xhat_i,k,m)^2 / M_k                      (eq. 44)
    NEES_k     = sum_m e' P^-1 e / M_k,   DM_k = sum_m sqrt(e' P^-1 e) / M_k   (eq. 46)
    trace_k    = sum_m trace(P_k,m) / M_k

Overall values average the per-step values over the steps where at least one run is defined:
``mse`` (eq. 45: over states and steps), ``anees``, ``dm`` (eq. 47), ``mean_trace``. Entries with
an undefined estimate (NaN mean or covariance: no prior yet, state not yet observable) are left
out of every metric and counted in ``excluded``.

Chi-square band: if the filter is consistent, M_k * NEES_k ~ chi2(M_k n), so the two-sided band
at confidence c is chi2.ppf((1 -+ c) / 2, M_k n) / M_k (scipy quantiles).

Standard errors of the overall MSE / ANEES / DM come from the spread of the per-run averages over
the valid steps of each run. They are exact for eqs. 45/47 when every run has the same set of
valid steps (the usual case: undefined steps are the same for all runs); otherwise they are the
standard error of the equally weighted mean of the per-run averages, a close approximation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import NumericalError
from .chi2 import chi2_quantile, expected_mahalanobis_consistent
from .linalg import finite_mean, overflow_is_inf, spd_inv, spd_inv_scaled, wide_diagonal

__all__ = [
    "MetricsAccumulator",
    "MetricsResult",
    "MetricsWorkspace",
    "chi2_quantile",
    "expected_mahalanobis_consistent",
]


class MetricsWorkspace:
    """Scratch arrays for `MetricsAccumulator.add`, reused from call to call.

    Fresh multi-megabyte temporaries are mapped anew by the allocator, and in a virtual machine
    their first-touch page faults cost several times the arithmetic done in them (reusing them
    took the paper example's evaluate from 0.44 to 0.31 s). So `add` works through a block in
    chunks of at most CHUNK_ELEMENTS run-step-states, in arrays kept here: a few hundred
    kilobytes that stay in cache and are touched once per workspace, however many blocks go
    through. Each accumulator owns one by default; accumulators used one after the other may
    share one.
    """

    #: run-step-states per chunk: 2^15 doubles = 256 KiB per array.
    CHUNK_ELEMENTS = 1 << 15

    def __init__(self) -> None:
        self.buffers: dict[str, np.ndarray] = {}

    def runs_per_chunk(self, per_run: int) -> int:
        """Runs per chunk for runs of `per_run` elements (at least one whole run)."""
        return max(1, self.CHUNK_ELEMENTS // per_run)

    def array(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """An uninitialised float array of `shape` for the temporary `name`: a view of a buffer
        kept from earlier calls (grown when too small), valid until the next call for `name`."""
        size = math.prod(shape)
        buf = self.buffers.get(name)
        if buf is None or buf.size < size:
            buf = self.buffers[name] = np.empty(size)
        return buf[:size].reshape(shape)


@dataclass
class MetricsAccumulator:
    """Sums of the Section VI metrics over runs, per time step; feed it blocks of whole runs."""

    n_steps: int  # K + 1
    n_states: int  # n
    runs: int = 0  # runs seen (including runs that are undefined everywhere)
    count: np.ndarray = field(init=False)  # (K+1,) runs with a defined estimate at step k
    sse: np.ndarray = field(init=False)  # (K+1, n) sum of squared errors
    sse_sq: np.ndarray = field(init=False)  # (K+1, n) sum of squared squared errors
    trace_sum: np.ndarray = field(init=False)  # (K+1,)
    nees_sum: np.ndarray = field(init=False)  # (K+1,)
    nees_sq: np.ndarray = field(init=False)  # (K+1,)
    dm_sum: np.ndarray = field(init=False)  # (K+1,)
    dm_sq: np.ndarray = field(init=False)  # (K+1,)
    # per-run averages over the run's valid steps: [count, sum, sum of squares] for mse/nees/dm
    run_count: int = 0
    run_sums: np.ndarray = field(init=False)  # (3,) mse, nees, dm
    run_sq: np.ndarray = field(init=False)  # (3,)
    #: scratch arrays of `add` (see MetricsWorkspace); not part of the result
    workspace: MetricsWorkspace = field(default_factory=MetricsWorkspace, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.n_steps < 1 or self.n_states < 1:
            raise ValueError(
                f"need n_steps >= 1 and n_states >= 1, got {self.n_steps}, {self.n_states}"
            )
        s, n = self.n_steps, self.n_states
        self.count = np.zeros(s, dtype=np.int64)
        self.sse = np.zeros((s, n))
        self.sse_sq = np.zeros((s, n))
        self.trace_sum = np.zeros(s)
        self.nees_sum = np.zeros(s)
        self.nees_sq = np.zeros(s)
        self.dm_sum = np.zeros(s)
        self.dm_sq = np.zeros(s)
        self.run_sums = np.zeros(3)
        self.run_sq = np.zeros(3)

    @property
    def excluded(self) -> np.ndarray:
        """(K+1,) number of runs whose estimate was undefined at step k."""
        return self.runs - self.count

    # ------------------------------------------------------------------ accumulate
    @overflow_is_inf
    def add(self, x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> None:
        """Add a block of whole runs.

        x, mean: (m, K+1, n); cov: (K+1, n, n) shared by all runs of the block (the common case:
        one inverse per step for all runs) or (m, K+1, n, n) per run. NaN in mean or cov marks
        an undefined estimate; that (run, step) entry is excluded and counted.
        """
        x = np.asarray(x, dtype=float)
        mean = np.asarray(mean, dtype=float)
        cov = np.asarray(cov, dtype=float)
        s, n = self.n_steps, self.n_states
        if x.ndim != 3 or x.shape[1:] != (s, n):
            raise ValueError(f"truth must have shape (runs, {s}, {n}), got {x.shape}")
        m = x.shape[0]
        if mean.shape != x.shape:
            raise ValueError(f"mean must have shape {x.shape}, got {mean.shape}")
        shared = cov.shape == (s, n, n)
        if not shared and cov.shape != (m, s, n, n):
            raise ValueError(
                f"cov must have shape ({s}, {n}, {n}) or ({m}, {s}, {n}, {n}), got {cov.shape}"
            )
        if m == 0:
            return

        ws = self.workspace
        terms = _cov_terms(cov) if shared else None  # one inverse per step for the block
        chunk = ws.runs_per_chunk(s * n)
        for a in range(0, m, chunk):
            b = min(m, a + chunk)
            err = np.subtract(x[a:b], mean[a:b], out=ws.array("err", (b - a, s, n)))
            per_run = self._add_steps(err, terms or _cov_terms(cov[a:b]), shared)
            self._add_runs(per_run)
        self.runs += m

    def _add_runs(self, per_run: np.ndarray) -> None:
        """Per-run averages over the run's own valid steps (whole runs are in every chunk)."""
        n_valid, run_sse, run_nees, run_dm = per_run
        has = n_valid > 0
        if has.any():
            k = n_valid[has]
            avg = np.stack([run_sse[has] / (self.n_states * k), run_nees[has] / k, run_dm[has] / k])
            self.run_count += int(has.sum())
            self.run_sums += avg.sum(axis=1)
            self.run_sq += (avg * avg).sum(axis=1)

    def _add_steps(
        self, err: np.ndarray, terms: tuple[np.ndarray, np.ndarray, np.ndarray | None], shared: bool
    ) -> np.ndarray:
        """Adds the per-step sums of a chunk of runs (err: (m, K+1, n) truth minus estimate,
        terms: `_cov_terms` of its covariances); returns each run's sums over its steps (4, m):
        valid steps, squared errors, NEES, DM."""
        m, w, n = err.shape
        ws = self.workspace
        p_inv, tr, cov_ok = terms
        per_run = np.zeros((4, m))
        # One sum tells whether everything is finite (the usual case); only otherwise is the
        # per-entry validity mask built and the undefined entries zeroed.
        if cov_ok is None and math.isfinite(float(err.sum())):
            valid = None
        else:
            valid = np.isfinite(err).all(axis=-1)  # (m, w)
            if cov_ok is not None:  # (w,) or (m, w)
                valid &= cov_ok[None, :] if shared else cov_ok
            err = np.where(valid[..., None], err, 0.0)

        if shared:
            # one inverse per step for all m runs: a batched (m x n) @ (n x n) product per step
            err_t = err.transpose(1, 0, 2)  # (w, m, n) view
            y = np.matmul(err_t, p_inv, out=ws.array("y", err_t.shape))
            nees = _rowdot(y, err_t, ws).T  # (m, w)
        else:
            y = np.matmul(err[..., None, :], p_inv, out=ws.array("y", (m, w, 1, n)))
            nees = _rowdot(y[..., 0, :], err, ws)
        if valid is None:
            self.count += m
            self.trace_sum += tr * m if shared else tr.sum(axis=0)
            per_run[0] += w
        else:
            nees = np.where(valid, nees, 0.0)
            count = valid.sum(axis=0)
            self.count += count
            self.trace_sum += tr * count if shared else np.where(valid, tr, 0.0).sum(axis=0)
            per_run[0] += valid.sum(axis=1)

        # Sums over runs and over steps as matrix-vector products: numpy reduces the short
        # trailing axes of these (m, w, n) arrays several times slower than BLAS does.
        ones_m, ones_w = np.ones(m), np.ones(w)
        sq = np.multiply(err, err, out=ws.array("sq", err.shape)).reshape(m, w * n)
        per_run[1] += sq @ np.ones(w * n)
        self.sse += (ones_m @ sq).reshape(w, n)
        self.sse_sq += (ones_m @ np.square(sq, out=sq)).reshape(w, n)
        self.nees_sum += ones_m @ nees
        per_run[2] += nees @ ones_w
        # NEES is negative only for an indefinite reported P
        dm = np.maximum(nees, 0.0, out=ws.array("dm", nees.shape))
        self.dm_sq += ones_m @ dm  # sum of DM^2 = sum of the non-negative NEES
        self.nees_sq += ones_m @ np.square(nees, out=nees)
        np.sqrt(dm, out=dm)
        self.dm_sum += ones_m @ dm
        per_run[3] += dm @ ones_w
        return per_run

    @overflow_is_inf
    def merge(self, other: MetricsAccumulator) -> MetricsAccumulator:
        """Add another accumulator's sums into this one (same steps and states); returns self."""
        if (other.n_steps, other.n_states) != (self.n_steps, self.n_states):
            raise ValueError(
                f"cannot merge accumulators of shape ({other.n_steps}, {other.n_states}) "
                f"into ({self.n_steps}, {self.n_states})"
            )
        self.runs += other.runs
        self.run_count += other.run_count
        for name in (
            "count",
            "sse",
            "sse_sq",
            "trace_sum",
            "nees_sum",
            "nees_sq",
            "dm_sum",
            "dm_sq",
            "run_sums",
            "run_sq",
        ):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        return self

    # ------------------------------------------------------------------ results
    @overflow_is_inf
    def finalize(self, confidence: float = 0.95) -> MetricsResult:
        """Per-step and overall metrics; `confidence` sets the two-sided chi-square NEES band."""
        if not 0.0 < confidence < 1.0:
            raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
        n = self.n_states
        c = self.count.astype(float)
        valid = self.count > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            inv = np.where(valid, 1.0 / np.where(valid, c, 1.0), np.nan)
            mse_step = self.sse * inv[:, None]
            trace_step = self.trace_sum * inv
            nees_step = self.nees_sum * inv
            dm_step = self.dm_sum * inv
            mse_step_se = _stderr_steps(self.sse, self.sse_sq, self.count)
            nees_step_se = _stderr_steps(self.nees_sum, self.nees_sq, self.count)
            dm_step_se = _stderr_steps(self.dm_sum, self.dm_sq, self.count)

        lower = np.full(self.n_steps, np.nan)
        upper = np.full(self.n_steps, np.nan)
        dof = c[valid] * n
        lower[valid] = chi2_quantile((1.0 - confidence) / 2.0, dof) / c[valid]
        upper[valid] = chi2_quantile((1.0 + confidence) / 2.0, dof) / c[valid]
        inside = valid & (nees_step >= lower) & (nees_step <= upper)

        def over_steps(a: np.ndarray) -> Any:
            if not valid.any():
                return np.full(a.shape[1:], np.nan) if a.ndim > 1 else float("nan")
            r = a[valid].mean(axis=0)
            return r if a.ndim > 1 else float(r)

        mse_per_state = over_steps(mse_step)
        se = [
            _stderr(self.run_sums[j], self.run_sq[j], self.run_count) for j in range(3)
        ]  # mse, anees, dm
        return MetricsResult(
            runs=self.runs,
            n_steps=self.n_steps,
            n_states=n,
            confidence=float(confidence),
            count=self.count.copy(),
            excluded=self.excluded.copy(),
            mse_step=mse_step,
            mse_step_stderr=mse_step_se,
            trace_step=trace_step,
            nees_step=nees_step,
            nees_step_stderr=nees_step_se,
            dm_step=dm_step,
            dm_step_stderr=dm_step_se,
            nees_lower=lower,
            nees_upper=upper,
            nees_inside=inside,
            mse_per_state=mse_per_state,
            mse=float(np.mean(mse_per_state)) if valid.any() else float("nan"),
            mean_trace=over_steps(trace_step),
            anees=over_steps(nees_step),
            dm=over_steps(dm_step),
            nees_fraction_inside=float(inside[valid].mean()) if valid.any() else float("nan"),
            stderr_mse=se[0],
            stderr_anees=se[1],
            stderr_dm=se[2],
        )


def _cov_terms(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """P^-1 and trace P of reported covariances ((K+1, n, n) or (m, K+1, n, n)), with the
    undefined ones (NaN) replaced by I, and which are defined (None: all of them)."""
    if math.isfinite(float(cov.sum())):
        cov_ok, p_safe = None, cov
    else:
        cov_ok = np.isfinite(cov).all(axis=(-2, -1))
        p_safe = np.where(cov_ok[..., None, None], cov, np.eye(cov.shape[-1]))
    try:
        # Badly scaled P (a position known to 1e-150 beside a velocity known to 0.1) loses its
        # small entries in LU's inverse: Jacobi scaling. Many P: the batch Cholesky kernel (5x).
        p_inv = spd_inv_scaled(p_safe) if wide_diagonal(p_safe) else spd_inv(p_safe)
    except (np.linalg.LinAlgError, NumericalError):
        p_inv = np.linalg.pinv(p_safe, hermitian=True)
    return p_inv, np.trace(p_safe, axis1=-2, axis2=-1), cov_ok


def _rowdot(a: np.ndarray, b: np.ndarray, ws: MetricsWorkspace) -> np.ndarray:
    """sum_i a[..., i] * b[..., i]; a loop over the (small) state axis, because numpy reduces a
    short trailing axis about ten times slower than it adds whole arrays."""
    out = np.multiply(a[..., 0], b[..., 0], out=ws.array("dot", a.shape[:-1]))
    term = ws.array("term", out.shape)
    for i in range(1, a.shape[-1]):
        out += np.multiply(a[..., i], b[..., i], out=term)
    return out


def _stderr(total: float, total_sq: float, count: int) -> float:
    """Standard error of a mean from the sum and the sum of squares of `count` samples."""
    if count < 2:
        return float("nan")
    mean = total / count
    var = max(total_sq / count - mean * mean, 0.0) * count / (count - 1)
    return math.sqrt(var / count)


def _stderr_steps(total: np.ndarray, total_sq: np.ndarray, count: np.ndarray) -> np.ndarray:
    c = count.astype(float).reshape(count.shape + (1,) * (total.ndim - 1))
    ok = c >= 2
    cs = np.where(ok, c, 2.0)
    mean = total / cs
    var = np.maximum(total_sq / cs - mean * mean, 0.0) * cs / (cs - 1.0)
    return np.where(ok, np.sqrt(var / cs), np.nan)


@dataclass(frozen=True)
class MetricsResult:
    """Finalised metrics of one architecture. Per-step arrays have NaN where no run is defined."""

    runs: int
    n_steps: int
    n_states: int
    confidence: float
    count: np.ndarray  # (K+1,) runs with a defined estimate
    excluded: np.ndarray  # (K+1,) runs left out (undefined estimate)
    mse_step: np.ndarray  # (K+1, n)                   eq. 44
    mse_step_stderr: np.ndarray  # (K+1, n)
    trace_step: np.ndarray  # (K+1,)
    nees_step: np.ndarray  # (K+1,) run-averaged NEES
    nees_step_stderr: np.ndarray  # (K+1,)
    dm_step: np.ndarray  # (K+1,) run-averaged Mahalanobis distance (eq. 46)
    dm_step_stderr: np.ndarray  # (K+1,)
    nees_lower: np.ndarray  # (K+1,) chi-square band of the run-averaged NEES
    nees_upper: np.ndarray  # (K+1,)
    nees_inside: np.ndarray  # (K+1,) bool
    mse_per_state: np.ndarray  # (n,)
    mse: float  # eq. 45
    mean_trace: float
    anees: float
    dm: float  # eq. 47
    nees_fraction_inside: float
    stderr_mse: float
    stderr_anees: float
    stderr_dm: float

    @property
    def valid_steps(self) -> np.ndarray:
        """(K+1,) bool: steps where at least one run has a defined estimate."""
        return self.count > 0

    def expected_overall(
        self,
        expected_mse: np.ndarray | None = None,
        expected_nees: np.ndarray | None = None,
        expected_dm: np.ndarray | None = None,
    ) -> dict[str, float | None]:
        """Overall expected values: means of the per-step expected arrays over the same steps as
        the Monte Carlo values (steps with a defined estimate; non-finite entries skipped)."""
        out: dict[str, float | None] = {}
        for key, arr, shape in (
            ("mse", expected_mse, (self.n_steps, self.n_states)),
            ("anees", expected_nees, (self.n_steps,)),
            ("dm", expected_dm, (self.n_steps,)),
        ):
            if arr is None:
                out[key] = None
                continue
            a = np.asarray(arr, dtype=float)
            if a.shape != shape:
                raise ValueError(f"expected {key} must have shape {shape}, got {a.shape}")
            valid = self.valid_steps
            out[key] = expected_means(a, valid) if key == "mse" else finite_mean(a[valid])
        return out

    def summary(
        self,
        expected_mse: np.ndarray | None = None,
        expected_nees: np.ndarray | None = None,
        expected_dm: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """The per-architecture entry of summary.json (DESIGN.md), plus `expected.dm`, `stderr`
        and `excluded`. An undefined value is NaN (written to JSON as null, listed in the
        top-level ``non_finite`` note); `expected` values are None without an exact analysis."""
        return {
            "mse": _num(self.mse),
            "mse_per_state": [_num(v) for v in self.mse_per_state],
            "mean_trace": _num(self.mean_trace),
            "anees": _num(self.anees),
            "nees_fraction_inside": _num(self.nees_fraction_inside),
            "dm": _num(self.dm),
            "expected": self.expected_overall(expected_mse, expected_nees, expected_dm),
            "stderr": {
                "mse": _num(self.stderr_mse),
                "anees": _num(self.stderr_anees),
                "dm": _num(self.stderr_dm),
            },
            "excluded": int(self.excluded.sum()),
        }

    def series(
        self,
        expected_mse: np.ndarray | None = None,
        expected_nees: np.ndarray | None = None,
        expected_dm: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Per-step arrays as `fusionlog.io.rrd.write_recording` takes them per architecture."""
        out = {
            "mse": self.mse_step,
            "trace": self.trace_step,
            "nees": self.nees_step,
            "dm": self.dm_step,
        }
        for key, arr in (
            ("expected_mse", expected_mse),
            ("expected_nees", expected_nees),
            ("expected_dm", expected_dm),
        ):
            if arr is not None:
                out[key] = np.asarray(arr, dtype=float)
        return out


def expected_means(mse_per_state: np.ndarray, valid: np.ndarray) -> float | None:
    """The overall expected MSE (eq. 45 on the exact per-step (K+1, n)): the mean over states of
    each state's finite mean over the steps `valid` (K+1,); None where a state has none."""
    sel = mse_per_state[valid]
    per_state = [finite_mean(sel[:, i]) for i in range(sel.shape[1])]
    return None if any(v is None for v in per_state) else float(np.mean(per_state))


def _num(v: float) -> float:
    # NaN (undefined) and inf stay: JSON writers (fusionlog.jsonout) turn them into null plus a
    # note, so that a null in a metric's place is never ambiguous.
    return float(v)
