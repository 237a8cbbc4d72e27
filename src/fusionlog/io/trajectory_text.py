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
from pathlib import Path

import numpy as np

__all__ = ["FORMATS", "csv_text", "first_log_time", "kitti_text", "seconds_text", "tum_text"]

FORMATS = ("tum", "kitti", "csv")


def seconds_text(ns: int) -> str:
    """Whole nanoseconds as exact decimal seconds: 1403636580838555574 -> 1403636580.838555574."""
    sign = "-" if ns < 0 else ""
    q, r = divmod(abs(int(ns)), 1_000_000_000)
    return f"{sign}{q}.{r:09d}"


def first_log_time(path: Path) -> int:
    """The smallest log_time (ns) of a fusionlog MCAP file's messages: its first instant's,
    the origin of the recording's clock (0 for a simulation), from the summary's statistics
    (the first message read where there are none). 0 where the file cannot tell (damaged: the
    caller's own reading reports it, with the file's name)."""
    from mcap.reader import make_reader

    from fusionlog.inputs import check_input

    check_input(path)  # a FIFO or a device would block
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is not None and summary.statistics is not None:
                return int(summary.statistics.message_start_time)
            for _schema, _channel, msg in reader.iter_messages(log_time_order=False):
                return int(msg.log_time)
    except Exception:  # noqa: BLE001 - damaged or not MCAP: the stage's reader says so
        return 0
    return 0


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
