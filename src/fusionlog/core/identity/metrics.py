"""Identity metrics of BAYES and DS estimates against the true classes, block by block of runs.

Per step k over the runs (the summary's values are means over the steps, ``final`` the values
at k = K):

* decision (:func:`.fusion.decision_weights`): BAYES the class of largest posterior; DS the class
  of largest belief, ties in belief broken by plausibility. Remaining ties are split evenly (a
  run counts 1/|tied| as correct if its class is among the tied ones: the expected accuracy of
  a random tie-break). A DS run in total conflict decides nothing (counts as wrong).
* ``accuracy``: share of runs classified correctly.
* ``mean_p_true``: mean probability of the true class: BAYES posterior; DS the normalised
  plausibility Pl({c}) / sum_c' Pl({c'}) (equal to a Bayes posterior with a uniform prior and
  the reports' contour functions as likelihoods, since Dempster's rule multiplies them).
* ``log_loss``: mean of -log of that probability (infinite if it is zero for some run: a
  reliable sensor ruled the true class out).
* DS: ``mean_belief_true``, ``mean_plausibility_true``, ``mean_conflict`` (per-step K),
  ``final.accumulated_conflict``, ``total_conflict`` (share of runs in total conflict at K).
* ``disagreement``: share of runs where the BAYES and DS decisions differ (ties as above:
  1 - sum_c w_BAYES(c) w_DS(c)).
* ``stderr``: Monte Carlo standard errors of the overall accuracy, log-loss and mean_p_true,
  from the spread of the per-run averages over the steps (whole runs come in one block, so the
  correlation of a run's steps is accounted for).

DS values are averaged over the runs where DS is defined (not in total conflict); accuracy and
disagreement over all runs. Pure numpy, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from .fusion import decision_weights
from .model import ARCHITECTURES

__all__ = ["IdentityEvaluation", "IdentityMetrics", "MetricSums", "PerClassSums", "SampleRuns"]

#: {run: (true class index, {ARCH: {"probability" | "belief" | "plausibility": (K+1, N)}})}
SampleRuns = dict[int, tuple[int, dict[str, dict[str, np.ndarray]]]]


class MetricSums:
    """Per-step sums over runs (and per-run averages for standard errors) of one metric."""

    def __init__(self, n_steps: int) -> None:
        self.sum = np.zeros(n_steps)
        self.count = np.zeros(n_steps)
        self.run_sum = 0.0
        self.run_sq = 0.0
        self.runs = 0

    def add(self, values: np.ndarray) -> None:
        """values (B, K+1) of whole runs, NaN where undefined (left out)."""
        ok = ~np.isnan(values)
        self.sum += np.where(ok, values, 0.0).sum(axis=0)
        self.count += ok.sum(axis=0)
        has = ok.any(axis=1)
        if has.any():
            with np.errstate(invalid="ignore"):
                per_run = np.where(ok, values, 0.0).sum(axis=1)[has] / ok.sum(axis=1)[has]
            self.run_sum += float(per_run.sum())
            self.run_sq += float((per_run * per_run).sum())
            self.runs += int(has.sum())

    def merge(self, other: MetricSums) -> None:
        """Add another accumulator's sums (other runs of the same steps) into this one."""
        self.sum += other.sum
        self.count += other.count
        self.run_sum += other.run_sum
        self.run_sq += other.run_sq
        self.runs += other.runs

    def series(self) -> np.ndarray:
        """(K+1,) mean over the runs where defined; NaN where no run is."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 0, self.sum / np.maximum(self.count, 1), np.nan)

    def overall(self) -> float:
        """Mean of :meth:`series` over the steps where it is defined."""
        s = self.series()
        s = s[~np.isnan(s)]
        return float(s.mean()) if s.size else math.nan

    def final(self) -> float:
        """The value at k = K."""
        return float(self.series()[-1])

    def stderr(self) -> float:
        """Standard error of the overall mean from the spread of the per-run averages."""
        n = self.runs
        if n < 2 or not math.isfinite(self.run_sq):
            return math.nan
        mean = self.run_sum / n
        var = max(self.run_sq / n - mean * mean, 0.0) * n / (n - 1)
        return math.sqrt(var / n)


class PerClassSums:
    """Per step and class c: mean over the runs whose truth is c of a score of class c."""

    def __init__(self, n_steps: int, n: int) -> None:
        self.sum = np.zeros((n_steps, n))
        self.count = np.zeros((n_steps, n))

    def add(self, truth: np.ndarray, scores: np.ndarray) -> None:
        """truth (B,) class indices, scores (B, K+1, N); NaN scores are left out."""
        own = _true(scores, truth)
        ok = ~np.isnan(own)
        onehot = truth[:, None] == np.arange(scores.shape[-1])[None, :]  # (B, N)
        self.sum += np.einsum("bk,bn->kn", np.where(ok, own, 0.0), onehot)
        self.count += np.einsum("bk,bn->kn", ok.astype(float), onehot)

    def merge(self, other: PerClassSums) -> None:
        """Add another accumulator's sums into this one."""
        self.sum += other.sum
        self.count += other.count

    def series(self) -> np.ndarray:
        """(K+1, N) means; NaN where no run of that class is defined."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 0, self.sum / np.maximum(self.count, 1), np.nan)


class IdentityEvaluation(NamedTuple):
    """What :meth:`IdentityMetrics.finish` returns."""

    #: summary["architectures"]: {ARCH: {"accuracy", "log_loss", "mean_p_true", ..., "final",
    #: "stderr"}}
    architectures: dict[str, dict[str, Any]]
    #: {ARCH: {metric or per-class kind: (K+1,) or (K+1, N)}}, the recording's time series
    series: dict[str, dict[str, np.ndarray]]
    #: (K+1,) share of runs where BAYES and DS decide differently; None unless both are there
    disagreement: np.ndarray | None
    #: summary's "disagreement" (mean over steps) and "final_disagreement"; None likewise
    disagreement_overall: float | None
    disagreement_final: float | None
    #: the first `sample_runs` runs, for drawing one by one
    samples: SampleRuns


def _true(values: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """values (B, K+1, N) at each run's true class: (B, K+1)."""
    return np.take_along_axis(values, truth[:, None, None], axis=-1)[..., 0]


