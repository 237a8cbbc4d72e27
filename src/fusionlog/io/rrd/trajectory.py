"""The trajectory metrics in the recording (DESIGN.md "Trajectory metrics"): APE and RPE over
time, and the first run's estimates after the alignment beside the raw ones.

=============================================  ============================================
``metrics/ape/<ARCH>``                          APE at each instant (run average, metres)
``metrics/rpe/<ARCH>``                          RPE of the pairs ending at each instant
``aligned/truth``, ``aligned/<ARCH>``           run 0's truth and aligned estimates in the
                                                plane of two position states (of three, the
                                                two along which the truth spreads most)
``raw/truth``, ``raw/<ARCH>``                   the same, as estimated (not aligned)
=============================================  ============================================

Two tabs, "Trajectory: aligned" and "Trajectory: raw", toggle between the aligned and the raw
paths; "APE, RPE" holds the time series.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from .stream import SeriesWriter, entity_path
from .style import TRUTH_COLOR, arch_color, arch_width
from .views import query, time_series_view

__all__ = ["trajectory_tabs", "write_trajectory"]

_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _path(xy: np.ndarray) -> np.ndarray:
    """The drawable points: finite and within float32 (Rerun's 2-D positions)."""
    return xy[(np.isfinite(xy) & (np.abs(xy) <= _FLOAT32_MAX)).all(axis=1)]


def _plane(traj: Mapping[str, Any]) -> list[int]:
    """Columns (of the position states) drawn: of three, the two along which run 0's truth
    spreads most (a camera frame's ground plane is x-z), in order; else those there are."""
    m = len(traj["states"])
    spread = traj.get("spread")
    if m <= 2 or spread is None:
        return list(range(min(2, m)))
    return sorted(int(i) for i in np.argsort(-np.asarray(spread, dtype=float), kind="stable")[:2])


def write_trajectory(
    w: SeriesWriter, traj: Mapping[str, Any], samples: Mapping[int, Any], positions: list[int]
) -> None:
    """The series and the two sets of paths (`positions`: the position states' indices in the
    state, to read run 0's truth and raw estimates from the sample runs)."""
    for arch, s in traj["series"].items():
        col, width = arch_color(arch), arch_width(arch)
        w.line(entity_path("metrics", "ape", arch), s["ape"], arch, col, width)
        w.line(entity_path("metrics", "rpe", arch), s["rpe"], arch, col, width)
    cols = _plane(traj)
    if len(cols) < 2 or 0 not in samples:
        return
    pos = [positions[c] for c in cols]
    truth, est = samples[0]
    t = _path(np.asarray(truth, dtype=float)[:, pos])
    for root in ("aligned", "raw"):
        strip = rr.LineStrips2D([t], colors=[TRUTH_COLOR], radii=[-2.0], labels=["truth"])
        w.rec.log(entity_path(root, "truth"), strip, static=True)
    for arch, aligned in traj["aligned"].items():
        paths = {"aligned": np.asarray(aligned, dtype=float)[:, cols]}
        if arch in est:
            paths["raw"] = np.asarray(est[arch][0], dtype=float)[:, pos]
        for root, xy in paths.items():
            strip = rr.LineStrips2D([_path(xy)], colors=[arch_color(arch)],
                                    radii=[-arch_width(arch)], labels=[arch])  # fmt: skip
            w.rec.log(entity_path(root, arch), strip, static=True)


def trajectory_tabs(traj: Mapping[str, Any] | None) -> list[Any]:
    """The blueprint's tabs: aligned and raw paths (a toggle), APE and RPE over time."""
    if not traj:
        return []
    names = traj["states"]
    tabs: list[Any] = []
    cols = _plane(traj)
    if len(cols) == 2:
        plane = f"({names[cols[0]]}, {names[cols[1]]})"
        tabs.append(rrb.Tabs(
            rrb.Spatial2DView(origin="/aligned", name=f"Trajectory: aligned {plane}"),
            rrb.Spatial2DView(origin="/raw", name=f"Trajectory: raw {plane}"),
            name="Trajectory: aligned / raw",
        ))  # fmt: skip
    tabs.append(rrb.Vertical(
        time_series_view("APE: ‖aligned estimate − truth‖ (m)", [query("metrics", "ape") + "/**"]),
        time_series_view("RPE: relative position error (m)", [query("metrics", "rpe") + "/**"],
                         legend=False),
        name="APE, RPE",
    ))  # fmt: skip
    return tabs
