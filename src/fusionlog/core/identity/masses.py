"""Dempster-Shafer mass functions as dicts (Challa & Koks, seed 004, Sec. 4, eqs. 43-47).

Equation numbers are those of Challa & Koks, "Bayesian and Dempster-Shafer fusion"
(``shared/seeds/004_e832512ceaf07c5b.txt``).

The clean API: a mass function maps subsets of the frame of discernment (frozensets of class
names) to masses, ``{frozenset({"Learjet"}): 0.3, frozenset({"Learjet", "Falcon"}): 0.42, ...}``.
:func:`subset_index`, :func:`mass_to_array` and :func:`array_to_mass` convert to and from the
power-set arrays of :mod:`.dempster`, which does the arithmetic: Dempster's rule (eq. 47),
support Bel(A) = sum_{B subset of A, B nonempty} m(B) and plausibility
Pl(A) = sum_{B cap A nonempty} m(B) = 1 - Bel(not A).

All functions are pure (no I/O). Invalid input raises ValueError with a one-line message.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from .dempster import MASS_TOL, MAX_FRAME_SIZE, dempster_combine_array

__all__ = [
    "Combination",
    "MassDict",
    "array_to_mass",
    "belief",
    "dempster_combine",
    "mass_to_array",
    "plausibility",
    "subset_index",
]

#: A mass function: subset of the frame -> mass.
MassDict = Mapping[frozenset, float]


class Combination(NamedTuple):
    """Result of :func:`dempster_combine`: combined masses and conflict K (eq. 47)."""

    masses: dict[frozenset, float]
    conflict: float


def _sorted_frame(elements: Iterable[Hashable]) -> tuple:
    elements = set(elements)
    try:
        return tuple(sorted(elements))  # type: ignore[type-var]
    except TypeError:
        return tuple(sorted(elements, key=repr))


def _check_frame(frame: Sequence[Hashable]) -> tuple:
    if isinstance(frame, str):
        raise ValueError("frame must be a sequence of class names, not a string")
    frame = tuple(frame)
    if not frame:
        raise ValueError("frame of discernment is empty")
    if len(set(frame)) != len(frame):
        raise ValueError(f"frame has repeated class names: {list(frame)}")
    if len(frame) > MAX_FRAME_SIZE:
        raise ValueError(f"frame of {len(frame)} classes exceeds MAX_FRAME_SIZE = {MAX_FRAME_SIZE}")
    return frame


def _fmt(subset: frozenset) -> str:
    return "{" + ", ".join(sorted(map(str, subset))) + "}"


def _check_mass_dict(m: MassDict, name: str, frame: tuple | None) -> None:
    if not isinstance(m, Mapping):
        raise ValueError(f"{name}: a mass function must be a mapping {{frozenset: mass}}")
    total = 0.0
    for key, value in m.items():
        if not isinstance(key, frozenset):
            raise ValueError(f"{name}: key {key!r} is not a frozenset of class names")
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{name}: mass of {_fmt(key)} is not a number: {value!r}") from None
        if not math.isfinite(v):
            raise ValueError(f"{name}: mass of {_fmt(key)} is not finite")
        if v < 0:
            raise ValueError(f"{name}: mass of {_fmt(key)} is negative ({v:g})")
        if not key and v != 0:
            raise ValueError(f"{name}: an input mass function puts mass {v:g} on the empty set")
        if frame is not None and not key <= set(frame):
            outside = _fmt(key - set(frame))
            raise ValueError(
                f"{name}: subset {_fmt(key)} is not within the frame ({outside} not in frame)"
            )
        total += v
    if abs(total - 1.0) > MASS_TOL:
        raise ValueError(f"{name}: masses sum to {total!r}, not one (tolerance {MASS_TOL:g})")


def subset_index(subset: Iterable[Hashable], frame: Sequence[Hashable]) -> int:
    """Bitmask index of a subset of the frame: bit j is set iff frame[j] is in the subset."""
    frame = _check_frame(frame)
    if isinstance(subset, str):
        raise ValueError(f"subset must be a collection of class names, not the string {subset!r}")
    pos = {name: j for j, name in enumerate(frame)}
    index = 0
    for name in subset:
        if name not in pos:
            raise ValueError(f"subset element {name!r} is not within the frame {list(frame)}")
        index |= 1 << pos[name]
    return index


def mass_to_array(m: MassDict, frame: Sequence[Hashable]) -> np.ndarray:
    """Dict mass function -> array of shape (2^N,) indexed by :func:`subset_index` (validated)."""
    frame = _check_frame(frame)
    _check_mass_dict(m, "m", frame)
    arr = np.zeros(1 << len(frame))
    for key, value in m.items():
        arr[subset_index(key, frame)] += float(value)
    return arr


def array_to_mass(m: ArrayLike, frame: Sequence[Hashable]) -> dict[frozenset, float]:
    """Array of shape (2^N,) -> dict mass function over its focal elements (non-zero masses).

    NaN entries (from ``on_total_conflict="nan"``) are kept.
    """
    frame = _check_frame(frame)
    arr = np.asarray(m, dtype=float)
    if arr.shape != (1 << len(frame),):
        raise ValueError(
            f"mass array has shape {arr.shape}, expected ({1 << len(frame)},) for a frame of "
            f"{len(frame)} classes"
        )
    return {
        frozenset(frame[j] for j in range(len(frame)) if b >> j & 1): float(arr[b])
        for b in range(arr.size)
        if arr[b] != 0
    }


def dempster_combine(
    m1: MassDict,
    m2: MassDict,
    *more: MassDict,
    frame: Sequence[Hashable] | None = None,
) -> Combination:
    """Dempster's rule of combination, eq. (47), for mass functions given as dicts.

    Each mass function maps frozensets of class names (subsets of the frame of discernment) to
    masses: non-negative, no mass on the empty set, summing to one within ``MASS_TOL``.

    Args:
        m1, m2, *more: the mass functions to combine (two or more; order does not matter).
        frame: the frame of discernment (the class names, in the order that defines the array
            bitmask). Without it, the frame is the union of all subsets named in the inputs,
            sorted; with it, every subset must lie within it.

    Returns:
        ``(masses, conflict)``: the combined mass function (focal elements with non-zero mass)
        and K, the mass on the empty set before normalisation (see
        :func:`dempster_combine_array`). Raises ValueError on total conflict (K = 1).
    """
    inputs = (m1, m2, *more)
    fr = _check_frame(frame) if frame is not None else None
    for i, m in enumerate(inputs):
        _check_mass_dict(m, f"m{i + 1}", fr)
    if fr is None:
        fr = _check_frame(_sorted_frame(x for m in inputs for key in m for x in key))
    arrays = [mass_to_array(m, fr) for m in inputs]
    masses, conflict = dempster_combine_array(*arrays)
    return Combination(array_to_mass(masses, fr), float(conflict))


def _subset_arg(subset: Iterable[Hashable], frame: Sequence[Hashable] | None) -> frozenset:
    if isinstance(subset, str):
        raise ValueError(f"subset must be a collection of class names, not the string {subset!r}")
    sub = frozenset(subset)
    if frame is not None and not sub <= set(_check_frame(frame)):
        raise ValueError(f"subset {_fmt(sub)} is not within the frame {list(frame)}")
    return sub


def belief(
    m: MassDict, subset: Iterable[Hashable], frame: Sequence[Hashable] | None = None
) -> float:
    """Support (belief) Bel(A) = sum of m(B) over nonempty B contained in A.

    The least probability the evidence commits to A (the paper's "support"). ``frame``, if
    given, is used to check that the mass function and the subset lie within it.
    """
    fr = _check_frame(frame) if frame is not None else None
    _check_mass_dict(m, "m", fr)
    sub = _subset_arg(subset, fr)
    return float(sum(float(v) for key, v in m.items() if key and key <= sub))


def plausibility(
    m: MassDict, subset: Iterable[Hashable], frame: Sequence[Hashable] | None = None
) -> float:
    """Plausibility Pl(A) = sum of m(B) over B intersecting A = 1 - Bel(not A).

    The most probability the evidence leaves for A. ``frame`` as in :func:`belief`.
    """
    fr = _check_frame(frame) if frame is not None else None
    _check_mass_dict(m, "m", fr)
    sub = _subset_arg(subset, fr)
    return float(sum(float(v) for key, v in m.items() if key & sub))
