"""``[estimate] ci_criterion``: the cost covariance intersection minimises (DESIGN.md "Unknown
correlation and the bound check"), ``"trace"`` (tr P, the default) or ``"det"`` (det P, what
MATLAB's ``fusecovint`` minimises by default). Read wherever [estimate] is (scenarios, model
and replay files) into `System.ci_criterion`, which every backend's CI takes."""

from __future__ import annotations

from typing import Any

from . import toml
from .toml import Ctx

__all__ = ["CI_CRITERIA", "ci_criterion"]

#: Values of [estimate] ci_criterion.
CI_CRITERIA: tuple[str, ...] = ("trace", "det")


def ci_criterion(ctx: Ctx, doc: dict[str, Any]) -> str:
    """[estimate] ci_criterion ("trace" when absent); an unknown value names the known ones."""
    est = doc.get("estimate")
    if not isinstance(est, dict) or "ci_criterion" not in est:
        return "trace"
    value = toml.string(ctx, est["ci_criterion"], "estimate.ci_criterion")
    if value not in CI_CRITERIA:
        raise ctx.err("estimate.ci_criterion", f"unknown criterion {value!r} (known: trace, det)")
    return value
