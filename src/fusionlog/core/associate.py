"""Truth samples at the estimator's instants (DESIGN.md, "Recorded logs, more formats").

A reference system (motion capture, RTK) samples at its own times, which are rarely the times
at which the sensors measure. ``associate`` gives the truth at each instant:

- ``"exact"``: the sample whose time equals the instant;
- ``"nearest"``: the closest sample within ``max_diff_ns`` (a tie goes to the earlier sample);
- ``"interpolate"``: linear between the samples just before and just after the instant (an
  equal time is that sample), both within ``max_diff_ns`` of it.

Times are integer nanoseconds, so "equal" and "within" are exact. An instant with no usable
sample has no truth (its row is NaN): the truth metrics skip it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["associate"]


def associate(
    instants: np.ndarray, times: np.ndarray, values: np.ndarray, match: str, max_diff_ns: int
) -> np.ndarray:
    """(len(instants), d) truth values at ``instants`` (NaN where none); ``times`` (N,) sorted
    int64 sample times, ``values`` (N, d)."""
    instants = np.asarray(instants, dtype=np.int64)
    times = np.asarray(times, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    out = np.full((len(instants), values.shape[1]), np.nan)
    if len(times) == 0:
        return out
    # index of the first sample at or after each instant
    hi = np.searchsorted(times, instants, side="left")
    hi_ok = hi < len(times)
    hic = np.minimum(hi, len(times) - 1)
    exact = hi_ok & (times[hic] == instants)
    if match == "exact":
        out[exact] = values[hic[exact]]
        return out
    lo = np.maximum(hi - 1, 0)
    lo_ok = hi > 0
    # differences as Python-exact int64 (times within one log: no overflow)
    d_lo = np.where(lo_ok, instants - times[lo], np.iinfo(np.int64).max)
    d_hi = np.where(hi_ok, times[hic] - instants, np.iinfo(np.int64).max)
    if match == "nearest":
        pick = np.where(d_lo <= d_hi, lo, hic)
        ok = np.minimum(d_lo, d_hi) <= max_diff_ns
        out[ok] = values[pick[ok]]
        return out
    if match != "interpolate":
        raise ValueError(f"unknown match {match!r}")
    both = lo_ok & hi_ok & (d_lo <= max_diff_ns) & (d_hi <= max_diff_ns) & ~exact
    span = (times[hic] - times[lo]).astype(np.float64)
    w = np.where(both, d_lo / np.where(span > 0, span, 1.0), 0.0)[:, None]
    inter = values[lo] * (1.0 - w) + values[hic] * w
    out[both] = inter[both]
    out[exact] = values[hic[exact]]
    return out
