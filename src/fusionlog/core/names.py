"""Architecture names used on the CLI, in MCAP topics and in summaries (DESIGN.md contract).

The names are those of the architecture registry (`core.architectures.registry`): one list,
so that a name parses exactly when a definition is registered for it.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..errors import FusionlogError
from .architectures.registry import STATE_ARCHITECTURES, definition, parse_arch
from .late_policy import late_refusal
from .model import System

#: The five architectures of the paper's Table I, in its column order.
PAPER_ARCHITECTURES: tuple[str, ...] = ("CKF", "HKF", "MSC-GMF", "MSC", "SKF")

__all__ = [
    "PAPER_ARCHITECTURES",
    "STATE_ARCHITECTURES",
    "check_architectures",
    "known_arch",
    "parse_arch",
    "parse_arch_of",
]


def parse_arch_of(arch: str, system: System) -> tuple[str, str | None]:
    """`parse_arch` on the system's sensors, and refused (ValueError) where the system's late
    sensors give the architecture no meaning or no plan (`core.late_policy.late_refusal`)."""
    out = parse_arch(arch, [s.name for s in system.sensors])
    why = late_refusal(system, definition(out[0]).locals, arch)
    if why is not None:
        raise ValueError(why)
    return out


def known_arch(arch: str, system: System) -> bool:
    """Whether `arch` names an architecture of this system (`parse_arch_of` accepts it)."""
    try:
        parse_arch_of(arch, system)
    except ValueError:
        return False
    return True


def check_architectures(names: Sequence[str], system: System, where: str) -> list[str]:
    """The architecture names, checked against the system's sensors (duplicates dropped, in
    order); FusionlogError "<where>: <reason>" for the first unknown one. The one check every
    command and the Python API make."""
    for a in names:
        try:
            parse_arch_of(a, system)
        except ValueError as e:
            raise FusionlogError(f"{where}: {e}") from e
    return list(dict.fromkeys(names))
