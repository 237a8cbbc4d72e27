"""APE and RPE of a long one-run log in blocks of time (issue 34; DESIGN.md "Trajectory metrics"),
in memory that does not grow with its instants: `TrajectoryPart`'s numbers, in two passes.

First pass (`add`, as the blocks come): the position columns of the truth and of each
architecture's means are spooled to an unnamed temporary file (m doubles each per instant) and
the alignment's moments accumulated (`core.trajectory_blocks.Moments`, over the first
`align_first` matched instants), with the truth's spread. Second pass (`finish`): the spool read
back block by block, each architecture's positions aligned, APE and RPE (pairs carried across
blocks, `RpeTaker`) summed and spooled for their median (`select`), the recording's series
(APE, RPE, run 0's aligned path) decimated as the others (`core.decimate`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from fusionlog.core.decimate import TreeDecimator
from fusionlog.core.trajectory import Alignment, AlignmentError, fit_count, summary_entries
from fusionlog.core.trajectory_blocks import ErrorSums, Moments, RpeTaker, select
from fusionlog.driver.long_log import Spool, time_block
from fusionlog.errors import FusionlogError

__all__ = ["LongTrajectory"]


class LongTrajectory:
    """The trajectory metrics of `archs` (`part`: the evaluator's `TrajectoryPart`)."""

    def __init__(self, part: Any, archs: Sequence[str]) -> None:
        self.s, self.times, self.source = part.sc.trajectory, part.times, part.source
        self.names = [part.sc.state_names[i] for i in self.s.positions]
        self.archs, self.pos = list(archs), list(self.s.positions)
        m = self.m = len(self.pos)
        self.spool = Spool(m * (1 + len(self.archs)))
        self.moments = {a: Moments(m) for a in self.archs}
        self.first: dict[str, Any] = {}  # the first matched (p, g): ``origin``
        self.seen = dict.fromkeys(self.archs, 0)  # matched instants so far
        self.spread = Moments(m)  # the truth's positions (S_gp's diagonal: their spread)
        self.edges: list[tuple[int, int]] = []

    def add(self, k0: int, k1: int, truth: np.ndarray, means: dict[str, np.ndarray]) -> None:
        """A block: truth (1, w, n), each architecture's means (1, w, n)."""
        g = truth[0][:, self.pos]
        ps = [means[a][0][:, self.pos] for a in self.archs]
        self.spool.write(k0, np.concatenate([g, *ps], axis=1))
        self.edges.append((k0, k1))
        fine = g[np.isfinite(g).all(axis=1)]
        self.spread.add(fine, fine)
        first = self.s.align_first
        for a, p in zip(self.archs, ps, strict=True):
            ok = np.flatnonzero(np.isfinite(p).all(axis=1) & np.isfinite(g).all(axis=1))
            if len(ok) and a not in self.first:
                self.first[a] = (p[ok[0]], g[ok[0]])
            fit = ok if first is None else ok[: max(first - self.seen[a], 0)]
            self.moments[a].add(p[fit], g[fit])
            self.seen[a] += len(ok)

    def _alignment(self, a: str) -> Alignment:
        """Architecture a's alignment (`core.trajectory.align`'s rules, from the moments)."""
        mode, m = self.s.align, self.m
        if mode == "none":
            return Alignment.identity(m)
        fit_count(self.seen[a], mode, self.s.align_first)  # too few: AlignmentError
        if mode == "origin":
            p0, g0 = self.first[a]
            return Alignment(np.eye(m), g0 - p0, 1.0)
        return Alignment(*self.moments[a].fit(mode == "similarity"))

    def _blocks(self) -> Iterator[tuple[int, int, np.ndarray]]:
        for k0, k1 in self.edges:
            yield k0, k1, self.spool.read(k0, k1)

    def finish(self, b: int) -> tuple[dict[str, Any], dict[str, Any]]:
        """({arch: {"ape", "rpe"}} of summary.json, the recording's ``trajectory``), the
        recording's series decimated in buckets of `b` instants. The spool is closed."""
        try:
            return self._finish(b)
        finally:
            self.spool.close()

    def _finish(self, b: int) -> tuple[dict[str, Any], dict[str, Any]]:
        m = self.m
        al: dict[str, Alignment] = {}
        for a in self.archs:
            try:
                al[a] = self._alignment(a)
            except AlignmentError as e:
                raise FusionlogError(f"{self.source}: {a}: {e}") from None
        takers = {a: RpeTaker(self.s.rpe_delta, self.s.rpe_unit) for a in self.archs}
        last: dict[str, Any] = {}  # each architecture's last instant taken: (aligned, truth)
        sums = {a: (ErrorSums(), ErrorSums()) for a in self.archs}
        errors = {a: (Spool(1), Spool(1)) for a in self.archs}
        tree = TreeDecimator(b)
        try:
            for k0, k1, rows in self._blocks():
                g, w = rows[:, :m], k1 - k0
                series: dict[str, Any] = {}
                aligned: dict[str, Any] = {}
                for i, a in enumerate(self.archs):
                    p = rows[:, m * (i + 1) : m * (i + 2)]
                    ok = np.flatnonzero(np.isfinite(p).all(axis=1) & np.isfinite(g).all(axis=1))
                    A = al[a]
                    x = A.scale * np.einsum("ij,kj->ki", A.rotation, p[ok]) + A.translation
                    ape = np.linalg.norm(x - g[ok], axis=1)
                    j = takers[a].take(x, self.times[k0:k1][ok])
                    xs, gs = x[j], g[ok][j]
                    if a in last and len(j):
                        xs, gs = np.vstack([last[a][0], xs]), np.vstack([last[a][1], gs])
                    rpe = np.linalg.norm((xs[1:] - xs[:-1]) - (gs[1:] - gs[:-1]), axis=1)
                    if len(j):
                        last[a] = (x[j[-1:]], g[ok][j[-1:]])
                    at = ok[j[-len(rpe) :]] if len(rpe) else ok[:0]
                    for e, s, sp in zip((ape, rpe), sums[a], errors[a], strict=True):
                        s.add(e)
                        sp.write(s.n - len(e), e[:, None])
                    series[a] = {"ape": _at(w, ok, ape), "rpe": _at(w, at, rpe)}
                    aligned[a] = np.full((w, m), np.nan)
                    aligned[a][ok] = x
                tree.add({"series": series, "aligned": aligned})
            entries = {}
            for a in self.archs:
                stats = [
                    s.statistics(_median(sp, s.n)) if s.n else None
                    for s, sp in zip(sums[a], errors[a], strict=True)
                ]
                nan = dict.fromkeys(("rmse", "mean", "median", "std", "min", "max"), np.nan)
                ape, rpe = summary_entries(
                    self.s, stats[0] or nan, stats[1] or nan, sums[a][1].n, al[a]
                )
                entries[a] = {"ape": ape, "rpe": rpe}
        finally:
            for pair in errors.values():
                for sp in pair:
                    sp.close()
        drawn = tree.result()
        out: dict[str, Any] = {"states": self.names, "positions": self.pos, **drawn}
        if self.spread.n:
            out["spread"] = np.diag(self.spread.Sgp) / self.spread.n
        return entries, out


def _at(w: int, idx: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(w,) NaN but v at idx."""
    out = np.full(w, np.nan)
    out[idx] = v
    return out


def _median(spool: Spool, n: int) -> float:
    """The median of the n errors spooled (np.median's: the mean of the two middle ones), read
    back a block of time at a time (its selection's arrays are of a block, not of the log)."""
    block = time_block()

    def blocks() -> Iterator[np.ndarray]:
        for a in range(0, n, block):
            yield spool.read(a, min(a + block, n))[:, 0]

    if n % 2:
        return select(blocks, n // 2)
    return (select(blocks, n // 2 - 1) + select(blocks, n // 2)) / 2
