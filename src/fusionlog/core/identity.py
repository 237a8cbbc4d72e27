"""Identity (classification) fusion: Bayes and Dempster-Shafer (Challa & Koks, seed 004).

Equation numbers are those of Challa & Koks, "Bayesian and Dempster-Shafer fusion"
(``shared/seeds/004_e832512ceaf07c5b.txt``).

Bayes (Sec. 3.2, eqs. 35-41). Sensor i reports, for each class x, either a likelihood
(y^i | x, Y_0^i) of its latest measurement (eq. 37) or a posterior (x | Y_1^i) computed with its
own prior (x | Y_0^i); in the second case the sensor's prior is divided out, eq. (38) for two
sensors and (41) for three or more:

    (x | Y_1^1 ... Y_1^S) = c prod_i [(x | Y_1^i) / (x | Y_0^i)] (x | Y_0^1 ... Y_0^S),

with c normalising over the classes x.

Dempster-Shafer (Sec. 4, eqs. 43-47). A mass function over a frame of discernment (the set of
classes) assigns masses to subsets. Two representations:

* dict: ``{frozenset({"Learjet"}): 0.3, frozenset({"Learjet", "Falcon"}): 0.42, ...}`` (clean API);
* array: masses over all 2^N subsets, shape (..., 2^N), where index ``b`` is the subset holding
  ``frame[j]`` for every bit ``j`` set in ``b`` (bit 0 = ``frame[0]``); index 0 is the empty set
  and index 2^N - 1 the whole frame. Leading dimensions are batch dimensions (runs, steps, ...).

Dempster's rule, eq. (47), normalises the conjunctive combination sum_{A cap B = C} m1(A) m2(B) by
the non-conflicting mass; the conflict K = sum_{A cap B = empty} m1(A) m2(B) is returned too.
Support (belief) and plausibility: Bel(A) = sum_{B subset of A, B nonempty} m(B),
Pl(A) = sum_{B cap A nonempty} m(B) = 1 - Bel(not A).

All functions are pure (numpy only, no I/O). Invalid input raises ValueError with a one-line
message.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "MASS_TOL",
    "MAX_FRAME_SIZE",
    "ArrayCombination",
    "Combination",
    "array_to_mass",
    "bayes_fusion",
    "bayes_fusion_posteriors",
    "belief",
    "belief_array",
    "dempster_combine",
    "dempster_combine_array",
    "mass_to_array",
    "plausibility",
    "plausibility_array",
    "subset_index",
]

#: Tolerance on "masses sum to one".
MASS_TOL = 1e-9
#: Largest frame the power-set (array) representation accepts: 2^20 doubles = 8 MiB per item.
MAX_FRAME_SIZE = 20
# Values the commonality (Moebius) path produces below this are rounding noise of exact zeros.
_NOISE = 1e-13

MassDict = Mapping[frozenset, float]


class Combination(NamedTuple):
    """Result of :func:`dempster_combine`: combined masses and conflict K (eq. 47)."""

    masses: dict[frozenset, float]
    conflict: float


class ArrayCombination(NamedTuple):
    """Result of :func:`dempster_combine_array`: masses (..., 2^N) and conflict K (...)."""

    masses: np.ndarray
    conflict: np.ndarray


# --------------------------------------------------------------------------------------------
# Bayes, eqs. (35)-(41)
# --------------------------------------------------------------------------------------------


def _nonneg_finite(a: ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    if np.any(arr < 0):
        raise ValueError(f"{name} must be non-negative (got {arr.min():g})")
    return arr


def bayes_fusion(likelihoods: ArrayLike, prior: ArrayLike) -> np.ndarray:
    """Fuse several sensors' class likelihoods with the fusion node's prior, eqs. (36)-(37).

    (x | Y_1^1 ... Y_1^S) = prod_i (y_1^i | x, Y_0^i) (x | Y_0^1 ... Y_0^S) / normalisation: the
    measurements are conditionally independent given the class (eq. 36), so the joint likelihood
    is the product of the sensors' likelihoods (eq. 37).

    Args:
        likelihoods: shape (..., S, C): for each of S sensors, the likelihood of its latest data
            for each of C classes (non-negative; need not sum to one; only ratios matter). Leading
            dimensions are batch dimensions (runs, steps, ...). One sensor is shape (..., 1, C).
        prior: the fusion node's prior (x | Y_0^1 ... Y_0^S), broadcastable to (..., C);
            non-negative, normalised by the function.

    Returns:
        Normalised fused class probabilities, shape broadcast(likelihoods[..., 0, :], prior).

    Computed in log space, so many sensors with small likelihoods do not underflow.
    """
    lik = _nonneg_finite(likelihoods, "likelihoods")
    pri = _nonneg_finite(prior, "prior")
    if lik.ndim < 2:
        raise ValueError(
            f"likelihoods must have shape (..., sensors, classes), got {lik.shape}; "
            "use shape (1, C) for one sensor"
        )
    if pri.ndim < 1 or pri.shape[-1] != lik.shape[-1]:
        raise ValueError(
            f"prior has {pri.shape[-1] if pri.ndim else 0} classes but likelihoods have "
            f"{lik.shape[-1]}"
        )
    try:
        out_shape = np.broadcast_shapes(lik.shape[:-2] + lik.shape[-1:], pri.shape)
    except ValueError:
        raise ValueError(
            f"prior shape {pri.shape} does not broadcast against likelihoods shape {lik.shape}"
        ) from None
    with np.errstate(divide="ignore"):
        log_post = np.log(lik).sum(axis=-2) + np.log(pri)
    log_post = np.broadcast_to(log_post, out_shape)
    top = log_post.max(axis=-1, keepdims=True)
    if np.any(np.isneginf(top)):
        raise ValueError(
            "fused evidence is zero for every class (prior and sensors exclude all classes)"
        )
    w = np.exp(log_post - top)
    return w / w.sum(axis=-1, keepdims=True)


def bayes_fusion_posteriors(
    posteriors: ArrayLike, sensor_priors: ArrayLike, prior: ArrayLike
) -> np.ndarray:
    """Fuse sensors' class posteriors, dividing out each sensor's own prior, eqs. (38) and (41).

    (x | Y_1^1 ... Y_1^S) = c prod_i [(x | Y_1^i) / (x | Y_0^i)] (x | Y_0^1 ... Y_0^S),
    c normalising over x: eq. (38) for S = 2 and eq. (41) for S = 3 ("and so on for more
    sensors"). By Bayes' rule, (x | Y_1^i) / (x | Y_0^i) is proportional in x to the likelihood
    (y_1^i | x, Y_0^i), so this is :func:`bayes_fusion` applied to those ratios.
    This is the paper's Tables 1-2 example.

    Args:
        posteriors: shape (..., S, C): each sensor's posterior (x | Y_1^i) after its latest data.
        sensor_priors: broadcastable to (..., S, C): each sensor's previous posterior
            (x | Y_0^i), strictly positive (it is divided by).
        prior: the fusion node's prior (x | Y_0^1 ... Y_0^S), broadcastable to (..., C).

    Returns:
        Normalised fused class probabilities, shape (..., C).
    """
    post = _nonneg_finite(posteriors, "posteriors")
    sp = _nonneg_finite(sensor_priors, "sensor_priors")
    if np.any(sp == 0):
        raise ValueError("sensor_priors must be strictly positive (eqs. 38/41 divide by them)")
    if post.ndim < 2:
        raise ValueError(
            f"posteriors must have shape (..., sensors, classes), got {post.shape}; "
            "use shape (1, C) for one sensor"
        )
    try:
        np.broadcast_shapes(post.shape, sp.shape)
    except ValueError:
        raise ValueError(
            f"sensor_priors shape {sp.shape} does not broadcast against posteriors shape "
            f"{post.shape}"
        ) from None
    if sp.ndim < 1 or sp.shape[-1] != post.shape[-1]:
        raise ValueError("sensor_priors and posteriors have different numbers of classes")
    return bayes_fusion(post / sp, prior)


# --------------------------------------------------------------------------------------------
# Dempster-Shafer: array representation
# --------------------------------------------------------------------------------------------


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


def _superset_sums(m: np.ndarray, n: int) -> np.ndarray:
    """Commonality q(A) = sum_{B superset of A} m(B) over the last axis (fast zeta transform)."""
    batch = m.shape[:-1]
    q = m.reshape(batch + (2,) * n).copy()
    for ax in range(len(batch), q.ndim):
        lo = [slice(None)] * q.ndim
        hi = [slice(None)] * q.ndim
        lo[ax], hi[ax] = 0, 1
        q[tuple(lo)] += q[tuple(hi)]
    return q.reshape(m.shape)


def _superset_diffs(q: np.ndarray, n: int) -> np.ndarray:
    """Inverse of :func:`_superset_sums` (Moebius transform)."""
    batch = q.shape[:-1]
    m = q.reshape(batch + (2,) * n).copy()
    for ax in range(len(batch), m.ndim):
        lo = [slice(None)] * m.ndim
        hi = [slice(None)] * m.ndim
        lo[ax], hi[ax] = 0, 1
        m[tuple(lo)] -= m[tuple(hi)]
    return m.reshape(q.shape)


def _conjunctive(
    m1: np.ndarray,
    m2: np.ndarray,
    method: Literal["auto", "pairs", "commonality"] = "auto",
) -> np.ndarray:
    """Unnormalised conjunctive combination c(C) = sum_{A cap B = C} m1(A) m2(B), eq. (45).

    Entry 0 is the conflict K. ``pairs`` adds the product of every pair of focal elements (in
    the union of the batch's supports) into the subset given by the bitwise AND of their indices:
    the paper's sums of products, with no cancellation; cost ~ pairs x batch, little memory.
    ``commonality`` multiplies commonality functions and transforms back (cost ~ N 2^N x batch,
    absolute rounding ~1e-15, so results below 1e-13 are set to zero). ``auto`` uses pairs while
    the number of focal-element pairs is at most 4 x 2^N (or 64).
    """
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
        q = _superset_sums(m1, n) * _superset_sums(m2, n)
        out = _superset_diffs(q, n)
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
    arrays = [_check_mass_array(m, f"m{i + 1}") for i, m in enumerate((m1, m2, *more))]
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


# --------------------------------------------------------------------------------------------
# Dempster-Shafer: dict representation
# --------------------------------------------------------------------------------------------


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
