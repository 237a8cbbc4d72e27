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

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .series import Series, fail

__all__ = ["to_enu"]


def _check_degrees(source: Path, what: str, s: Series) -> None:
    lat, lon = s.values[:, 0], s.values[:, 1]
    for name, v, bound in (("latitude", lat, 90.0), ("longitude", lon, 180.0)):
        bad = np.flatnonzero(np.abs(v) > bound)
        if bad.size:
            i = int(bad[0])
            raise fail(
                source,
                what,
                f"geodetic: {name} {v[i]:.10g} (reading {i + 1} in time order, "
                f"{int(s.times_ns[i])} ns) is outside ±{bound:g}: values must be degrees "
                f"[latitude, longitude{', altitude' if s.values.shape[1] == 3 else ''}]"
                + (f" ({bad.size} readings)" if bad.size > 1 else ""),
            )


def to_enu(
    source: Path, what: str, s: Series, origin: Sequence[float] | None
) -> tuple[Series, tuple[float, float, float]]:
    """The fixes of ``s`` as east, north[, up] metres about ``origin`` (lat, lon, alt), and the
    origin used. ``s.values`` has 2 (latitude, longitude) or 3 (and altitude) columns."""
    import pymap3d  # needed only for geodetic sensors

    d = s.values.shape[1]
    if d not in (2, 3):
        raise fail(
            source,
            what,
            f"geodetic: values has {d} fields; give [latitude, longitude] or "
            "[latitude, longitude, altitude]",
        )
    _check_degrees(source, what, s)
    if origin is None:
        first = s.values[0]
        origin = (float(first[0]), float(first[1]), float(first[2]) if d == 3 else 0.0)
    lat0, lon0, alt0 = (float(x) for x in origin)
    alt = s.values[:, 2] if d == 3 else np.full(len(s.values), alt0)
    e, n, u = pymap3d.geodetic2enu(s.values[:, 0], s.values[:, 1], alt, lat0, lon0, alt0)
    enu = np.stack([e, n, u], axis=1)[:, :d]
    return dataclasses.replace(s, values=np.ascontiguousarray(enu)), (lat0, lon0, alt0)
