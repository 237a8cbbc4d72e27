"""Model components (sensors, motion) and their registries: see `base`.

Importing this package registers the kinds it ships (`linear`; `range-bearing`, `range`,
`bearing` in `polar`; `coordinated-turn` in `turn`); a new kind is a module here
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
from .polar import BearingSensor, RangeBearingSensor, RangeSensor
from .turn import CoordinatedTurn

__all__ = [
    "BearingSensor",
    "CoordinatedTurn",
    "RangeBearingSensor",
    "RangeSensor",
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
