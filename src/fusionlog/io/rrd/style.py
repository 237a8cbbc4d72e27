"""Colours and line widths shared by every recording: an architecture (and a class of an
identity scenario) has the same colour in every plot of every recording, whatever the order or
the number of the architectures shown."""

from __future__ import annotations

import zlib
from collections.abc import Sequence

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

#: Stable colours (Tableau 10) per architecture; unknown names get one from a hash of the name.
_PALETTE: dict[str, tuple[int, int, int]] = {
    "CKF": (31, 119, 180),
    "HKF": (255, 127, 14),
    "MSC-GMF": (44, 160, 44),
    "MSC": (214, 39, 40),
    "SKF": (148, 103, 189),
    "CI": (140, 86, 75),
    "FBS": (227, 119, 194),
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
    if arch in _PALETTE:
        return _PALETTE[arch]
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
