"""The late-measurement keys (DESIGN.md "Late measurements"): ``[[sensors]] latency`` and
``[estimate] late``.

``latency`` = seconds (>= 0, finite; a measurement taken at t arrives at t + latency) or a
table ``{min = a, max = b}`` (0 <= a <= b: each measurement's delay uniform in [a, b], drawn
from the seed). ``late`` = "reprocess" (default) | "retrodict" | "neglect": what the filters
do with a measurement that arrives after a later one (`core.latency`).
"""

from __future__ import annotations

from typing import Any

from fusionlog.core.late_policy import LATE_POLICIES
from fusionlog.core.timing import MAX_PERIOD_S

from . import toml
from .toml import Ctx

__all__ = ["LATE_POLICIES", "late_section", "latency_dict", "sensor_latency"]


def _seconds(ctx: Ctx, v: Any, where: str) -> float:
    x = toml.number(ctx, v, where)
    if x < 0:
        raise ctx.err(where, f"must be >= 0, got {toml.fmt(x)}")
    if x > MAX_PERIOD_S:
        raise ctx.err(where, f"{toml.fmt(x)} s is beyond 1e+09 s")
    return x


def sensor_latency(ctx: Ctx, t: dict[str, Any], where: str) -> tuple[float, float]:
    """A sensor table's ``latency`` as (min, max) seconds; (0, 0) when absent."""
    if "latency" not in t:
        return (0.0, 0.0)
    v, key = t["latency"], f"{where}.latency"
    if isinstance(v, dict):
        toml.check_keys(ctx, v, key, ("min", "max"), required=("min", "max"))
        lo, hi = _seconds(ctx, v["min"], f"{key}.min"), _seconds(ctx, v["max"], f"{key}.max")
        if lo > hi:
            raise ctx.err(key, f"min ({toml.fmt(lo)} s) > max ({toml.fmt(hi)} s)")
        return (lo, hi)
    x = _seconds(ctx, v, key)
    return (x, x)


def latency_dict(latency: tuple[float, float]) -> dict[str, Any]:
    """The ``latency`` key of a sensor table (empty when on time)."""
    lo, hi = latency
    if hi == 0.0:
        return {}
    return {"latency": float(lo) if lo == hi else {"min": float(lo), "max": float(hi)}}


def late_section(ctx: Ctx, doc: dict[str, Any]) -> str:
    """``[estimate] late``: the policy for late measurements (default "reprocess")."""
    est = doc.get("estimate")
    if not isinstance(est, dict) or "late" not in est:
        return LATE_POLICIES[0]
    late = toml.string(ctx, est["late"], "estimate.late")
    if late not in LATE_POLICIES:
        raise ctx.err(
            "estimate.late", f"unknown policy {late!r} (known: {', '.join(LATE_POLICIES)})"
        )
    return late
