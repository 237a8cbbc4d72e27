"""Chi-square quantities of the consistency checks (Bar-Shalom, Li and Kirubarajan 2001, sec.
5.4): the two-sided band's quantiles of NEES and NIS and the expected Mahalanobis distance of a
consistent filter (the DM of eqs. 46-47), from scipy.special's routines."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["chi2_quantile", "expected_mahalanobis_consistent"]


def chi2_quantile(q: float | np.ndarray, dof: float | np.ndarray) -> np.ndarray:
    """Chi-square quantile, `scipy.stats.chi2.ppf(q, dof)`'s routine without scipy.stats (0.5 s);
    scipy.special (0.25 s) imported here: a Dask worker only sums, and never needs it."""
    from scipy.special import chdtri

    q, dof = np.asarray(q, dtype=float), np.asarray(dof, dtype=float)
    if q.ndim or dof.size <= 16:
        return chdtri(dof, 1.0 - q)
    # a long log's band has one degree of freedom per instant, nearly all equal: each distinct
    # one once (chdtri's iteration costs ~1 us an element), the same values
    values, inverse = np.unique(dof, return_inverse=True)
    return chdtri(values, 1.0 - q)[inverse.reshape(dof.shape)]


def expected_mahalanobis_consistent(n: int) -> float:
    """E[sqrt(chi2_n)] = sqrt(2) Gamma((n+1)/2) / Gamma(n/2): the DM of a consistent filter."""
    from scipy.special import gammaln  # (see chi2_quantile)

    return math.sqrt(2.0) * math.exp(gammaln((n + 1) / 2.0) - gammaln(n / 2.0))
