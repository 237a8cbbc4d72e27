"""Trajectory files other tools read (DESIGN.md "Trajectory metrics", ``fusionlog export``).

* **TUM** (Sturm et al. 2012, the TUM RGB-D benchmark): ``time tx ty tz qx qy qz qw`` per line,
  space-separated, time in seconds; the orientation is the identity (0 0 0 1): fusionlog
  estimates positions.
* **KITTI** (Geiger et al. 2012, odometry benchmark): the 3 × 4 matrix [R | t] of each pose,
  row-major, 12 numbers per line, no time; R = I.
* **CSV**: a header, then ``time`` and every state with its standard deviation
  (``<state>,<state>_std``; the truth has no standard deviation).

Times are the recording's clock, written exactly from its nanoseconds (never through a float);
values as Python's ``repr`` of the double: the shortest decimal that reads back to the very same
number (17 significant digits where needed, never fewer than the value has). Rows whose
position is not finite (an estimate not yet defined, an instant without truth) are left out of
TUM and KITTI, which have no way to say "none"; CSV writes them as ``nan``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["FORMATS", "csv_text", "kitti_text", "seconds_text", "tum_text"]

FORMATS = ("tum", "kitti", "csv")


def seconds_text(ns: int) -> str:
    """Whole nanoseconds as exact decimal seconds: 1403636580838555574 -> 1403636580.838555574."""
    sign = "-" if ns < 0 else ""
    q, r = divmod(abs(int(ns)), 1_000_000_000)
    return f"{sign}{q}.{r:09d}"


def _num(x: float) -> str:
    return repr(float(x))  # shortest round-trip; "nan" / "inf" for the non-finite


def _rows(positions: np.ndarray) -> np.ndarray:
    return np.flatnonzero(np.isfinite(positions).all(axis=1))


def tum_text(stamps_ns: Sequence[int], positions: np.ndarray) -> str:
    """TUM lines of the positions (N, 3) at the stamps (N,) ns."""
    lines = [
        " ".join([seconds_text(stamps_ns[k]), *map(_num, positions[k]), "0.0 0.0 0.0 1.0"])
        for k in _rows(positions)
    ]
    return "".join(line + "\n" for line in lines)


def kitti_text(positions: np.ndarray) -> str:
    """KITTI lines of the positions (N, 3): [I | p] row-major."""
    out = []
    for k in _rows(positions):
        x, y, z = map(_num, positions[k])
        out.append(f"1.0 0.0 0.0 {x} 0.0 1.0 0.0 {y} 0.0 0.0 1.0 {z}\n")
    return "".join(out)


def csv_text(
    stamps_ns: Sequence[int],
    names: Sequence[str],
    values: np.ndarray,
    std: np.ndarray | None,
) -> str:
    """CSV of every state (N, n) (and its standard deviation (N, n) where given)."""
    header = ["time"]
    for s in names:
        header += [s] + ([f"{s}_std"] if std is not None else [])
    out = [",".join(header) + "\n"]
    for k in range(values.shape[0]):
        cells = [seconds_text(stamps_ns[k])]
        for i in range(values.shape[1]):
            cells.append(_num(values[k, i]))
            if std is not None:
                cells.append(_num(std[k, i]))
        out.append(",".join(cells) + "\n")
    return "".join(out)
