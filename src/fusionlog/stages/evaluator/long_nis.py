"""NIS, whiteness, availability and the first run's readings of a long one-run log, block of time
by block (issue 34): what `NisPart` accumulates over the whole log, here with nothing of the
size of the log kept.

An instant's innovation needs the estimate of the instant before (the prediction x_k^- = F x_{k-1},
`core.nis`): each block is handed to `NisAccumulator` with the previous block's last instant in
front, whose own (meaningless) values are dropped. FBS's innovations are its forward filter's,
the centralised KF, run here block by block from its short plans (`SteadyLog`). The summary
sums over instants (NIS, degrees of freedom, instants inside the band) and the whiteness from
lagged sums (`core.nis.WhitenessSums`) are those of the whole log.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fusionlog.core.architectures.long_log import SteadyLog
from fusionlog.core.architectures.replay_blocks import ReplayBlocks, system_window
from fusionlog.core.nis import WhitenessSums

from ..consistency import NisAccumulator, availability
from .nis_part import NisPart

__all__ = ["LongNis"]


def _cat(prev: Any, cur: Any, axis: int) -> Any:
    return cur if prev is None else np.concatenate([prev, cur], axis=axis)


class LongNis:
    """The blocks of one log for `part` (the evaluator's `NisPart`: its system, sensors and
    schedule); `forward` (a smoother's innovations): the centralised KF's short plans, or a
    replay's CKF carried block to block, or the name of the CKF among the estimates a replay
    hands over (the same filter on the same readings: nothing recomputed), or None."""

    def __init__(
        self, part: NisPart, forward: SteadyLog | ReplayBlocks | str | None, ckf: str
    ) -> None:
        self.part, self.forward, self.ckf = part, forward, ckf
        self.archs = part.archs
        self.prev: dict[str, Any] = {}  # each architecture's (mean, cov) of the last instant
        self.zprev: np.ndarray | None = None
        self.fprev: Any = None
        self.sums: dict[tuple[str, str], np.ndarray] = {}  # NIS, count, dof, inside, instants
        self.white: dict[tuple[str, str], WhitenessSums] = {}

    def add(
        self, k0: int, k1: int, sensors: dict[str, np.ndarray], estimates: dict[str, Any]
    ) -> dict[str, Any]:
        """One block's series (for the recording's decimation) from its readings and estimates."""
        p, fs = self.part, self.part.system
        out: dict[str, Any] = {"availability": {}}
        for s, t in zip(fs.sensors, p.topics, strict=True):
            got = (~np.isnan(sensors[t]).any(axis=-1)).sum(axis=0)
            out["availability"][s.name] = availability(got, p.scheduled[s.name][k0:k1], 1)
        if not self.archs:
            return out
        z = np.concatenate([sensors[t] for t in p.topics], axis=-1)
        cut = 0 if self.zprev is None else 1
        ests = {}
        for a in self.archs:
            mean, cov = estimates[a]
            prev = self.prev.get(a, (None, None))
            # instants on axis -3: shared (K, n, n) or per run (M, K, n, n), as an EKF's may be
            ests[a] = (_cat(prev[0], mean, 1), _cat(prev[1], cov, -3))
            self.prev[a] = (mean[:, -1:], cov[..., -1:, :, :])
        fwd = None
        if isinstance(self.forward, str):  # a replay's CKF among the estimates: the same filter
            f = estimates[self.forward]
        elif isinstance(self.forward, ReplayBlocks):  # a replay's forward CKF, carried
            e = self.forward.estimates(k0, k1, z[0], None)[self.ckf]
            f = (e.mean, e.cov)
        elif self.forward is not None:
            f = (self.forward.forward(self.ckf, z, k0, None), self.forward.cov(self.ckf, k0, k1))
        if self.forward is not None:
            prev = self.fprev or (None, None)
            fwd = (_cat(prev[0], f[0], 1), _cat(prev[1], f[1], 0))
            self.fprev = (f[0][:, -1:], f[1][-1:])
        # the system on the window's instants (a replay's per-message R, irregular intervals)
        acc = NisAccumulator(system_window(fs, k0 - cut, k1, False), self.archs, k1 - k0 + cut)
        acc.add(_cat(self.zprev, z, 1), ests, forward=fwd)
        self.zprev = z[:, -1:]
        series = acc.series(p.confidence)
        first = acc.first_run()
        out["nis"], out["innovations"] = {}, {}
        for (a, part), total in acc.sum.items():
            mean, lo, hi = (v[cut:] for v in series[a][part])
            count, dof = acc.count[(a, part)][cut:], acc.dof[(a, part)][cut:]
            have = count > 0
            inside = ((mean >= lo) & (mean <= hi))[have].sum()
            add = [total[cut:][have].sum(), count[have].sum(), dof[have].sum(), inside, have.sum()]
            self.sums[(a, part)] = self.sums.get((a, part), 0.0) + np.array(add, dtype=float)
            out["nis"].setdefault(a, {})[part] = (mean, lo, hi)
            if a in first:
                normalised = first[a][part][cut:]
                out["innovations"].setdefault(a, {})[part] = normalised
                key = (a, part)
                if key not in self.white:
                    self.white[key] = WhitenessSums(normalised.shape[-1])
                self.white[key].add(normalised)
        out["measured"] = self._measured(sensors)
        return out

    def _measured(self, sensors: dict[str, np.ndarray]) -> dict[int, dict[str, np.ndarray]]:
        """The first run's readings of a state a sensor measures directly (as `NisPart`)."""
        fs, out = self.part.system, {}
        H = fs.linear_measurement() if fs.linear else None
        for s, t, sl in zip(fs.sensors, self.part.topics, fs.sensor_slices, strict=True):
            for row, h in enumerate(H[sl] if H is not None else ()):
                if np.count_nonzero(h) == 1 and h.max() == 1.0:
                    out.setdefault(int(np.argmax(h)), {})[s.name] = sensors[t][0, :, row]
        return out

    def summary(self) -> dict[str, Any]:
        """Per architecture its `nis` entry (as `NisAccumulator.summary`)."""
        out: dict[str, Any] = {}
        for a in self.archs:
            entries = {}
            for (b, part), (total, count, dof, inside, have) in self.sums.items():
                if b != a:
                    continue
                nan = float("nan")
                entries[part] = {
                    "mean": total / count if count else nan,
                    "fraction_inside": inside / have if have else nan,
                    "dof": dof / count if count else nan,
                }
                white = self.white.get((a, part), WhitenessSums(1)).result()
                entries[part] |= {f"whiteness_{k}": float(v) for k, v in white.items()}
            out[a] = entries[next(iter(entries))] if len(entries) == 1 else entries
        return out
