"""The per-interval F, Q of a model on irregular instants, formed a stretch at a time on demand.

`System.on_times` (`core.model`) discretises a continuous model for every interval between the
log's instants: F = expm(A Δ), Q by Van Loan's method (`timing.van_loan`), one matrix
exponential per distinct interval. Held whole, the K intervals' F and Q are 2 K n² doubles (64 MB
at 10^6 instants with 2 states, and ~240 MB while `van_loan` formed them, issue 34). Here they
are formed only for the intervals asked for: `PerInterval` stands where the (K, n, n) arrays
stood (`System.Fs`, `System.Qs`), indexed like them — a range (`System.transitions`, a block of
time) formed at once, a single interval (`System.F_at`, `GQG_at`, instant by instant) from a
cached stretch of `STRETCH` intervals — from the instants' times, which the log holds anyway.

The numbers are those of forming every interval at once: `van_loan` computes each interval's
F and Q from its Δ alone (elementwise powers and one product per row), so the distinct
intervals of a stretch give the same bits as those of the whole log (tests/test_intervals.py).

`PerInstant` does the same for a matrix per instant: the stacked R of eq. (31) of a long log whose
messages carry their own covariance (`System.Rs`), formed from a source a block at a time
(`stages.noise`: the messages' covariances spooled block of time by block).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from .timing import van_loan

__all__ = [
    "STRETCH",
    "MotionNoise",
    "PerInstant",
    "PerInterval",
    "Transitions",
    "VanLoan",
    "same_per_interval",
]

#: Intervals formed at once for a single interval's F or Q (`PerInterval[k]`): one stretch
#: (a few hundred kB) cached per system, so an instant-by-instant loop forms each once.
STRETCH = 1 << 12


class VanLoan:
    """The F, Q of a continuous model (A, Qc) for an array of intervals (`timing.van_loan`)."""

    def __init__(self, A: np.ndarray, Qc: np.ndarray) -> None:
        self.A, self.Qc = A, Qc
        self.key = A.tobytes() + Qc.tobytes()  # the model bit for bit

    def __call__(self, deltas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return van_loan(self.A, self.Qc, deltas)


class MotionNoise:
    """The Q(Δ) (n, n) of a nonlinear motion (`core.models`) for an array of intervals, one
    call each (F: None, the motion is f(x, Δ))."""

    key = None  # a model's Q is a function: only the same source is known to be equal

    def __init__(self, Q_of: Callable[[float], np.ndarray], n: int) -> None:
        self.Q_of, self.n = Q_of, n

    def __call__(self, deltas: np.ndarray) -> tuple[None, np.ndarray]:
        Q = [self.Q_of(float(d)) for d in deltas]
        return None, np.stack(Q) if Q else np.empty((0, self.n, self.n))


class Transitions:
    """The (F, Q) of the intervals between the instants `times` (K+1,) s: `form(deltas)`
    (`VanLoan`, `MotionNoise`) gives them for an array of distinct intervals ((U, n, n) each;
    F None for a motion without a matrix); `form.key` names the model bit for bit (two sources
    with equal keys and times form equal matrices; None: only the source itself is known to)."""

    def __init__(self, times: np.ndarray, form: VanLoan | MotionNoise) -> None:
        self.times, self.form, self.key = times, form, form.key
        self._cached: tuple[int, tuple] | None = None

    def __len__(self) -> int:
        return len(self.times) - 1

    def __getstate__(self) -> dict:  # pickled (Dask) without the cached stretch
        return {**self.__dict__, "_cached": None}

    def deltas(self, key) -> np.ndarray:
        """The intervals t_{k+1} - t_k of the intervals `key` (a slice, an int or an int array,
        numpy's meaning over 0..K-1): the values of `np.diff(times)[key]`."""
        if isinstance(key, slice):
            a, b, step = key.indices(len(self))
            if step == 1:
                b = max(a, b)
                return self.times[a + 1 : b + 1] - self.times[a:b]
            key = np.arange(a, b, step)
        idx = np.arange(len(self))[key]  # numpy's bounds and negative indices
        return self.times[idx + 1] - self.times[idx]

    def of(self, key) -> tuple:
        """(F, Q) of the intervals `key`, shaped as `deltas(key)` + (n, n) (F None where the
        motion has none)."""
        if isinstance(key, (int, np.integer)):
            k = int(key) + len(self) if key < 0 else int(key)
            if not 0 <= k < len(self):
                raise IndexError(f"interval {key} of {len(self)}")
            c = k // STRETCH
            if self._cached is None or self._cached[0] != c:
                self._cached = (c, self.of(slice(c * STRETCH, (c + 1) * STRETCH)))
            F, Q = self._cached[1]
            j = k - c * STRETCH
            return (None if F is None else F[j]), Q[j]
        d = self.deltas(key)
        uniq, where = np.unique(d, return_inverse=True)
        F, Q = self.form(uniq)
        where = where.reshape(d.shape)
        out = (None if F is None else F[where], Q[where])
        for a in out:
            if a is not None:
                a.flags.writeable = False  # shared by the cache: what a caller gets to read
        return out


class _Formed(np.lib.mixins.NDArrayOperatorsMixin):
    """What an array of per-step matrices formed on demand does as an array: `np.asarray(x)`
    and arithmetic form every step; `x[k]` and `x[a:b]` (`__getitem__`) form those."""

    __slots__ = ()

    def __getitem__(self, key) -> np.ndarray:  # pragma: no cover - each kind forms its own
        raise NotImplementedError

    def __len__(self) -> int:  # pragma: no cover
        raise NotImplementedError

    def __iter__(self) -> Iterator[np.ndarray]:
        for k in range(len(self)):
            yield self[k]

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = self[:]
        return out if dtype is None else out.astype(dtype)

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        args = [np.asarray(x) if isinstance(x, _Formed) else x for x in inputs]
        return getattr(ufunc, method)(*args, **kwargs)

    @property
    def ndim(self) -> int:
        return 1 + self[0].ndim if len(self) else 3

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self),) + self[0].shape if len(self) else (0, 0, 0)


