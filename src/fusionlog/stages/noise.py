"""The measurement noise of a log whose messages carry their own covariance.

An imported recording (`fusionlog import`) writes each message's covariance where R varies from
message to message (the Block's optional ``covariance``). The filters then use, at each instant,
the stacked R of eq. (31) with those blocks in place of the sensors' nominal R
(`core.model.System.Rs`); a sensor given by its messages alone (no R in the replay file) takes
the mean of its messages' covariances as its nominal R.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fusionlog.core.model import System, nominal_R
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.topics import sensor_topic

__all__ = ["with_covariances", "with_message_covariances"]


def with_message_covariances(system: System, log: McapFile) -> System:
    """`system` with the per-instant R of the log's sensor messages (itself when none has)."""
    topics = {sen.name: sensor_topic(sen.name) for sen in system.sensors}
    found = log.message_covariances_of([t for t in topics.values() if t in log.topics])
    covs = {name: c for name, t in topics.items() if (c := found.get(t)) is not None}
    return with_covariances(system, covs, log.steps(), str(log.path))


def with_covariances(
    system: System, covs: dict[str, np.ndarray], instants: int, source: str
) -> System:
    """`system` with the per-instant stacked R (`System.Rs`, eq. 31) of its sensors' own
    covariances `covs[name]` ((K+1, m, m), NaN at instants without one) over `instants` K+1
    (itself when there are none); a sensor without an R of its own takes `nominal_R`."""
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
            sensors[j] = dataclasses.replace(sen, R=nominal_R(covs[sen.name]))
    nominal = dataclasses.replace(system, sensors=tuple(sensors))
    Rs = np.repeat(nominal.R[None], instants, axis=0)
    for sen, sl in zip(nominal.sensors, nominal.sensor_slices, strict=True):
        if sen.name in covs:
            c = covs[sen.name]
            have = np.isfinite(c).all(axis=(-2, -1))
            Rs[have, sl, sl] = c[have]
    return dataclasses.replace(nominal, Rs=Rs)


def _finite(a: np.ndarray) -> bool:
    return bool(np.isfinite(a).all())
