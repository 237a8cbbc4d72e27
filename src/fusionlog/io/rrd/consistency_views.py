"""What a recording shows without ground truth: the NIS of every architecture with its chi-square
band, and when each sensor measured (the share of runs whose measurement arrived).

==============================================  ==========================================
``metrics/nis/<ARCH>/<part>``                   run-averaged NIS of the architecture's
                                                innovations (``<part>``: ``all`` for the
                                                centralised innovation, else a sensor)
``metrics/nis/<ARCH>/<part>/lower``, ``upper``  two-sided chi-square band of that average
``sensors/<sensor>/measured``                   share of the runs whose measurement arrived,
                                                at each instant the sensor measures
==============================================  ==========================================
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import IO

import numpy as np
import rerun.blueprint as rrb

from .stream import SeriesWriter, entity_path, recording_error
from .style import BOUND_COLOR, arch_color, arch_width, class_color
from .views import query, time_series_view

__all__ = ["NisSeries", "check_consistency", "consistency_views", "write_consistency"]

#: {ARCH: {part: (nis (K+1,), lower (K+1,), upper (K+1,))}}
NisSeries = Mapping[str, Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]]]


def check_consistency(
    file: IO[bytes], steps: int, nis: NisSeries, availability: Mapping[str, np.ndarray]
) -> None:
    for arch, parts in nis.items():
        for part, arrays in parts.items():
            if len(arrays) != 3 or any(np.shape(a) != (steps,) for a in arrays):
                raise recording_error(file, f"NIS of {arch}/{part}: three series of {steps}")
    for name, v in availability.items():
        if np.shape(v) != (steps,):
            raise recording_error(file, f"availability of {name}: shape {np.shape(v)}")


def write_consistency(
    w: SeriesWriter,
    nis: NisSeries,
    availability: Mapping[str, np.ndarray],
    confidence: float | None = None,
) -> None:
    # Every architecture's band of a part is named alike ("χ² 95% lower", as the NEES band),
    # so a view's legend lists the band once and the architectures after it: one entry per
    # band and architecture (21 for 7 architectures) pushed most architectures off the legend.
    band = f"χ² {confidence:.0%}" if confidence is not None else "χ²"
    for arch, parts in nis.items():
        col, width = arch_color(arch), arch_width(arch)
        for part, (mean, lower, upper) in parts.items():
            label = f"{arch} ({part})"
            w.line(entity_path("metrics", "nis", arch, part), mean, label, col, width)
            for side, arr in (("lower", lower), ("upper", upper)):
                p = entity_path("metrics", "nis", arch, part, side)
                w.line(p, arr, f"{band} {side}", BOUND_COLOR, 1.0)
    for i, (name, v) in enumerate(availability.items()):
        w.points(entity_path("sensors", name, "measured"), v, name, class_color(i))


def consistency_views(
    nis: NisSeries, availability: Mapping[str, np.ndarray], traces: bool = False
) -> list:
    """A "Consistency without truth" tab (one NIS view per architecture, and the trace of P
    when there is no truth to show it beside), and a "Sensors" tab (a view per sensor)."""
    tabs: list = []
    if nis:
        views = [
            time_series_view(
                f"NIS of {arch}, run average (grey: χ² band)",
                [query("metrics", "nis", arch) + "/**"],
                legend=len(parts) > 1,
            )
            for arch, parts in nis.items()
        ]
        if traces:
            views.append(time_series_view("trace of P", [query("metrics", "trace") + "/**"]))
        tabs.append(rrb.Grid(*views, name="Consistency without truth"))
    if availability:
        # One view per sensor: without dropouts every share is 1, and in one view the sensor
        # drawn last hid the others' instants (coordinated_turn.toml's camera under the radar).
        views = [
            time_series_view(
                f"{name}: share of runs measured at each of its instants (1 = none lost)",
                [query("sensors", name) + "/**"],
                legend=False,
            )
            for name in availability
        ]
        tabs.append(rrb.Vertical(*views, name="Sensors"))
    return tabs
