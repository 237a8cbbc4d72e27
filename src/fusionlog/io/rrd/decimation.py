"""Long logs in a recording that stays usable: what is kept at full resolution, what decimated.

No screen shows 10^6 points of a NIS or an innovation series: above `OVERVIEW_POINTS` instants
those series (every ``metrics/...``, ``innovations/...``, ``sensors/...``, the ±2σ bands) keep
every n-th of their logged values, n = ceil(instants / OVERVIEW_POINTS). What the user zooms
into keeps full resolution: the estimates' means, the truth and the sensors' readings of the
first run (``runs/0/<state>/<ARCH>/mean``, ``.../truth``, ``.../measured/...``), as long as
they fit `FULL_POINTS` values together; beyond that they too keep every m-th value, m as small
as fits. The recording says which in its ``decimation`` property (instants, the two strides,
the entity patterns of each).
"""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["FULL_POINTS", "OVERVIEW_POINTS", "decimation"]

#: Instants above which the overview series are decimated.
OVERVIEW_POINTS = 100_000
#: Values of the full-resolution series together, at most.
FULL_POINTS = 12_000_000


def _full(path: str) -> bool:
    parts = path.split("/")
    if parts[0] != "runs":
        return False
    return parts[-1] in ("mean", "truth") or (len(parts) >= 2 and parts[-2] == "measured")


def decimation(instants: int, full_series: int) -> tuple[Callable[[str], int] | None, dict]:
    """(stride of each entity path, the recording's ``decimation`` property), or (None, {})
    for a log short enough to keep everything; `full_series`: how many series are meant to
    keep full resolution."""
    if instants <= OVERVIEW_POINTS:
        return None, {}
    overview = math.ceil(instants / OVERVIEW_POINTS)
    full = max(1, math.ceil(full_series * instants / FULL_POINTS))

    def stride(path: str) -> int:
        return full if _full(path) else overview

    prop = {
        "instants": str(instants),
        "full_resolution": "runs/0/<state>/<ARCH>/mean, runs/0/<state>/truth, "
        "runs/0/<state>/measured/<sensor>: "
        + ("every instant" if full == 1 else f"every {full}th logged value (too many to keep)"),
        "decimated": f"every other series (metrics, NIS, innovations, bands, sensors): every "
        f"{overview}th logged value; summary.json has the values over every instant",
    }
    return stride, prop
