"""Filters for nonlinear sensors and motion (DESIGN.md, "Nonlinear sensors and motion"): the EKF
and UKF local filters batched over runs (`local`), every fusion architecture with them
(`architectures`), late sensors under each policy (`late`: reprocess and neglect in every
architecture, `retrodict`: Al1 in the EKF), and the posterior Cramér-Rao bound that stands
beside the Monte Carlo values where no exact analysis exists (`pcrb`). The models themselves
(range-bearing sensors, the coordinated turn) are components in `core.models`.
"""

from .architectures import Track, estimate, estimate_steps
from .local import Stacked, UkfParams, predict, sigma_points, update, update_ekf, update_ukf
from .pcrb import PcrbAccumulator, pcrb_summary

__all__ = [
    "PcrbAccumulator",
    "Stacked",
    "Track",
    "UkfParams",
    "estimate",
    "estimate_steps",
    "pcrb_summary",
    "predict",
    "sigma_points",
    "update",
    "update_ekf",
    "update_ukf",
]
