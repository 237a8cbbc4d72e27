"""Colours and line widths shared by every recording: an architecture (and a class of an
identity scenario) has the same colour in every plot of every recording, whatever the order or
the number of the architectures shown."""

from __future__ import annotations

import zlib
from collections.abc import Sequence

from fusionlog.core.architectures.registry import REGISTRY

__all__ = [
    "BOUND_COLOR",
    "CKF",
    "INPUT_COLOR",
    "TRUTH_COLOR",
    "arch_color",
    "arch_width",
    "class_color",
    "lighter",
]

#: Stable colours (Tableau 10) of the identity architectures; a state architecture's is its
#: definition's (`core.architectures.definition`), or, without one, a hash of its name.
_IDENTITY: dict[str, tuple[int, int, int]] = {
    "BAYES": (188, 189, 34),
    "DS": (23, 190, 207),
}
_EXTRA = [
    (174, 199, 232),
    (255, 187, 120),
    (152, 223, 138),
    (255, 152, 150),
    (197, 176, 213),
    (196, 156, 148),
    (247, 182, 210),
    (219, 219, 141),
    (158, 218, 229),
]
#: Per-class colours in identity sample-run views (distinct from the architecture colours).
_CLASS_COLORS = [
    (228, 26, 28),
    (55, 126, 184),
    (77, 175, 74),
    (152, 78, 163),
    (255, 127, 0),
    (166, 86, 40),
    (247, 129, 191),
    (153, 153, 153),
    (255, 217, 47),
    (102, 194, 165),
    (141, 160, 203),
    (231, 138, 195),
]
TRUTH_COLOR = (230, 230, 230)
BOUND_COLOR = (150, 150, 150)
INPUT_COLOR = (140, 140, 140)
CKF = "CKF"


def arch_color(arch: str) -> tuple[int, int, int]:
    """The fixed colour of an architecture in every plot (deterministic across runs)."""
    if arch in _IDENTITY:
        return _IDENTITY[arch]
    arch_def = REGISTRY.get(arch.partition(":")[0])
    if arch_def is not None and arch_def.color is not None:
        return arch_def.color
    # no colour of its own, or estimates of a name no definition has (another tool's file:
    # evaluated without an exact analysis, drawn all the same)
    return _EXTRA[zlib.crc32(arch.encode()) % len(_EXTRA)]


def arch_width(arch: str) -> float:
    """Line width of an architecture's Monte Carlo curves."""
    # The CKF is drawn wider so that an architecture that coincides with it (HKF) stays visible.
    return 4.0 if arch == CKF else 2.0


def class_color(index: int) -> tuple[int, int, int]:
    """The colour of the class with this index in identity sample-run views."""
    return _CLASS_COLORS[index % len(_CLASS_COLORS)]


def lighter(color: Sequence[int], amount: float = 0.5) -> tuple[int, int, int]:
    """`color` moved towards white by `amount` (0: unchanged, 1: white)."""
    r, g, b = (int(round(c + (255 - c) * amount)) for c in color)
    return r, g, b
