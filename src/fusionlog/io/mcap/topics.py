"""The topic names of fusionlog's logs (DESIGN.md "MCAP files"), spelled once.

Sensors file: ``/truth`` and ``/sensors/<sensor name>``; estimates file:
``/estimates/<ARCH>``.
"""

from __future__ import annotations

__all__ = [
    "ESTIMATES_PREFIX",
    "SENSORS_PREFIX",
    "TRUTH",
    "arch_of",
    "estimates_topic",
    "sensor_topic",
]

TRUTH = "/truth"
SENSORS_PREFIX = "/sensors/"
ESTIMATES_PREFIX = "/estimates/"


def sensor_topic(name: str) -> str:
    """The topic of sensor `name`'s readings."""
    return SENSORS_PREFIX + name


def estimates_topic(arch: str) -> str:
    """The topic of architecture `arch`'s estimates."""
    return ESTIMATES_PREFIX + arch


def arch_of(topic: str) -> str:
    """The architecture of an estimates topic."""
    return topic.removeprefix(ESTIMATES_PREFIX)
