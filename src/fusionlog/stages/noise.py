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

__all__ = ["with_message_covariances"]


def with_message_covariances(system: System, log: McapFile) -> System:
    """`system` with the per-instant R of the log's sensor messages (itself when none has)."""
    covs = {}
    for j, sen in enumerate(system.sensors):
        topic = sensor_topic(sen.name)
        c = log.message_covariances(topic) if topic in log.topics else None
        if c is not None:
            covs[j] = c
    bad = [s.name for j, s in enumerate(system.sensors) if j not in covs and not _finite(s.R)]
    if bad:
        raise FusionlogError(
            f"{log.path}: sensor {bad[0]!r} has no R and its messages carry no covariance"
        )
    if not covs:
        return system
    sensors = list(system.sensors)
    for j, c in covs.items():
        if not _finite(sensors[j].R):
            sensors[j] = dataclasses.replace(sensors[j], R=nominal_R(c))
    nominal = dataclasses.replace(system, sensors=tuple(sensors))
    Rs = np.repeat(nominal.R[None], log.steps(), axis=0)
    for j, c in covs.items():
        sl = nominal.sensor_slices[j]
        have = np.isfinite(c).all(axis=(-2, -1))
        Rs[have, sl, sl] = c[have]
    return dataclasses.replace(nominal, Rs=Rs)


def _finite(a: np.ndarray) -> bool:
    return bool(np.isfinite(a).all())
