"""Tolerances from the conditioning of the problem, not from one machine's rounding.

Two exact computations of the same quantity by different paths (the per-run and the shared
builders, LU and Cholesky, BLAS kernels that sum in another order) differ by rounding errors
amplified by the conditioning of what they solve: the information matrix of a filter that
started without a prior, the generalised Millman system (singular in the paper's example).
A tolerance tuned on one machine's summation order fails on another (OpenBLAS picks its
kernels by CPU). Here the amplification is measured instead: the model's entries are changed
at rounding level (a few ulps, as a different summation order changes them) and the
computation repeated; how far that moves each result is the problem's own sensitivity to
rounding, whichever machine runs it. A backward-stable computation on any machine stays
within a small multiple of it (`SAFETY`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from fusionlog.core.model import System

EPS = np.finfo(float).eps
#: Relative size of the entry changes: a few ulps, as rounding leaves them.
REL = 4 * EPS
#: A backward-stable result stays within this multiple of the measured sensitivity.
SAFETY = 20.0
#: A step whose result moves by more than this (relative) under rounding-level changes has a
#: condition number above ~1e9: its answer is not decided by working precision (a weight that
#: jumps between corners, an information matrix singular to rounding). Such steps are not
#: compared.
JUMP = 1e-6


def perturbed(system: System, rng: np.random.Generator, rel: float = REL) -> System:
    """`system` with every model entry multiplied by (1 + rel u), u uniform in [-1, 1];
    covariances stay symmetric."""

    def p(A, sym=False):
        if A is None:
            return None
        A = np.asarray(A, dtype=float)
        d = A * rel * rng.uniform(-1.0, 1.0, A.shape)
        if sym:
            d = 0.5 * (d + np.swapaxes(d, -1, -2))
        return A + d

    sensors = tuple(dataclasses.replace(s, H=p(s.H), R=p(s.R, True)) for s in system.sensors)

    def dist(d):
        return None if d is None else dataclasses.replace(d, mean=p(d.mean), cov=p(d.cov, True))

    prior = dist(system.prior)
    # The truth's initial distribution stays the filters' prior where it was (no bias appears).
    initial = prior if system.initial is system.prior else dist(system.initial)
    return dataclasses.replace(
        system,
        F=p(system.F),
        Q=p(system.Q, True),
        sensors=sensors,
        prior=prior,
        initial=initial,
        cross_R={k: p(v) for k, v in system.cross_R.items()},
        Fs=p(system.Fs),
        Qs=p(system.Qs, True),
        Rs=p(system.Rs, True),
    )


@dataclasses.dataclass
class Sensitivity:
    """How far rounding-level changes of the model move each field of a result.

    Fields are arrays with the steps on their first axis. `unsettled` (K+1,): the steps at
    which some field's definedness (NaN or not) flips or its value jumps (`JUMP`) under such
    changes — a decision made at rounding level (an information matrix singular to working
    precision, covariance intersection's weights jumping to another corner), which two
    machines may make either way; those steps are not compared. `rel[f]`: the largest change
    of field f at the other steps, relative to its largest entry."""

    rel: dict[str, float]
    unsettled: np.ndarray

    def tolerance(self, field: str, floor: float = 1e-12) -> float:
        return max(floor, SAFETY * self.rel[field])


def sensitivity(
    compute: Callable[[System], object],
    system: System,
    fields: tuple[str, ...],
    trials: int = 4,
    seed: int = 0,
) -> Sensitivity:
    """The sensitivity of `compute(system)`'s `fields` (arrays with the steps first) to
    rounding-level changes of the model (`perturbed`), over a few random changes."""
    rng = np.random.default_rng(seed)
    base = compute(system)
    others = [compute(perturbed(system, rng)) for _ in range(trials)]
    steps = np.shape(getattr(base, fields[0]))[0]
    unsettled = np.zeros(steps, bool)
    for other in others:
        for f in fields:
            a = np.asarray(getattr(base, f)).reshape(steps, -1)
            b = np.asarray(getattr(other, f)).reshape(steps, -1)
            unsettled |= (np.isnan(a) != np.isnan(b)).any(axis=1)
            # Relative to the step's largest entry, or to a millionth of the field's (a field
            # that is zero at a step, as the bias of a filter whose prior is the truth's).
            scale = np.nanmax(np.abs(a), axis=1, initial=0.0)
            scale = np.maximum(scale, 1e-6 * scale.max(initial=0.0))
            change = np.nanmax(np.abs(a - b), axis=1, initial=0.0)
            unsettled |= change > JUMP * scale
    rel = dict.fromkeys(fields, 0.0)
    for other in others:
        for f in fields:
            a = np.asarray(getattr(base, f))[~unsettled]
            b = np.asarray(getattr(other, f))[~unsettled]
            ok = ~np.isnan(a) & ~np.isnan(b)
            scale = np.abs(a[ok]).max(initial=0.0)
            if scale > 0:
                rel[f] = max(rel[f], float(np.abs(a[ok] - b[ok]).max() / scale))
    return Sensitivity(rel, unsettled)


def assert_agree(actual, desired, tol: float, unsettled: np.ndarray | None, what: str) -> None:
    """The same undefined (NaN) entries and the entries defined in both to `tol` relative to
    the largest one, at every step (first axis) but the `unsettled` ones."""
    actual, desired = np.asarray(actual), np.asarray(desired)
    if unsettled is not None:
        actual, desired = actual[~unsettled], desired[~unsettled]
    np.testing.assert_array_equal(np.isnan(actual), np.isnan(desired), err_msg=what)
    ok = ~np.isnan(desired)
    scale = np.abs(desired[ok]).max(initial=0.0)
    np.testing.assert_allclose(actual[ok], desired[ok], rtol=tol, atol=tol * scale, err_msg=what)
