"""Trajectory metrics (`core.trajectory`) of one run handed over in blocks of time (issue 34: a
long log in memory that does not grow with its instants).

APE's alignment (Umeyama 1991) needs every matched instant, but only through their moments:
the means of the estimate's and the truth's positions, the estimate's variance and their
cross-covariance (eqs. 34-38), merged block by block (`Moments`: the pairwise update of Chan,
Golub and LeVeque, "Updating formulae and a pairwise algorithm for computing sample
variances", 1979, stable where raw sums of squares would cancel). A first pass accumulates them,
a second computes the aligned errors. RPE's pairs follow the matched sequence (`RpeTaker`
carries each rule's state into the next block). The errors' statistics: sums and extremes per
block (`ErrorSums`), the median by selection over the errors handed over again (`select`:
four passes over the 16-bit digits of their IEEE patterns, no more than a block in memory).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from .rpe_pairs import RpeTaker
from .trajectory import umeyama_moments

__all__ = ["ErrorSums", "Moments", "RpeTaker", "select"]


class Moments:
    """Count N, means of p and g (m,), S_pp = sum |p - mu_p|^2 and S_gp = sum (g - mu_g)(p -
    mu_p)^T of paired positions handed over in blocks (p, g (w, m))."""

    def __init__(self, m: int) -> None:
        self.n = 0
        self.mu_p, self.mu_g = np.zeros(m), np.zeros(m)
        self.Spp, self.Sgp = 0.0, np.zeros((m, m))

    def add(self, p: np.ndarray, g: np.ndarray) -> None:
        nb = len(p)
        if nb == 0:
            return
        mp, mg = p.mean(axis=0), g.mean(axis=0)
        dp, dg = p - mp, g - mg
        spp, sgp = float(np.einsum("ij,ij->", dp, dp)), dg.T @ dp
        if self.n == 0:
            self.n, self.mu_p, self.mu_g, self.Spp, self.Sgp = nb, mp, mg, spp, sgp
            return
        n = self.n + nb
        ep, eg = mp - self.mu_p, mg - self.mu_g
        f = self.n * nb / n
        self.Spp += spp + f * float(ep @ ep)
        self.Sgp = self.Sgp + sgp + f * np.outer(eg, ep)
        self.mu_p = self.mu_p + ep * (nb / n)
        self.mu_g = self.mu_g + eg * (nb / n)
        self.n = n

    def fit(self, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
        """Umeyama's rotation, translation and scale (`umeyama_moments`)."""
        n = self.n
        rot, t, c = umeyama_moments(
            self.mu_p[None], self.mu_g[None], np.array([self.Spp / n]), (self.Sgp / n)[None], n,
            with_scale,
        )  # fmt: skip
        return rot[0], t[0], float(c[0])


class ErrorSums:
    """Count, mean and sum of squared deviations (merged as `Moments`), sum of squares,
    minimum and maximum of errors handed over in blocks: rmse, mean, std (population), min
    and max of `core.trajectory.error_statistics` (the median: `select`)."""

    def __init__(self) -> None:
        self.n, self.mean, self.M2, self.sq = 0, 0.0, 0.0, 0.0
        self.min, self.max = np.inf, -np.inf

    def add(self, e: np.ndarray) -> None:
        nb = len(e)
        if nb == 0:
            return
        mb = float(np.mean(e))
        m2 = float(np.sum((e - mb) ** 2))
        n = self.n + nb
        d = mb - self.mean
        self.M2 += m2 + d * d * self.n * nb / n
        self.mean += d * nb / n
        self.n = n
        self.sq += float(np.sum(e * e))
        self.min, self.max = min(self.min, float(e.min())), max(self.max, float(e.max()))

    def statistics(self, median: float) -> dict[str, float]:
        n = self.n
        return {
            "rmse": float(np.sqrt(self.sq / n)),
            "mean": self.mean,
            "median": median,
            "std": float(np.sqrt(self.M2 / n)),
            "min": self.min,
            "max": self.max,
        }


def select(blocks: Callable[[], Iterable[np.ndarray]], rank: int) -> float:
    """The `rank`-th smallest (from 0) of nonnegative doubles handed over in blocks, each call
    of `blocks` handing them all again: four passes, each counting the next 16 bits of the IEEE
    patterns (in the order of the values, for nonnegative doubles) of those whose higher bits
    are the ones found so far."""
    prefix, r = 0, rank
    for shift in (48, 32, 16, 0):
        counts = np.zeros(1 << 16, dtype=np.int64)
        for e in blocks():
            u = np.ascontiguousarray(e, dtype="<f8").view(np.uint64)
            if shift < 48:
                u = u[(u >> np.uint64(shift + 16)) == np.uint64(prefix)]
            digit = ((u >> np.uint64(shift)) & np.uint64(0xFFFF)).astype(np.intp)
            counts += np.bincount(digit, minlength=1 << 16)
        c = np.cumsum(counts)
        d = int(np.searchsorted(c, r, side="right"))
        r -= int(c[d - 1]) if d else 0
        prefix = (prefix << 16) | d
    return float(np.array([prefix], dtype=np.uint64).view(np.float64)[0])
