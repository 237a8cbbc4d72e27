"""The rules that pick the instants of RPE's pairs (`core.trajectory`, DESIGN.md "Trajectory
metrics": every delta frames, metres of path, or seconds), for a matched sequence handed over
whole or in blocks of time (`core.trajectory_blocks`): one place for both, with the state a
rule carries from one block to the next."""

from __future__ import annotations

import numpy as np

__all__ = ["RPE_UNITS", "TIME_TOL", "RpeTaker"]

RPE_UNITS = ("frames", "m", "s")
#: Tolerance of the seconds rule of the RPE pairs: the recording's clock is in nanoseconds.
TIME_TOL = 1e-9


class RpeTaker:
    """The instants of a matched sequence an RPE pair ends or starts at (`rpe_pairs`' rules),
    the sequence handed over in order, in one piece or in blocks of time: what the rule carries
    from one block to the next (instants seen; the path since the last instant taken and the
    last position; the time the next one must reach) is kept here."""

    def __init__(self, delta: float, unit: str) -> None:
        if unit not in RPE_UNITS:
            raise ValueError(f"unknown RPE unit {unit!r}")
        self.delta, self.unit = delta, unit
        self.seen, self.path = 0, 0.0
        self.last: np.ndarray | None = None  # ``m``: the last position before the block
        self.until: float | None = None  # ``s``: the time the next instant taken reaches

    def take(self, positions: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Indices (into the block) of the instants taken among positions (N, m), times (N,)."""
        n, delta = positions.shape[0], self.delta
        if self.unit == "frames":
            ids = np.flatnonzero((self.seen + np.arange(n)) % int(delta) == 0)
        elif self.unit == "m":
            step = np.zeros(n)
            if n > 1:
                step[1:] = np.linalg.norm(np.diff(positions, axis=0), axis=1)
            if n and self.last is not None:
                step[0] = np.linalg.norm(positions[:1] - self.last, axis=1)[0]
            taken, path = [0] if n and not self.seen else [], self.path
            for k in range(1 if taken else 0, n):  # a running sum reset at each instant taken
                path += step[k]
                if path >= delta:
                    taken.append(k)
                    path = 0.0
            self.path = path
            self.last = positions[-1:].copy() if n else self.last
            ids = np.array(taken, dtype=int)
        else:  # "s"
            taken = []
            k = 0 if self.until is None else int(np.searchsorted(times, self.until, "left"))
            while k < n:
                taken.append(k)
                self.until = times[k] + delta - TIME_TOL
                k = max(int(np.searchsorted(times, self.until, side="left")), k + 1)
            ids = np.array(taken, dtype=int)
        self.seen += n
        return ids
