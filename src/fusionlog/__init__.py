"""fusionlog: multi-sensor state estimation experiments logged to MCAP and Rerun."""

__version__ = "0.1.0"

from .errors import FusionlogError, NumericalError, ValidationError

#: The Python API (`fusionlog.api`), loaded on first use: `import fusionlog.cli` stays light.
_API = (
    "Estimate",
    "Estimates",
    "Evaluation",
    "Simulation",
    "estimate",
    "evaluate",
    "load",
    "simulate",
)

#: what the API raises on bad input: FusionlogError (ValidationError for a scenario, and
#: NumericalError for numbers that cannot be computed with, are FusionlogErrors)
__all__ = [*_API, "identify", "FusionlogError", "NumericalError", "ValidationError"]


def __getattr__(name: str):
    if name == "identify":  # `fusionlog.stages.identify`: noise from the data
        from .stages.identify import identify

        return identify
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'fusionlog' has no attribute {name!r}")
