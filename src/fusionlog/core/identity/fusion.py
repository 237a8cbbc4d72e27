"""Identity fusion over blocks of runs: BAYES and DS estimates from report indices (seed 004).

Challa & Koks (``shared/seeds/004_e832512ceaf07c5b.txt``). Reports come as indices (B, K+1, S):
for run b, step k and sensor s, the index of the report in that sensor's ``reports``; the index
len(reports) means "no report" at that step (no evidence). The estimate at k uses every report
at t <= k, vectorised over the runs of the block.

* ``BAYES``: posterior_k(c) proportional to prior(c) prod_{t<=k} prod_s confusion_s[c, r_{s,t}]:
  eqs. (36)-(37) with the sensors' likelihoods, applied recursively (the posterior is the next
  prior, eqs. 38/41); log-likelihoods are summed, then :func:`.bayes.bayes_fusion` normalises.
* ``DS``: report R of a sensor is the simple support function m(R) = reliability,
  m(frame) = 1 - reliability; every report is combined with Dempster's rule (eq. 47,
  :func:`.dempster.dempster_combine_array`) into the running mass function over the 2^N subsets.

What :func:`estimate` returns per run and step (``dim`` = :func:`dims`, names = :func:`columns`)
is what the estimates file's ``/estimates/<ARCH>`` carries:

=========  ======  ===========================================================================
``BAYES``  N       posterior probability of each class, in ``classes`` order
``DS``     2N + 2  Bel({c}) of each class, then Pl({c}) of each class, then the conflict K of
                   that step's combination, then the accumulated conflict 1 - prod_{t<=k}(1-K_t)
=========  ======  ===========================================================================

A run whose DS combination reaches total conflict (K = 1, possible only with reliability 1) has
NaN belief and plausibility from then on, per-step conflict 1 at that step and NaN after,
accumulated conflict 1.

Decisions (:func:`decision_weights`): BAYES the class of largest posterior; DS the class of
largest belief, ties broken by plausibility; remaining ties split evenly.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .bayes import bayes_fusion
from .dempster import belief_array, dempster_combine_array, plausibility_array
from .model import ARCHITECTURES, IdentitySensor, IdentitySystem

__all__ = [
    "TIE_TOL",
    "bayes_posteriors",
    "columns",
    "decision_weights",
    "dims",
    "ds_columns",
    "ds_combine",
    "estimate",
    "report_indices",
]

#: Two scores closer than this count as a tie in a decision.
TIE_TOL = 1e-12


def report_indices(values: np.ndarray, n: int, what: str, allow_nan: bool) -> np.ndarray:
    """Float indices (as stored in a log) -> int64, NaN -> n (the "no report" row).

    Raises ValueError naming `what` if a value is not an index 0..n-1 (or NaN where
    `allow_nan` is false).
    """
    v = values
    nan = np.isnan(v)
    if nan.any() and not allow_nan:
        raise ValueError(f"{what}: NaN where a class index is expected")
    ok = nan | ((v >= 0) & (v < n) & (v == np.floor(v)))
    if not ok.all():
        bad = float(v[~ok][0])  # a Python float: numpy 2 would print np.float64(...)
        raise ValueError(f"{what}: value {bad!r} is not an index 0..{n - 1}")
    return np.where(nan, n, v).astype(np.int64)


def bayes_posteriors(
    reports: np.ndarray,
    sensors: Sequence[IdentitySensor],
    prior: np.ndarray,
    run_offset: int = 0,
) -> np.ndarray:
    """Cumulative Bayes posteriors (B, K+1, N) from report indices (B, K+1, S).

    A report index equal to the sensor's number of reports means "no report" (likelihood 1).
    posterior_k ∝ prior · prod_{t<=k} prod_s P(r_{s,t} | class): eqs. (36)-(37) recursively;
    log-likelihoods are summed over sensors and time and scaled so that the largest class has
    likelihood 1, then :func:`bayes_fusion` applies the prior and normalises.
    Raises ValueError if the reports of some run have zero likelihood for every class (only
    possible under a model other than the one that simulated them); `run_offset` numbers the
    runs in that message.
    """
    B, K1, S = reports.shape
    n = np.asarray(prior).shape[-1]
    loglik = np.zeros((B, K1, n))
    with np.errstate(divide="ignore"):
        for s, sensor in enumerate(sensors):
            loglik += np.log(sensor.likelihood())[reports[..., s]]
    cum = np.cumsum(loglik, axis=1)
    top = cum.max(axis=-1, keepdims=True)
    if np.isneginf(top).any():
        b, k = (int(i) for i in np.argwhere(np.isneginf(top[..., 0]))[0])
        raise ValueError(
            f"run {run_offset + b}, step {k}: the reports have zero likelihood for every class "
            "under the model's confusion matrices"
        )
    lik = np.exp(cum - top)
    return bayes_fusion(lik[..., None, :], prior)


def ds_combine(
    reports: np.ndarray, sensors: Sequence[IdentitySensor], n_classes: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cumulative Dempster-Shafer combination of every report (eq. 47).

    reports: (B, K+1, S) report indices (the sensor's number of reports = no report). Starts
    from the vacuous mass function; at step k combines the running masses with each sensor's
    report mass (m(R) = reliability, m(frame) = 1 - reliability) by Dempster's rule.
    Returns Bel({c}) and Pl({c}) (B, K+1, N), the conflict K of step k's combination (B, K+1)
    and the accumulated conflict 1 - prod_{t<=k}(1 - K_t) (B, K+1). A run in total conflict
    (K = 1) has NaN Bel and Pl from then on, conflict 1 at that step and NaN after, and
    accumulated conflict 1.
    """
    B, K1, S = reports.shape
    size = 1 << n_classes
    tables = [s.mass_table(n_classes) for s in sensors]
    vacuous = np.zeros(size)
    vacuous[-1] = 1.0
    m = np.tile(vacuous, (B, 1))
    dead = np.zeros(B, dtype=bool)
    acc = np.zeros(B)
    bel = np.full((B, K1, n_classes), np.nan)
    pl = np.full((B, K1, n_classes), np.nan)
    conflict = np.full((B, K1), np.nan)
    accumulated = np.ones((B, K1))
    for k in range(K1):
        inputs = [tables[s][reports[:, k, s]] for s in range(S)]
        res = dempster_combine_array(m, *inputs, on_total_conflict="nan")
        newly = ~dead & ~np.isfinite(res.masses).all(axis=-1)
        live = ~dead & ~newly
        m = np.where(live[:, None], res.masses, vacuous)  # dead runs: a placeholder
        conflict[live, k] = res.conflict[live]
        conflict[newly, k] = 1.0
        acc = np.where(live, 1.0 - (1.0 - acc) * (1.0 - res.conflict), 1.0)
        accumulated[:, k] = acc
        dead |= newly
        if live.any():
            ml = m[live]
            for c in range(n_classes):
                bel[live, k, c] = belief_array(ml, 1 << c)
                pl[live, k, c] = plausibility_array(ml, 1 << c)
    return bel, pl, conflict, accumulated


