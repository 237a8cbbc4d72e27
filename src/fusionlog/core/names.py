"""Architecture names used on the CLI, in MCAP topics and in summaries (DESIGN.md contract).

The names are those of the architecture registry (`core.architectures.registry`): one list,
so that a name parses exactly when a definition is registered for it.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..errors import FusionlogError
from .architectures.registry import STATE_ARCHITECTURES, parse_arch
from .model import System

#: The five architectures of the paper's Table I, in its column order.
PAPER_ARCHITECTURES: tuple[str, ...] = ("CKF", "HKF", "MSC-GMF", "MSC", "SKF")

__all__ = [
    "PAPER_ARCHITECTURES",
    "STATE_ARCHITECTURES",
    "check_architectures",
    "known_arch",
    "parse_arch",
]


def known_arch(arch: str, system: System) -> bool:
    """Whether `arch` names an architecture of this system (`parse_arch` accepts it)."""
    try:
        parse_arch(arch, [s.name for s in system.sensors])
    except ValueError:
        return False
    return True


def check_architectures(names: Sequence[str], system: System, where: str) -> list[str]:
    """The architecture names, checked against the system's sensors (duplicates dropped, in
    order); FusionlogError "<where>: <reason>" for the first unknown one. The one check every
    command and the Python API make."""
    for a in names:
        try:
            parse_arch(a, [s.name for s in system.sensors])
        except ValueError as e:
            raise FusionlogError(f"{where}: {e}") from e
    return list(dict.fromkeys(names))
