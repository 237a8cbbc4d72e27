"""Model components (sensors, motion) and their registries: see `base`.

Importing this package registers the kinds it ships (`linear`); a new kind is a module here
with a class decorated by `register_sensor` / `register_motion`, imported below.
"""

from .base import (
    MOTION_KINDS,
    SENSOR_KINDS,
    MotionModel,
    NotLinear,
    SensorModel,
    register_motion,
    register_sensor,
)
from .linear import LinearMotion, LinearSensor

__all__ = [
    "MOTION_KINDS",
    "SENSOR_KINDS",
    "LinearMotion",
    "LinearSensor",
    "MotionModel",
    "NotLinear",
    "SensorModel",
    "register_motion",
    "register_sensor",
]