class PerInterval(_Formed):
    """F (`which` 0) or Q (1) of every interval of a `Transitions`, indexed like the (K, n, n)
    array it stands for: `x[k]`, `x[a:b]`, `x[int_array]` form those intervals (read only);
    `np.asarray(x)` and arithmetic (`3.0 * x`) form them all."""

    __slots__ = ("source", "which")

    def __init__(self, source: Transitions, which: int) -> None:
        self.source, self.which = source, which

    def __getstate__(self) -> tuple:
        return (self.source, self.which)

    def __setstate__(self, state: tuple) -> None:
        self.source, self.which = state

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, key) -> np.ndarray:
        return self.source.of(key)[self.which]


class PerInstant(_Formed):
    """A matrix per instant of a long log (the stacked R of eq. (31) where a recorded log's
    messages carry their own covariance, `System.Rs`), indexed like the (K+1, m, m) array it
    stands for and formed for the instants asked for by `source.form(k0, k1)` ((k1 - k0, m, m),
    the same bits whatever the range; `source.key` names them: equal keys, equal matrices).
    `x[k]` forms a cached stretch of `STRETCH` instants (an instant-by-instant loop forms each
    once), `x[a:b]` those instants, `x[:, rows][:, :, rows]` (a subset of the sensors) and
    `x.map(f)` stand for the arrays of the stretches `f` or the index makes, formed likewise."""

    __slots__ = ("source", "post")

    def __init__(self, source: Any, post: tuple = ()) -> None:
        self.source, self.post = source, post

    def __len__(self) -> int:
        return len(self.source)

    @property
    def key(self) -> Any:
        """What names these matrices bit for bit (None: only this object is known to)."""
        key = getattr(self.source, "key", None)
        return None if key is None else (key, self.post)

    def map(self, f: Callable[[np.ndarray], np.ndarray]) -> PerInstant:
        """`f` of every stretch ((w, m, m) -> (w, ...)), formed when asked for."""
        return PerInstant(self.source, self.post + (f,))

    def _formed(self, k0: int, k1: int) -> np.ndarray:
        if k1 - k0 == 1:  # one instant: from the cached stretch around it
            c = k0 // STRETCH
            got = getattr(self.source, "cached", None)
            if got is None or got[0] != c:
                a = c * STRETCH
                got = self.source.cached = (c, self.source.form(a, min(a + STRETCH, len(self))))
            j = k0 - c * STRETCH
            out = got[1][j : j + 1]
        else:
            out = self.source.form(k0, k1)
        for p in self.post:
            out = p(out)
        return out

    def __getitem__(self, key) -> np.ndarray:
        if isinstance(key, tuple):
            first, rest = (key[0], key[1:]) if key else (slice(None), ())
            if not rest:
                return self[first]
            if isinstance(first, slice) and first == slice(None):
                return self.map(_Index(rest))
            got = self[first]
            return got[rest] if isinstance(first, (int, np.integer)) else got[(slice(None), *rest)]
        K1 = len(self)
        if isinstance(key, (int, np.integer)):
            k = int(key) + K1 if key < 0 else int(key)
            if not 0 <= k < K1:
                raise IndexError(f"instant {key} of {K1}")
            return self._formed(k, k + 1)[0]
        if isinstance(key, slice) and key.indices(K1)[2] == 1:
            a, b, _ = key.indices(K1)
            return self._formed(a, max(a, b))
        idx = np.arange(K1)[key]  # numpy's meaning (steps, arrays, masks): their range formed
        if not idx.size:
            return self._formed(0, 0)[idx]
        lo = int(idx.min())
        return self._formed(lo, int(idx.max()) + 1)[idx - lo]


