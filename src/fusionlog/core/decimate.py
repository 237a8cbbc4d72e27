"""Time series of a long log sized for a viewer: min, mean and max per bucket of instants.

No screen shows 10^6 points of a series; the viewer itself aggregates a long series per pixel
column (Rerun's MinMax/MinMaxAverage aggregation). A recording does the same before it is
written, so that the viewer loads 3 000 points per entity instead of the whole log: above
`DECIMATE_ABOVE` instants the instants are cut into consecutive buckets of b =
ceil(instants / BUCKETS) and each bucket becomes three points, at its first, middle and last
instant: the extreme that comes first in the bucket, the bucket's mean, the other extreme
(monotone within the bucket: the drawn curve keeps every bucket's minimum and maximum, hence
its shape and its spikes). Non-finite values are left out of a bucket (all of them: NaN).

`Decimator` reduces one series handed over block by block (a long log evaluated in blocks of
time) with one partial bucket kept; `TreeDecimator` does it for nested dicts/tuples of series.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "BUCKETS",
    "DECIMATE_ABOVE",
    "Decimator",
    "TreeDecimator",
    "bucket_size",
    "plane_at",
    "point_steps",
]

#: Instants up to which every series is kept whole.
DECIMATE_ABOVE = 30_000
#: Buckets of a decimated series (three points each). 3 000 points are more than the pixel
#: columns of any view at 1920 px, so the curve on screen is the same; with 10 000 buckets the
#: headless viewer's software renderer (llvmpipe) did not draw the first frame of the paper's
#: ten views within its 15 s, with 1 000 it draws every view (benchmarks/README.md).
BUCKETS = 1_000


def bucket_size(instants: int, full_resolution: bool = False) -> int:
    """Instants per bucket of a log of `instants` (1: kept whole)."""
    if full_resolution or instants <= DECIMATE_ABOVE:
        return 1
    return math.ceil(instants / BUCKETS)


def point_steps(instants: int, b: int) -> np.ndarray:
    """The instants of a decimated series' points: each bucket's first, middle and last (all
    instants when b = 1)."""
    if b == 1:
        return np.arange(instants)
    a = np.arange(0, instants, b)
    e = np.minimum(a + b, instants) - 1
    return np.stack([a, (a + e) // 2, e], axis=1).reshape(-1)


def _reduce(v: np.ndarray) -> np.ndarray:
    """Buckets (nb, s, ...) -> their points (nb * 3, ...)."""
    ok = np.isfinite(v)
    if ok.all():  # the usual case: v itself (C order, as the copies below) in their place
        lo_v = hi_v = total = np.ascontiguousarray(v)
        count = np.full(v.shape[:1] + v.shape[2:], v.shape[1])
    else:
        lo_v = np.where(ok, v, np.inf)
        hi_v = np.where(ok, v, -np.inf)
        total = np.where(ok, v, 0.0)
        count = ok.sum(axis=1)
    ilo, ihi = lo_v.argmin(axis=1), hi_v.argmax(axis=1)
    # the extremes where argmin/argmax found them (min/max along a middle axis of a (nb, b,
    # n) series take ~20 times as long as the arg- reductions)
    lo = np.take_along_axis(lo_v, ilo[:, None], axis=1)[:, 0]
    hi = np.take_along_axis(hi_v, ihi[:, None], axis=1)[:, 0]
    some = count > 0
    mean = np.where(some, total.sum(axis=1) / np.maximum(count, 1), np.nan)
    first, second = np.where(ilo <= ihi, lo, hi), np.where(ilo <= ihi, hi, lo)
    first, second = np.where(some, first, np.nan), np.where(some, second, np.nan)
    return np.stack([first, mean, second], axis=1).reshape(-1, *v.shape[2:])


#: Parts (each block's points) a `Decimator` keeps apart before joining them into one array.
_PARTS = 8


class Decimator:
    """One series (w, ...) handed over in order, block by block, reduced to its points."""

    def __init__(self, b: int) -> None:
        self.b = b
        self.parts: list[np.ndarray] = []
        self.rest: np.ndarray | None = None

    def add(self, v: np.ndarray) -> None:
        v = np.asarray(v, dtype=float)
        if self.b == 1:
            self.parts.append(v.copy())
            return
        if self.rest is not None and len(self.rest):
            v = np.concatenate([self.rest, v])
        full = len(v) // self.b * self.b
        if full:
            self.parts.append(_reduce(v[:full].reshape(-1, self.b, *v.shape[1:])))
            if len(self.parts) > _PARTS:  # one array: a part per block would grow with them
                self.parts = [np.concatenate(self.parts)]
        self.rest = v[full:].copy()

    def result(self) -> np.ndarray:
        if self.rest is not None and len(self.rest):
            self.parts.append(_reduce(self.rest[None]))
            self.rest = None
        out = np.concatenate(self.parts) if len(self.parts) > 1 else self.parts[0]
        self.parts = [out]
        return out


class TreeDecimator:
    """Nested dicts and tuples whose leaves are series (w, ...) of the same instants, handed
    over block by block (the same structure each time), reduced leaf by leaf."""

    def __init__(self, b: int, length: int | None = None) -> None:
        self.b, self.length = b, length
        self.leaves: dict[tuple, Decimator] = {}
        self.kept: dict[tuple, np.ndarray] = {}  # arrays that are no series (not `length` long)
        self.shape: Any = None

    def add(self, tree: Any) -> None:
        self.shape = _walk(tree, (), self._leaf)

    def _leaf(self, path: tuple, v: np.ndarray) -> tuple:
        if self.length is not None and (v.ndim == 0 or v.shape[0] != self.length):
            self.kept[path] = v
            return path
        d = self.leaves.get(path)
        if d is None:
            d = self.leaves[path] = Decimator(self.b)
        d.add(v)
        return path

    def result(self) -> Any:
        """The tree of the last block's structure with each leaf's points."""

        def done(path: tuple, leaf: tuple) -> np.ndarray:
            return self.kept[leaf] if leaf in self.kept else self.leaves[leaf].result()

        return _walk(self.shape, (), done, leaf_is=tuple)


def _walk(tree: Any, path: tuple, fn, leaf_is: type = np.ndarray) -> Any:
    if isinstance(tree, dict):
        return {k: _walk(v, (*path, k), fn, leaf_is) for k, v in tree.items()}
    if leaf_is is tuple and isinstance(tree, tuple) and tree and tree[0] == "__leaf__":
        return fn(path, tree[1])
    if isinstance(tree, tuple | list):
        return type(tree)(_walk(v, (*path, i), fn, leaf_is) for i, v in enumerate(tree))
    if isinstance(tree, np.ndarray):
        return ("__leaf__", fn(path, tree))
    return tree


#: The `Evaluation` fields whose arrays are series over the instants.
SERIES_FIELDS = (
    "series", "nees_bounds", "samples", "availability", "nis", "traces", "measured", "pcrb",
    "innovations", "trajectory", "bands",
)  # fmt: skip


def with_derived(tree: dict[str, Any], reference: str) -> dict[str, Any]:
    """`tree` (the `Evaluation`'s series fields) with what the recording draws as a function of
    several series computed before they are decimated (a bucket's extremes of a difference
    are not the difference of the extremes): each architecture's MSE minus the `reference`
    architecture's ("mse_minus_ckf") and each sample run's ±2σ band ("bands"). The given
    dicts are not changed."""
    series = {a: dict(d) for a, d in (tree.get("series") or {}).items()}
    ref = series.get(reference)
    for a, d in series.items():
        if ref is not None and a != reference:
            d["mse_minus_ckf"] = np.asarray(d["mse"], float) - np.asarray(ref["mse"], float)
    with np.errstate(over="ignore", invalid="ignore"):  # inf - inf: NaN, drawn as a gap
        bands = {
            m: {a: (v[0] - 2 * v[1], v[0] + 2 * v[1]) for a, v in est.items()}
            for m, (_, est) in (tree.get("samples") or {}).items()
        }
    return {**tree, "series": series, "bands": bands}


def note(instants: int, b: int) -> dict[str, str]:
    """The recording's ``decimation`` property."""
    return {
        "instants": str(instants),
        "bucket": str(b),
        "points": "each bucket of instants as three points at its first, middle and last "
        "instant: the extreme that comes first, the mean, the other extreme (non-finite "
        "values left out); summary.json has the values over every instant; "
        "[evaluate] full_resolution = true keeps every instant",
    }


def decimate_evaluation(ev: Any, reference: str) -> Any:
    """`ev` (`core.evaluation.Evaluation`) with its series decimated where the log is longer
    than `DECIMATE_ABOVE` instants, unless it asks for full resolution or is decimated already
    (`reference`: the architecture the others' MSE is drawn against, see `with_derived`). A
    state plane is sampled at the points' instants (`plane_at`)."""
    import dataclasses

    K1 = len(ev.times)
    b = bucket_size(K1, ev.full_resolution)
    if b == 1 or ev.steps is not None:
        return ev
    tree = TreeDecimator(b, K1)
    tree.add(with_derived({f: getattr(ev, f) for f in SERIES_FIELDS}, reference))
    steps = point_steps(K1, b)
    return dataclasses.replace(
        ev, **tree.result(), times=np.asarray(ev.times)[steps], steps=steps, decimation=note(K1, b),
        plane=plane_at(ev.plane, steps),
    )  # fmt: skip


def plane_at(plane: dict[str, Any] | None, steps: np.ndarray, k0: int = 0) -> dict | None:
    """The state plane's truth, sample estimates and ellipses at the instants `steps` (of a
    block whose first instant is k0): each frame a real state and covariance, not a bucket's
    extremes (a covariance's entries' extremes are no covariance)."""
    if plane is None:
        return None
    at = np.asarray(steps) - k0
    return {
        **plane,
        "truth": np.asarray(plane["truth"])[at],
        "estimates": {a: np.asarray(v)[at] for a, v in plane["estimates"].items()},
        "ellipses": {k: np.asarray(v)[at] for k, v in plane["ellipses"].items()},
    }