def _neg_log(p: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return -np.log(p)


class IdentityMetrics:
    """Accumulates the identity metrics of blocks of whole runs (see the module docstring).

    n_steps: K + 1 instants; classes: the frame (N names); archs: a subset of ARCHITECTURES, in
    the order of the summary; sample_runs: how many of the first runs to keep whole.
    """

    def __init__(
        self,
        n_steps: int,
        classes: Sequence[str],
        archs: Sequence[str],
        sample_runs: int = 0,
    ) -> None:
        unknown = [a for a in archs if a not in ARCHITECTURES]
        if unknown or not archs:
            raise ValueError(f"identity architectures must be some of {ARCHITECTURES}: {archs}")
        self.n_steps, self.classes, self.archs = n_steps, tuple(classes), tuple(archs)
        self.sample_runs = sample_runs
        n = len(self.classes)
        self.metrics: dict[str, dict[str, MetricSums]] = {}
        for a in self.archs:
            names = ["accuracy", "p_true", "log_loss"]
            if a == "DS":
                names += ["belief_true", "plausibility_true", "conflict", "accumulated_conflict"]
            self.metrics[a] = {k: MetricSums(n_steps) for k in names}
        self.per_class = {
            (a, kind): PerClassSums(n_steps, n)
            for a in self.archs
            for kind in (("probability",) if a == "BAYES" else ("belief", "plausibility"))
        }
        self.disagreement = MetricSums(n_steps) if len(self.archs) == 2 else None
        self.total_conflict = 0  # DS runs in total conflict at k = K
        self.runs = 0
        self.samples: SampleRuns = {}

    def add(self, truth: np.ndarray, estimates: Mapping[str, np.ndarray], run_offset: int) -> None:
        """Add a block of whole runs [run_offset, run_offset + B).

        truth: (B,) true class indices; estimates: {ARCH: (B, K+1, dim)} for every architecture
        of this accumulator, as :func:`.fusion.estimate` returns them.
        """
        n = len(self.classes)
        runs = truth.shape[0]
        weights: dict[str, np.ndarray] = {}
        for a in self.archs:
            v = estimates[a]
            mt = self.metrics[a]
            if a == "BAYES":
                p = v
                weights[a] = decision_weights(p)
                self.per_class[(a, "probability")].add(truth, p)
                kept = {"probability": v}
            else:
                bel, pl = v[..., :n], v[..., n : 2 * n]
                with np.errstate(invalid="ignore", divide="ignore"):
                    p = pl / pl.sum(axis=-1, keepdims=True)
                weights[a] = decision_weights(bel, tiebreak=pl)
                mt["belief_true"].add(_true(bel, truth))
                mt["plausibility_true"].add(_true(pl, truth))
                mt["conflict"].add(v[..., 2 * n])
                mt["accumulated_conflict"].add(v[..., 2 * n + 1])
                self.per_class[(a, "belief")].add(truth, bel)
                self.per_class[(a, "plausibility")].add(truth, pl)
                self.total_conflict += int(np.isnan(bel[:, -1]).any(axis=-1).sum())
                kept = {"belief": bel, "plausibility": pl}
            p_true = _true(p, truth)
            mt["accuracy"].add(_true(weights[a], truth))
            mt["p_true"].add(p_true)
            mt["log_loss"].add(_neg_log(p_true))
            for r in range(run_offset, min(run_offset + runs, self.sample_runs)):
                entry = self.samples.setdefault(r, (int(truth[r - run_offset]), {}))[1]
                # copies: a view would keep the whole block alive
                entry[a] = {k: x[r - run_offset].copy() for k, x in kept.items()}
        if self.disagreement is not None:
            self.disagreement.add(1.0 - (weights["BAYES"] * weights["DS"]).sum(axis=-1))
        self.runs += runs

    def merge(self, other: IdentityMetrics) -> IdentityMetrics:
        """Add the sums of another accumulator (other runs, same layout) into this one."""
        if (other.n_steps, other.classes, other.archs) != (self.n_steps, self.classes, self.archs):
            raise ValueError("cannot merge identity metrics of different steps, classes or archs")
        for a, mt in self.metrics.items():
            for k, s in mt.items():
                s.merge(other.metrics[a][k])
        for key, pc in self.per_class.items():
            pc.merge(other.per_class[key])
        if self.disagreement is not None and other.disagreement is not None:
            self.disagreement.merge(other.disagreement)
        self.total_conflict += other.total_conflict
        self.runs += other.runs
        self.samples = dict(sorted({**self.samples, **other.samples}.items()))
        return self

    def finish(self) -> IdentityEvaluation:
        """The summary's architectures, the time series, the disagreement and the samples."""
        arch_summary: dict[str, dict[str, Any]] = {}
        series: dict[str, dict[str, np.ndarray]] = {}
        for a in self.archs:
            mt = self.metrics[a]
            entry: dict[str, Any] = {
                "accuracy": mt["accuracy"].overall(),
                "log_loss": mt["log_loss"].overall(),
                "mean_p_true": mt["p_true"].overall(),
            }
            final: dict[str, Any] = {
                "accuracy": mt["accuracy"].final(),
                "log_loss": mt["log_loss"].final(),
                "mean_p_true": mt["p_true"].final(),
            }
            if a == "DS":
                entry["mean_belief_true"] = mt["belief_true"].overall()
                entry["mean_plausibility_true"] = mt["plausibility_true"].overall()
                entry["mean_conflict"] = mt["conflict"].overall()
                final["mean_belief_true"] = mt["belief_true"].final()
                final["mean_plausibility_true"] = mt["plausibility_true"].final()
                final["accumulated_conflict"] = mt["accumulated_conflict"].final()
                entry["total_conflict"] = self.total_conflict / self.runs
            entry["final"] = final
            entry["stderr"] = {
                "accuracy": mt["accuracy"].stderr(),
                "log_loss": mt["log_loss"].stderr(),
                "mean_p_true": mt["p_true"].stderr(),
            }
            arch_summary[a] = entry
            series[a] = {k: s.series() for k, s in mt.items()}
            for (aa, kind), pc in self.per_class.items():
                if aa == a:
                    series[a][kind] = pc.series()
        d = self.disagreement
        return IdentityEvaluation(
            architectures=arch_summary,
            series=series,
            disagreement=d.series() if d is not None else None,
            disagreement_overall=d.overall() if d is not None else None,
            disagreement_final=d.final() if d is not None else None,
            samples=dict(self.samples),
        )
