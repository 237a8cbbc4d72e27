"""Architecture names used on the CLI, in MCAP topics and in summaries (DESIGN.md contract)."""

from __future__ import annotations

#: Kalman-filter architectures of the Ajgl-Simandl-Dunik paper plus CI, the smoother and the
#: plain average of the local estimates (Gustafsson-Hendeby's "LS" fusion).
STATE_ARCHITECTURES: tuple[str, ...] = (
    "CKF",
    "HKF",
    "MSC-GMF",
    "MSC",
    "SKF",
    "CI",
    "FBS",
    "AVG",
)

#: The five architectures of the paper's Table I, in its column order.
PAPER_ARCHITECTURES: tuple[str, ...] = ("CKF", "HKF", "MSC-GMF", "MSC", "SKF")


def parse_arch(name: str, sensor_names: list[str] | tuple[str, ...]) -> tuple[str, str | None]:
    """Split an architecture name into (base, sensor); `SKF:<sensor>` picks the SKF's sensor.

    Raises ValueError with a readable reason for an unknown name or sensor.
    """
    base, _, sensor = name.partition(":")
    if base not in STATE_ARCHITECTURES:
        known = ", ".join(STATE_ARCHITECTURES)
        raise ValueError(f"unknown architecture {name!r} (known: {known}, SKF:<sensor>)")
    if sensor and base != "SKF":
        raise ValueError(f"architecture {name!r}: only SKF takes a sensor suffix")
    if base == "SKF":
        if not sensor_names:
            raise ValueError("SKF needs at least one sensor")
        if not sensor:
            return base, sensor_names[0]
        if sensor not in sensor_names:
            raise ValueError(
                f"architecture {name!r}: no sensor {sensor!r} (sensors: {', '.join(sensor_names)})"
            )
        return base, sensor
    return base, None
