"""Where a time-series legend hides the least of the curves.

A group of views that share their colours (Fig. 4: one view per state) needs the legend once.
The data are known when the recording is written, so the legend goes on the view and in the
corner where it covers the fewest curve points: with auto-fitted axes a view's data span the
unit square, x over the steps and y from the smallest to the largest value, and the legend is a
box in one corner whose size is estimated from its entries (the viewer draws it at a fixed
font size, so it takes a larger share of a smaller plot). The estimate need not be exact: a
corner that the curves leave empty stays empty for a somewhat larger box.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["CORNERS", "legend_box", "place_legend"]

#: Corners in order of preference when they hide equally little.
CORNERS = ("RightTop", "LeftTop", "RightBottom", "LeftBottom")
#: At most this many points per curve are checked (long series are thinned, short ones
#: interpolated so that a segment crossing the box counts).
_SAMPLES = 400


def legend_box(entries: int, longest_name: int, stacked: int, columns: int) -> tuple[float, float]:
    """(width, height) of a legend as fractions of its plot, for `entries` names of at most
    `longest_name` characters in a plot that is one of `stacked` rows and `columns` columns
    (measured in the viewer at 1920x1080: 7 entries take 0.37 of a plot's height with two
    rows, a 13-character name 0.21 of its width with three columns)."""
    height = (0.03 + 0.025 * entries) * stacked
    width = (0.06 + 0.011 * longest_name) * columns
    return min(width, 1.0), min(height, 1.0)


def _normalised(curves: Sequence[np.ndarray]) -> np.ndarray | None:
    """(N, 2) points of every curve in the unit square of the auto-fitted axes."""
    pts = []
    for y in curves:
        y = np.asarray(y, dtype=float)
        if y.size < 2:
            continue
        x = np.arange(y.size, dtype=float)
        if y.size < _SAMPLES:  # interpolate: a short segment may cross the box between points
            xs = np.linspace(0.0, y.size - 1.0, _SAMPLES)
            ys = np.interp(xs, x, y)  # NaN where a neighbour is NaN: dropped below
        else:
            idx = np.linspace(0, y.size - 1, _SAMPLES).round().astype(int)
            xs, ys = x[idx], y[idx]
        pts.append(np.stack([xs / (y.size - 1.0), ys], axis=-1))
    if not pts:
        return None
    p = np.concatenate(pts)
    p = p[np.isfinite(p).all(axis=1)]
    if p.shape[0] == 0:
        return None
    lo, hi = p[:, 1].min(), p[:, 1].max()
    p[:, 1] = (p[:, 1] - lo) / (hi - lo) if hi > lo else 0.5
    return p


def _hidden(p: np.ndarray, corner: str, box: tuple[float, float]) -> int:
    w, h = box
    in_x = p[:, 0] >= 1.0 - w if corner.startswith("Right") else p[:, 0] <= w
    in_y = p[:, 1] >= 1.0 - h if corner.endswith("Top") else p[:, 1] <= h
    return int(np.count_nonzero(in_x & in_y))


def place_legend(
    views: Sequence[Sequence[np.ndarray]], box: tuple[float, float]
) -> tuple[int, str]:
    """(view index, corner) where a legend of size `box` hides the fewest points of the views'
    curves (each view: its series over the steps, NaN where not logged). Ties go to the
    earlier view and the earlier corner of :data:`CORNERS`."""
    best = (0, CORNERS[0])
    best_hidden: int | None = None
    for i, curves in enumerate(views):
        p = _normalised(curves)
        if p is None:
            continue
        for corner in CORNERS:
            n = _hidden(p, corner, box)
            if best_hidden is None or n < best_hidden:
                best, best_hidden = (i, corner), n
    return best