class _Index:
    """The index `rest` of every instant's matrix (`PerInstant`'s `x[:, rows]`)."""

    __slots__ = ("rest",)

    def __init__(self, rest: tuple) -> None:
        self.rest = rest

    def __call__(self, a: np.ndarray) -> np.ndarray:
        return a[(slice(None),) + self.rest]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Index) and _same_index(self.rest, other.rest)

    def __hash__(self) -> int:
        return hash(len(self.rest))


def _same_index(a: tuple, b: tuple) -> bool:
    return len(a) == len(b) and all(
        (x == y) if isinstance(x, slice) or isinstance(y, slice) else np.array_equal(x, y)
        for x, y in zip(a, b, strict=True)
    )


def same_per_interval(a, default_a: np.ndarray, b, default_b: np.ndarray, count: int) -> bool:
    """Whether two systems' matrices of the `count` intervals are equal bit for bit: `a`, `b`
    are (count, ...) arrays or `PerInterval`s, or None (`default_a`, `default_b` at every
    interval); compared a stretch at a time, two `PerInterval`s of the same model and times
    (two `PerInstant`s of the same key) without forming them."""
    if any(x is not None and len(x) != count for x in (a, b)):
        return False
    if isinstance(a, PerInstant) and isinstance(b, PerInstant):
        if a is b or (a.key is not None and a.key == b.key):
            return True
    if isinstance(a, PerInterval) and isinstance(b, PerInterval) and a.which == b.which:
        sa, sb = a.source, b.source
        same = sa.key is not None and sa.key == sb.key
        if sa is sb or (same and np.array_equal(sa.times, sb.times)):
            return True
    if a is None and b is None:
        return default_a.shape == default_b.shape and np.array_equal(default_a, default_b)
    for k0 in range(0, count, STRETCH):
        k1 = min(k0 + STRETCH, count)
        x = np.broadcast_to(default_a, (k1 - k0,) + default_a.shape) if a is None else a[k0:k1]
        y = np.broadcast_to(default_b, (k1 - k0,) + default_b.shape) if b is None else b[k0:k1]
        if x.shape != y.shape or not np.array_equal(x, y):
            return False
    return True
