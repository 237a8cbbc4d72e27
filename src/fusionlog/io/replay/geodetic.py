"""Geodetic fixes (WGS 84 latitude, longitude in degrees, altitude in metres) to local ENU metres.

A GNSS receiver reports where it is on the ellipsoid; a filter with a linear position model
needs metres. ``to_enu`` converts every fix with ``pymap3d.geodetic2enu`` about ``origin``
(default: the first fix in time order), so the first reading of a log without an origin is
(0, 0, 0). With two values (latitude, longitude) the fixes are taken at the origin's altitude
and only east and north are kept. The covariances are left as read: a NavSatFix's
``position_covariance`` is already in the ENU frame of the fix, in m² (REP 145), and over the
few kilometres of a log the tangent planes at the fix and at the origin agree to well under the
receiver's accuracy.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .series import Series, fail

__all__ = ["to_enu"]


def _check_degrees(source: Path, what: str, s: Series) -> None:
    """Latitudes within ±90, longitudes within ±180, block by block: the first reading
    outside (in time order) named, with their count."""
    d = s.rows.dtype["v"].shape[0]
    for col, name, bound in ((0, "latitude", 90.0), (1, "longitude", 180.0)):
        first, count, at = None, 0, 0
        for b in s.rows.blocks():
            bad = np.flatnonzero(np.abs(b["v"][:, col]) > bound)
            if bad.size and first is None:
                i = int(bad[0])
                first = (at + i, float(b["v"][i, col]), int(b["t"][i]))
            count, at = count + bad.size, at + len(b)
        if first is not None:
            i, v, t = first
            raise fail(
                source,
                what,
                f"geodetic: {name} {v:.10g} (reading {i + 1} in time order, "
                f"{t} ns) is outside ±{bound:g}: values must be degrees "
                f"[latitude, longitude{', altitude' if d == 3 else ''}]"
                + (f" ({count} readings)" if count > 1 else ""),
            )


def to_enu(
    source: Path, what: str, s: Series, origin: Sequence[float] | None
) -> tuple[Series, tuple[float, float, float]]:
    """The fixes of ``s`` as east, north[, up] metres about ``origin`` (lat, lon, alt), and the
    origin used. ``s.values`` has 2 (latitude, longitude) or 3 (and altitude) columns. The
    fixes are converted as they are read (`Rows.transform`), a block at a time."""
    d = s.rows.dtype["v"].shape[0]
    if d not in (2, 3):
        raise fail(
            source,
            what,
            f"geodetic: values has {d} fields; give [latitude, longitude] or "
            "[latitude, longitude, altitude]",
        )
    _check_degrees(source, what, s)
    if origin is None:
        first = s.rows.read(0, 1)["v"][0]
        origin = (float(first[0]), float(first[1]), float(first[2]) if d == 3 else 0.0)
    lat0, lon0, alt0 = (float(x) for x in origin)

    def enu(values: np.ndarray) -> np.ndarray:
        import pymap3d  # needed only for geodetic sensors

        alt = values[:, 2] if d == 3 else np.full(len(values), alt0)
        e, n, u = pymap3d.geodetic2enu(values[:, 0], values[:, 1], alt, lat0, lon0, alt0)
        return np.stack([e, n, u], axis=1)[:, :d]

    return Series.of_rows(s.rows.with_transform(enu), s.notes, s.recorded), (lat0, lon0, alt0)