def estimate(
    system: IdentitySystem, reports: np.ndarray, arch: str, run_offset: int = 0
) -> np.ndarray:
    """(B, K+1, dims(N)[arch]): architecture `arch`'s estimates from report indices (B, K+1, S).

    The rows of ``/estimates/<arch>`` (see the module docstring). Raises ValueError for an
    unknown architecture or reports the model rules out (BAYES, see :func:`bayes_posteriors`).
    """
    if arch == "BAYES":
        return bayes_posteriors(reports, system.sensors, system.prior, run_offset)
    if arch == "DS":
        bel, pl, kk, ka = ds_combine(reports, system.sensors, system.n)
        return np.concatenate([bel, pl, kk[..., None], ka[..., None]], -1)
    raise ValueError(f"unknown identity architecture {arch!r} (known: {', '.join(ARCHITECTURES)})")


def decision_weights(score: np.ndarray, tiebreak: np.ndarray | None = None) -> np.ndarray:
    """Weights (..., N) of the decided classes: 1/|T| on the tied maxima T of `score`, ties
    broken by `tiebreak` if given; all zero where `score` is not finite (no decision)."""
    ok = np.isfinite(score).all(axis=-1, keepdims=True)
    s = np.where(ok, score, 0.0)
    tied = s >= s.max(axis=-1, keepdims=True) - TIE_TOL
    if tiebreak is not None:
        t = np.where(tied & ok, tiebreak, -np.inf)
        tied &= t >= t.max(axis=-1, keepdims=True) - TIE_TOL
    w = tied / tied.sum(axis=-1, keepdims=True)
    return np.where(ok, w, 0.0)


def ds_columns(classes: Sequence[str]) -> list[str]:
    """Column names of ``/estimates/DS``."""
    return (
        [f"Bel({c})" for c in classes]
        + [f"Pl({c})" for c in classes]
        + ["conflict", "accumulated_conflict"]
    )


def columns(classes: Sequence[str], archs: Sequence[str]) -> dict[str, list[str]]:
    """Column names of ``/estimates/<ARCH>`` for each of `archs` (in that order)."""
    cols = {"BAYES": [f"P({c})" for c in classes], "DS": ds_columns(classes)}
    return {a: cols[a] for a in archs}


def dims(n: int) -> dict[str, int]:
    """Values per run of ``/estimates/<ARCH>`` for N = `n` classes."""
    return {"BAYES": n, "DS": 2 * n + 2}
