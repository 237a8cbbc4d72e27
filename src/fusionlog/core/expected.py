"""What the exact analysis gives (`exact.analyse`, `exact_nodes`, `exact_replay`): the true
error statistics of an architecture per step, and the error that names a reported covariance
without them."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..errors import NumericalError


@dataclass
class Expected:
    """Exact expected error statistics per step k = 0..K (per run, with a leading run axis
    (M, ...), for a per-run plan)."""

    mse: np.ndarray  # (..., K+1, n, n): E[e e^T]
    bias: np.ndarray  # (..., K+1, n): E[e]
    P: np.ndarray  # (..., K+1, n, n): the covariance the architecture reports
    nees: np.ndarray  # (..., K+1): E[e^T P^-1 e] = tr(P^-1 E[e e^T])
    dm: np.ndarray  # (..., K+1): E[sqrt(e^T P^-1 e)], eq. (46)

    @property
    def mse_per_state(self) -> np.ndarray:
        """(..., K+1, n) expected MSE of each state component, the exact counterpart of eq. (44)."""
        return np.diagonal(self.mse, axis1=-2, axis2=-1).copy()

    @cached_property
    def bound(self) -> np.ndarray:
        """(..., K+1) lambda_max(P^-1 E[e e^T]), the bound check's ratio (`core.bound`; NaN
        where the architecture has no estimate)."""
        from .bound import bound_ratio

        return bound_ratio(self.P, self.mse)

    @property
    def defined(self) -> np.ndarray:
        """(..., K+1) where the architecture reports a covariance, i.e. has an estimate."""
        return np.isfinite(self.P).all(axis=(-2, -1))


def not_definite(where: str) -> NumericalError:
    """The error of a reported covariance without NEES or DM at `where` (a step, a run)."""
    return NumericalError(
        f"{where}: the reported covariance is not positive definite to working precision "
        "(no NEES or DM)"
    )
