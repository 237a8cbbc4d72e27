"""Nonlinear sensors and motion (DESIGN.md, "Nonlinear sensors and motion"): measurement and motion
models with analytic Jacobians (`measurement`, `motion`), the EKF and UKF local filters batched
over runs (`local`), every fusion architecture with them (`architectures`), and the posterior
Cramér-Rao bound that stands beside the Monte Carlo values where no exact analysis exists
(`pcrb`). Modules are imported on use; this package imports nothing heavy.
"""

from .architectures import Track, estimate
from .local import UkfParams, predict, sigma_points, update, update_ekf, update_ukf
from .measurement import POLAR_KINDS, Linear, Polar, Stacked, wrap, wrap_angles
from .motion import CoordinatedTurn, LinearMotion
from .pcrb import PcrbAccumulator, pcrb_summary
from .system import FILTERS, NonlinearSystem

__all__ = [
    "FILTERS",
    "POLAR_KINDS",
    "CoordinatedTurn",
    "Linear",
    "LinearMotion",
    "NonlinearSystem",
    "PcrbAccumulator",
    "Polar",
    "Stacked",
    "Track",
    "UkfParams",
    "estimate",
    "pcrb_summary",
    "predict",
    "sigma_points",
    "update",
    "update_ekf",
    "update_ukf",
    "wrap",
    "wrap_angles",
]
