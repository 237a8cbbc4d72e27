"""The measurement noise of a log whose messages carry their own covariance.

An imported recording (`fusionlog import`) writes each message's covariance where R varies from
message to message (the Block's optional ``covariance``). The filters then use, at each instant,
the stacked R of eq. (31) with those blocks in place of the sensors' nominal R
(`core.model.System.Rs`); a sensor given by its messages alone (no R in the replay file) takes
the mean of its messages' covariances as its nominal R.

A long one-run log taken in blocks of time (issue 34) does not hold its K+1 stacked R (8 m^2
bytes an instant): its messages' covariances are read block of time by block
(`McapFile.covariance_blocks`) into an unnamed temporary file (`driver.long_log.Spool`), and
`System.Rs` is a `core.intervals.PerInstant` that stacks the R of the instants asked for from
it -- the same bits as the whole array (`stacked_R`, one rule for both).
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Sequence

import numpy as np

from fusionlog.core.intervals import PerInstant
from fusionlog.core.model import System, nominal_R
from fusionlog.driver.long_log import Spool, edges, time_block
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.topics import sensor_topic

__all__ = [
    "SpooledCovariances",
    "message_covariances",
    "stacked_R",
    "with_covariances",
    "with_message_covariances",
]


def stacked_R(R: np.ndarray, parts: Sequence[tuple[slice, np.ndarray]], w: int) -> np.ndarray:
    """The stacked R (w, m, m) of eq. (31) at w instants: the nominal `R` (m, m), with each
    sensor's block `sl` replaced by its message's covariance (`parts`: (sl, (w, d, d)), NaN
    where the instant has none)."""
    Rs = np.repeat(R[None], w, axis=0)
    for sl, c in parts:
        have = np.isfinite(c).all(axis=(-2, -1))
        Rs[have, sl, sl] = c[have]
    return Rs


class SpooledCovariances:
    """A one-run log's per-message covariances (NaN at instants without one) of its sensors
    that carry them, spooled block of time by block: `at[name]` = (first column, dim) of a
    sensor's d x d doubles in the spool's rows (one row an instant). The systems whose R it
    forms hold it as long as they like: the spool is closed when it is collected."""

    def __init__(self, spool: Spool, at: dict[str, tuple[int, int]], instants: int) -> None:
        self.spool, self.at, self.instants = spool, at, instants
        weakref.finalize(self, spool.close)

    def __contains__(self, name: str) -> bool:
        return name in self.at

    def __bool__(self) -> bool:
        return bool(self.at)

    def read(self, name: str, k0: int, k1: int, rows: np.ndarray | None = None) -> np.ndarray:
        """The sensor's covariances at instants k0..k1-1 (k1 - k0, d, d) (of the spool's rows
        there, when read already)."""
        o, d = self.at[name]
        rows = self.spool.read(k0, k1) if rows is None else rows
        return rows[:, o : o + d * d].reshape(-1, d, d)


class _StackedR:
    """The source of a `PerInstant` `System.Rs`: the stacked R of instants k0..k1-1 formed
    from a `SpooledCovariances` (`stacked_R`)."""

    def __init__(self, covs: SpooledCovariances, system: System) -> None:
        self.covs, self.R = covs, system.R
        self.parts = [
            (s.name, sl)
            for s, sl in zip(system.sensors, system.sensor_slices, strict=True)
            if s.name in covs
        ]
        where = tuple((name, sl.start, sl.stop) for name, sl in self.parts)
        self.key = (id(covs), self.R.tobytes(), self.R.shape, where)
        self.cached = None  # `PerInstant`'s stretch

    def __len__(self) -> int:
        return self.covs.instants

    def form(self, k0: int, k1: int) -> np.ndarray:
        rows = self.covs.spool.read(k0, k1)
        parts = [(sl, self.covs.read(name, k0, k1, rows)) for name, sl in self.parts]
        return stacked_R(self.R, parts, k1 - k0)


def message_covariances(
    names: Sequence[str], log: McapFile, blocked: bool = False
) -> dict[str, np.ndarray] | SpooledCovariances:
    """The per-message covariances (K+1, d, d) of the log's sensors `names` that carry them
    (`McapFile.message_covariances_of`), or, `blocked`, spooled block of time by block."""
    topics = {name: sensor_topic(name) for name in dict.fromkeys(names)}
    topics = {name: t for name, t in topics.items() if t in log.topics}
    if not blocked:
        found = log.message_covariances_of(list(topics.values()))
        return {name: c for name, t in topics.items() if (c := found.get(t)) is not None}
    names = list(topics)
    dims = [log.dim_of(topics[n]) for n in names]
    offsets = np.concatenate([[0], np.cumsum([d * d for d in dims])]).astype(int)
    carried: set[str] = set()
    spool: list[Spool] = []  # made once some topic carries one (before: no log has any)
    try:
        for k0, k1, got in log.covariance_blocks(list(topics.values()), time_block(), carried):
            if not spool and not carried:
                continue
            if not spool:  # the instants before had none: NaN rows
                spool.append(Spool(int(offsets[-1])))
                for a, b in edges(k0, time_block()):
                    spool[0].write(a, np.full((b - a, spool[0].width), np.nan))
            w = k1 - k0
            fill = [
                got[topics[n]].reshape(w, -1) if topics[n] in got else np.full((w, d * d), np.nan)
                for n, d in zip(names, dims, strict=True)
            ]
            spool[0].write(k0, np.concatenate(fill, axis=1))
    except BaseException:
        for sp in spool:
            sp.close()
        raise
    at = {n: (int(offsets[i]), dims[i]) for i, n in enumerate(names) if topics[n] in carried}
    if not spool:
        return {}
    return SpooledCovariances(spool[0], at, log.steps())


def with_message_covariances(
    system: System,
    log: McapFile,
    blocked: bool = False,
    covs: dict[str, np.ndarray] | SpooledCovariances | None = None,
) -> System:
    """`system` with the per-instant R of the log's sensor messages (itself when none has):
    whole, or (`blocked`) a `PerInstant` formed block by block from their spool; `covs`:
    `message_covariances` read already (the filter's and the truth's model share them)."""
    if covs is None:
        covs = message_covariances([s.name for s in system.sensors], log, blocked)
    return with_covariances(system, covs, log.steps(), str(log.path))


def with_covariances(
    system: System,
    covs: dict[str, np.ndarray] | SpooledCovariances,
    instants: int,
    source: str,
) -> System:
    """`system` with the per-instant stacked R (`System.Rs`, eq. 31) of its sensors' own
    covariances `covs[name]` ((K+1, m, m), NaN at instants without one; or spooled) over
    `instants` K+1 (itself when there are none); a sensor without an R of its own takes
    `nominal_R`."""
    bad = [s.name for s in system.sensors if s.name not in covs and not _finite(s.R)]
    if bad:
        raise FusionlogError(
            f"{source}: sensor {bad[0]!r} has no R and its messages carry no covariance"
        )
    if not covs:
        return system
    sensors = list(system.sensors)
    for j, sen in enumerate(sensors):
        if sen.name in covs and not _finite(sen.R):
            # (spooled: read whole, a sensor whose R the resolved scenario lacks; the import
            # records the nominal R, so an imported log never does)
            c = covs[sen.name] if isinstance(covs, dict) else covs.read(sen.name, 0, instants)
            sensors[j] = dataclasses.replace(sen, R=nominal_R(c))
    nominal = dataclasses.replace(system, sensors=tuple(sensors))
    if isinstance(covs, SpooledCovariances):
        return dataclasses.replace(nominal, Rs=PerInstant(_StackedR(covs, nominal)))
    parts = [
        (sl, covs[sen.name])
        for sen, sl in zip(nominal.sensors, nominal.sensor_slices, strict=True)
        if sen.name in covs
    ]
    return dataclasses.replace(nominal, Rs=stacked_R(nominal.R, parts, instants))


def _finite(a: np.ndarray) -> bool:
    return bool(np.isfinite(a).all())
