"""Dempster's rule over the power set as arrays (Challa & Koks, seed 004, Sec. 4, eqs. 43-47).

Equation numbers are those of Challa & Koks, "Bayesian and Dempster-Shafer fusion"
(``shared/seeds/004_e832512ceaf07c5b.txt``).

A mass function over a frame of discernment of N classes is an array of masses over all 2^N
subsets, shape (..., 2^N): index ``b`` is the subset holding ``frame[j]`` for every bit ``j`` set
in ``b`` (bit 0 = ``frame[0]``); index 0 is the empty set and index 2^N - 1 the whole frame.
Leading dimensions are batch dimensions (runs, steps, ...), so whole blocks of runs combine at
once. (The dict representation, ``{frozenset: mass}``, is :mod:`.masses`.)

Dempster's rule, eq. (47), normalises the conjunctive combination (eq. 45)
sum_{A cap B = C} m1(A) m2(B) by the non-conflicting mass; the conflict
K = sum_{A cap B = empty} m1(A) m2(B) is returned too. Subset intersection is the bitwise AND of
indices. Support (belief) and plausibility: Bel(A) = sum_{B subset of A, B nonempty} m(B),
Pl(A) = sum_{B cap A nonempty} m(B) = 1 - Bel(not A).

All functions are pure (numpy only, no I/O). Invalid input raises ValueError with a one-line
message.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "MASS_TOL",
    "MAX_FRAME_SIZE",
    "ArrayCombination",
    "belief_array",
    "conjunctive",
    "dempster_combine_array",
    "plausibility_array",
]

#: Tolerance on "masses sum to one".
MASS_TOL = 1e-9
#: Largest frame the power-set (array) representation accepts: 2^20 doubles = 8 MiB per item.
MAX_FRAME_SIZE = 20
# Values the commonality (Moebius) path produces below this are rounding noise of exact zeros.
_NOISE = 1e-13

Method = Literal["auto", "pairs", "commonality"]


class ArrayCombination(NamedTuple):
    """Result of :func:`dempster_combine_array`: masses (..., 2^N) and conflict K (...)."""

    masses: np.ndarray
    conflict: np.ndarray


def _frame_bits(size: int, name: str) -> int:
    n = size.bit_length() - 1
    if size < 2 or size != 1 << n:
        raise ValueError(
            f"{name}: last axis has length {size}, not 2**N subsets of a frame of N >= 1 classes"
        )
    if n > MAX_FRAME_SIZE:
        raise ValueError(f"{name}: frame of {n} classes exceeds MAX_FRAME_SIZE = {MAX_FRAME_SIZE}")
    return n


def _check_mass_array(m: ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(m, dtype=float)
    if arr.ndim < 1:
        raise ValueError(f"{name}: a mass array needs a last axis of 2**N subsets")
    _frame_bits(arr.shape[-1], name)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: masses must be finite")
    if np.any(arr < 0):
        raise ValueError(f"{name}: masses must be non-negative (got {arr.min():g})")
    if np.any(arr[..., 0] != 0):
        raise ValueError(f"{name}: an input mass function puts mass on the empty set")
    total = arr.sum(axis=-1)
    bad = np.abs(total - 1.0) > MASS_TOL
    if np.any(bad):
        where = np.argwhere(bad)[0] if total.ndim else ()
        got = float(total[tuple(where)])
        at = f" at batch index {tuple(int(i) for i in where)}" if total.ndim else ""
        raise ValueError(f"{name}: masses sum to {got!r}{at}, not one (tolerance {MASS_TOL:g})")
    return arr


def _superset_transform(m: np.ndarray, n: int, op: np.ufunc) -> np.ndarray:
    """Over the last axis (2^N subsets): with ``np.add`` the commonality
    q(A) = sum_{B superset of A} m(B) (fast zeta transform); with ``np.subtract`` its inverse
    (Moebius transform). One pass per class j: entries without j combine with those with j."""
    batch = m.shape[:-1]
    q = m.reshape(batch + (2,) * n).copy()
    for ax in range(len(batch), q.ndim):
        lo = [slice(None)] * q.ndim
        hi = [slice(None)] * q.ndim
        lo[ax], hi[ax] = 0, 1
        without = q[tuple(lo)]  # a view: the ufunc writes into q
        op(without, q[tuple(hi)], out=without)
    return q.reshape(m.shape)


def _check_inputs(masses: tuple[ArrayLike, ...]) -> list[np.ndarray]:
    """Validated mass arrays over one frame with broadcastable batch shapes (m1, m2, ...)."""
    arrays = [_check_mass_array(m, f"m{i + 1}") for i, m in enumerate(masses)]
    size = arrays[0].shape[-1]
    for i, arr in enumerate(arrays[1:], start=2):
        if arr.shape[-1] != size:
            raise ValueError(
                f"m1 and m{i} are over different frames ({size} vs {arr.shape[-1]} subsets)"
            )
    try:
        np.broadcast_shapes(*(arr.shape for arr in arrays))
    except ValueError:
        shapes = ", ".join(str(arr.shape) for arr in arrays)
        raise ValueError(f"mass arrays have incompatible batch shapes: {shapes}") from None
    return arrays


def conjunctive(m1: ArrayLike, m2: ArrayLike, method: Method = "auto") -> np.ndarray:
    """Unnormalised conjunctive combination c(C) = sum_{A cap B = C} m1(A) m2(B), eq. (45).

    m1, m2: valid mass arrays (..., 2^N) as for :func:`dempster_combine_array`. Returns
    c (..., 2^N), whose entry 0 is the conflict K; Dempster's rule (eq. 47) is c / (1 - K) off
    the empty set. `method` chooses the summation (the results agree to ~1e-13):

    * ``pairs`` adds the product of every pair of focal elements (in the union of the batch's
      supports) into the subset given by the bitwise AND of their indices: the paper's sums of
      products, with no cancellation; cost ~ pairs x batch, little memory.
    * ``commonality`` multiplies commonality functions and transforms back (cost ~ N 2^N x
      batch, absolute rounding ~1e-15, so results below 1e-13 are set to zero).
    * ``auto`` uses pairs while the number of focal-element pairs is at most 4 x 2^N (or 64).
    """
    a, b = _check_inputs((m1, m2))
    return _conjunctive(a, b, method)


def _conjunctive(m1: np.ndarray, m2: np.ndarray, method: Method = "auto") -> np.ndarray:
    """:func:`conjunctive` on inputs already checked."""
    m1, m2 = np.broadcast_arrays(m1, m2)
    size = m1.shape[-1]
    n = size.bit_length() - 1
    batch_axes = tuple(range(m1.ndim - 1))
    f1 = np.flatnonzero(np.any(m1 != 0, axis=batch_axes))
    f2 = np.flatnonzero(np.any(m2 != 0, axis=batch_axes))
    if method == "auto":
        method = "pairs" if f1.size * f2.size <= max(64, 4 * size) else "commonality"
    if method == "pairs":
        out = np.zeros(m1.shape)
        for a in f1:
            for b in f2:
                out[..., a & b] += m1[..., a] * m2[..., b]
        return out
    if method == "commonality":
        q = _superset_transform(m1, n, np.add) * _superset_transform(m2, n, np.add)
        out = _superset_transform(q, n, np.subtract)
        out[np.abs(out) < _NOISE] = 0.0
        return out
    raise ValueError(f"unknown method {method!r}")


def dempster_combine_array(
    m1: ArrayLike,
    m2: ArrayLike,
    *more: ArrayLike,
    on_total_conflict: Literal["raise", "nan"] = "raise",
) -> ArrayCombination:
    """Dempster's rule of combination, eq. (47), for masses indexed by subset bitmask.

    m^{1,2}(C) = sum_{A cap B = C} m^1(A) m^2(B) / sum_{A cap B != empty} m^1(A) m^2(B)
    (the first form of eq. 47; it equals the second, with 1 - K, when the inputs sum to one,
    and keeps the output summing to one). Subset intersection is the bitwise AND of indices.

    Args:
        m1, m2, *more: mass arrays of shape (..., 2^N) with the same N and broadcastable leading
            batch dimensions (runs, steps, ...). Each item must be non-negative, put no mass on
            the empty set (index 0) and sum to one within ``MASS_TOL``.
        on_total_conflict: "raise" (default) raises ValueError if K = 1 for any item (Dempster's
            rule is undefined); "nan" returns NaN masses for those items (K = 1) instead, so one
            item does not stop a batch.

    Returns:
        ``(masses, conflict)``: combined masses (..., 2^N) with masses[..., 0] = 0, and
        K (...) = mass on the empty set before normalisation. For more than two inputs they are
        combined left to right (the rule is commutative and associative) and K is the conflict
        of the whole conjunctive combination, 1 - prod_i (1 - K_i) over the steps.
    """
    if on_total_conflict not in ("raise", "nan"):
        raise ValueError(f"on_total_conflict must be 'raise' or 'nan', got {on_total_conflict!r}")
    arrays = _check_inputs((m1, m2, *more))
    combined = arrays[0]
    conflict: np.ndarray = np.zeros(combined.shape[:-1])
    dead = np.zeros(combined.shape[:-1], dtype=bool)  # items already in total conflict ("nan")
    for arr in arrays[1:]:
        raw = _conjunctive(combined, arr)
        k = raw[..., 0].copy()
        raw[..., 0] = 0.0
        norm = raw.sum(axis=-1)
        total = (norm <= 0) | dead
        if np.any(total):
            if on_total_conflict == "raise":
                count = int(np.count_nonzero(total))
                what = "the inputs" if norm.ndim == 0 else f"{count} of {norm.size} items"
                raise ValueError(
                    f"total conflict (K = 1) for {what}: Dempster's rule (eq. 47) is undefined"
                )
            norm = np.where(total, np.nan, norm)
            k = np.where(total, 1.0, k)
            dead = total
        combined = raw / norm[..., None]
        conflict = np.where(dead, 1.0, conflict + (1.0 - conflict) * k)
    return ArrayCombination(combined, conflict)


def belief_array(m: ArrayLike, subset: int) -> np.ndarray:
    """Support (belief) Bel(A) = sum_{B subset of A, B nonempty} m(B) for A given as a bitmask.

    m has shape (..., 2^N); returns shape (...). Bel(empty) = 0, Bel(frame) = 1.
    """
    arr = _check_mass_array(m, "m")
    idx = _check_subset_index(subset, arr.shape[-1])
    b = np.arange(arr.shape[-1])
    return arr[..., ((b & ~idx) == 0) & (b != 0)].sum(axis=-1)


def plausibility_array(m: ArrayLike, subset: int) -> np.ndarray:
    """Plausibility Pl(A) = sum_{B cap A nonempty} m(B) = 1 - Bel(not A), A given as a bitmask.

    m has shape (..., 2^N); returns shape (...). Pl(empty) = 0, Pl(frame) = 1.
    """
    arr = _check_mass_array(m, "m")
    idx = _check_subset_index(subset, arr.shape[-1])
    b = np.arange(arr.shape[-1])
    return arr[..., (b & idx) != 0].sum(axis=-1)


def _check_subset_index(subset: int, size: int) -> int:
    if isinstance(subset, bool) or not isinstance(subset, (int, np.integer)):
        raise ValueError(f"subset must be an integer bitmask, got {type(subset).__name__}")
    if not 0 <= subset < size:
        raise ValueError(f"subset bitmask {subset} is outside the frame (0 .. {size - 1})")
    return int(subset)
