"""What the evaluator checks without ground truth: each architecture's NIS (`core.nis`) over
blocks of runs, its chi-square band, and the whiteness of its normalised innovations; and when
each sensor measured (the share of runs whose measurement arrived).

Which innovations (DESIGN.md, summary.json `nis`) follows from what an architecture's
definition says its filters are (`core.architectures.definition`):

* centralised and hierarchical (CKF, HKF): each sensor's part of the centralised innovation
  against the architecture's prediction (z_s - H_s x^-, S_s = H_s P^- H_s' + R_s), so that a
  sensor whose R is wrong shows by name; with a single sensor, the whole innovation (HKF with
  the block-diagonal R it believes); the smoother (FBS): that of its forward filter, the
  centralised KF;
* single (SKF:<s>): its sensor's innovation;
* per-sensor (MSC, MSC-GMF, CI, AVG, ...): each sensor's innovation against the *fused*
  prediction. The local filters' own innovations are the same for all of them (the same
  locals, no feedback), so they could not tell the fusion rules apart; against the fused
  prediction an over-confident rule (MSC) shows NIS above the band.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fusionlog.core.architectures import REGISTRY, definition, estimate, parse_arch
from fusionlog.core.metrics import chi2_quantile
from fusionlog.core.model import System
from fusionlog.core.nis import innovations_of, whiteness

__all__ = ["NisAccumulator", "availability"]

#: Runs whose normalised innovations are kept for the whiteness check.
WHITENESS_RUNS = 200


def _parts(system: System, arch: str) -> list[tuple[str, np.ndarray]]:
    """(part name, rows of z) of an architecture's innovations: one per sensor, named by it
    (a single sensor's whole innovation too, not "all")."""
    _, sensor = parse_arch(arch, [s.name for s in system.sensors])
    kind = definition(arch).locals
    rows = np.arange(system.m)
    sl = system.sensor_slices
    if kind == "single":
        return [(sensor, rows[sl[system.sensor_index(sensor)]])]
    return [(s.name, rows[sl[j]]) for j, s in enumerate(system.sensors)]


def _centralised() -> str:
    """The registered centralised KF (a smoother's forward filter)."""
    return next(a.name for a in REGISTRY.values() if a.locals == "centralised")


class NisAccumulator:
    """Sums of NIS and degrees of freedom per instant, per architecture and part."""

    def __init__(self, system: System, archs: list[str], instants: int) -> None:
        self.system, self.archs = system, archs
        self.parts = {a: _parts(system, a) for a in archs}
        self.sum = {(a, p): np.zeros(instants) for a in archs for p, _ in self.parts[a]}
        self.dof = {key: np.zeros(instants) for key in self.sum}
        self.count = {key: np.zeros(instants) for key in self.sum}
        self.white: dict[tuple[str, str], list[np.ndarray]] = {key: [] for key in self.sum}
        self.kept = 0

    def add(
        self,
        z: np.ndarray,
        estimates: dict[str, tuple[np.ndarray, np.ndarray]],
        forward: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """One block: the stacked readings z (runs, K+1, m) and each architecture's estimates
        (`forward`: the centralised KF's, a smoother's forward filter, when the caller has
        them; else computed here)."""
        keep = max(0, WHITENESS_RUNS - self.kept)
        for a in self.archs:
            kind = definition(a).locals
            mean, cov = estimates[a]
            system, R = self.system, None
            if kind == "smoother":  # its forward filter: the centralised KF on the same data
                if forward is None:
                    fwd = estimate(self.system, z, _centralised())
                    forward = (fwd.mean, fwd.cov)
                mean, cov = forward
            if kind == "hierarchical" and len(self.system.sensors) == 1:  # its one
                R = self._blockdiag()
            parts = self.parts[a]
            got = innovations_of(system, mean, cov, z, [rows for _, rows in parts], R)
            for (part, _), inn in zip(parts, got, strict=True):
                key = (a, part)
                have = np.isfinite(inn.nis)
                self.sum[key] += np.where(have, inn.nis, 0.0).sum(axis=0)
                self.dof[key] += np.where(have, inn.dof, 0).sum(axis=0)
                self.count[key] += have.sum(axis=0)
                if keep:
                    self.white[key].append(inn.normalised[:keep])
        self.kept += min(keep, z.shape[0])

    def first_run(self) -> dict[str, dict[str, np.ndarray]]:
        """{ARCH: {part: (K+1, r)}} the first run's normalised innovations (NaN where none)."""
        return {
            a: {part: self.white[(a, part)][0][0] for part, _ in self.parts[a]}
            for a in self.archs
            if all(self.white[(a, part)] for part, _ in self.parts[a])
        }

    def _blockdiag(self) -> np.ndarray | None:
        if self.system.Rs is not None:
            return None  # per instant: the system's R (cross-covariances are rare in logs)
        R = np.zeros((self.system.m, self.system.m))
        for s, sl in zip(self.system.sensors, self.system.sensor_slices, strict=True):
            R[sl, sl] = s.R
        return R

    def series(self, confidence: float) -> dict[str, dict[str, tuple[np.ndarray, ...]]]:
        """{ARCH: {part: (run-averaged NIS, band lower, band upper)}}, NaN where no data."""
        q = (1.0 - confidence) / 2.0
        out: dict[str, dict[str, tuple[np.ndarray, ...]]] = {}
        for (a, part), s in self.sum.items():
            n, dof = self.count[(a, part)], self.dof[(a, part)]
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.where(n > 0, s / n, np.nan)
                lo = np.where(n > 0, chi2_quantile(q, np.maximum(dof, 1)) / n, np.nan)
                hi = np.where(n > 0, chi2_quantile(1 - q, np.maximum(dof, 1)) / n, np.nan)
            out.setdefault(a, {})[part] = (mean, lo, hi)
        return out

    def summary(self, confidence: float) -> dict[str, dict[str, Any]]:
        """Per architecture: {"mean", "fraction_inside", "dof", "whiteness"} of its innovation,
        or one such entry per sensor where there are several (DESIGN.md summary.json)."""
        series = self.series(confidence)
        out: dict[str, dict[str, Any]] = {}
        for a in self.archs:
            entries = {}
            for part, _ in self.parts[a]:
                key = (a, part)
                mean, lo, hi = series[a][part]
                have = self.count[key] > 0
                n = self.count[key][have].sum()
                entries[part] = {
                    "mean": float(self.sum[key][have].sum() / n) if n else float("nan"),
                    "fraction_inside": float(((mean >= lo) & (mean <= hi))[have].mean())
                    if have.any()
                    else float("nan"),
                    "dof": float(self.dof[key][have].sum() / n) if n else float("nan"),
                }
                white = whiteness(np.concatenate(self.white[key]) if self.white[key] else
                                  np.zeros((0, 1, 1)))  # fmt: skip
                # flat numbers (a summary's metrics are numbers): whiteness_<what>
                entries[part] |= {f"whiteness_{k}": float(v) for k, v in white.items()}
            # one innovation (a single sensor, SKF:<s>): its entry itself (DESIGN.md)
            out[a] = entries[next(iter(entries))] if len(entries) == 1 else entries
        return out


def availability(measured: np.ndarray, scheduled: np.ndarray, runs: int) -> np.ndarray:
    """(K+1,) share of the runs whose measurement arrived, NaN where the sensor does not
    measure; `measured` counts the runs with a reading at each instant."""
    return np.where(scheduled, measured / max(runs, 1), np.nan)
