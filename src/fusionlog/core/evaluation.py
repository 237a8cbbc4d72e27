"""The result of evaluating a state scenario's estimates: a plain, typed value.

What the evaluator accumulated over every block, finished: the summary.json dict (DESIGN.md
"summary.json": MSE eq. 45, ANEES, DM eq. 47, the exact expected values, NIS), the per-step
series of each architecture (metrics per architecture and step, with their exact values), the
NEES band, a few sample runs and what the recording's other views draw. `io.rrd` writes it
(`write_evaluation`), `report` prints its summary (`format_table`); the Python API's
`fusionlog.Evaluation` adds those two as methods (`table`, `save`): the value here stays data.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Evaluation", "SampleRun"]

#: A sample run: its truth (K+1, n) and each architecture's (mean (K+1, n), std (K+1, n)).
SampleRun = tuple[np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]


@dataclass
class Evaluation:
    """An evaluation of M runs over instants k = 0..K.

    `summary`: the summary.json dict. `times` (K+1,) s. `series[arch]`: per-step arrays,
    "mse" (K+1, n), "trace", "nees", "dm" (K+1,) and, where an exact analysis exists,
    "expected_mse" (K+1, n), "expected_nees", "expected_dm" (K+1,); "bound" (K+1,) the bound
    check's lambda_max(P^-1 E[e e^T]) (`core.bound`), exact or a Monte Carlo estimate.
    `nees_bounds`: the two-sided chi-square band (lower, upper) of the run-averaged NEES,
    each (K+1,), at `confidence`. `samples[m]`: sample run m. `plane`: the 2-D state-plane
    view's data;
    `availability[sensor]` (K+1,) share of runs measured; `nis[arch][part]`: (run-averaged
    NIS, band lower, band upper); `traces[arch]` (K+1,) tr P without truth; `measured[state]
    [sensor]` (K+1,) the first sample run's direct readings; `properties`: the recording's
    (scenario text, provenance); `pcrb` (K+1, n) the PCRB on each state's MSE.
    `innovations[arch][sensor]` (K+1, r): a replayed log's normalised innovations, None for a
    scenario; with them the recording takes the layout of one log (`io.rrd.log_recording`).
    """

    summary: dict[str, Any]
    times: np.ndarray
    state_names: tuple[str, ...]
    confidence: float
    series: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    nees_bounds: tuple[np.ndarray, np.ndarray] | None = None
    samples: dict[int, SampleRun] = field(default_factory=dict)
    plane: Mapping[str, Any] | None = None
    availability: dict[str, np.ndarray] = field(default_factory=dict)
    nis: dict[str, Any] | None = None
    traces: dict[str, np.ndarray] | None = None
    measured: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)
    properties: dict[str, Any] = field(default_factory=dict)
    #: (K+1, n): the posterior Cramér-Rao bound on each state's MSE, where there is no exact
    #: analysis (nonlinear models; summary.json's "pcrb")
    pcrb: np.ndarray | None = None
    innovations: dict[str, dict[str, np.ndarray]] | None = None
    #: the filters' sensor names, in their order (the table names a single sensor's row)
    sensors: tuple[str, ...] = ()
    #: the trajectory metrics' recording (`stages.trajectory_eval.TrajectoryPart.recording`):
    #: position state names and indices, APE and RPE over time, run 0's aligned positions
    trajectory: dict[str, Any] | None = None
    #: a long log's series decimated (`core.decimate`): the instant of each point (`times` is
    #: then each point's time) and the recording's ``decimation`` property; None: every instant
    steps: np.ndarray | None = None
    decimation: dict[str, str] | None = None
    #: `[evaluate] full_resolution`: the recording keeps every instant of a long log
    full_resolution: bool = False
    #: a decimated log's sample-run bands {run: {arch: (lower, upper)}} (K+1, n) each,
    #: decimated as drawn (`core.decimate.with_derived`); None: mean ∓ 2 std
    bands: dict[int, dict[str, tuple[np.ndarray, np.ndarray]]] | None = None

    @property
    def architectures(self) -> list[str]:
        """The architectures evaluated, in the summary's order."""
        return list(self.summary["architectures"])
