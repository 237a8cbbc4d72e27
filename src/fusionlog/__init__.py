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
#: `fusionlog.export` (`fusionlog.api_export`): a recording's trajectory as TUM, KITTI or CSV
_EXPORT = ("export",)

#: what the API raises on bad input: FusionlogError (ValidationError for a scenario, and
#: NumericalError for numbers that cannot be computed with, are FusionlogErrors)
__all__ = [*_API, *_EXPORT, "identify", "FusionlogError", "NumericalError", "ValidationError"]


def __getattr__(name: str):
    if name == "identify":  # `fusionlog.stages.identify`: noise from the data
        from .stages.identify import identify

        return identify
    if name in _API:
        from . import api

        return getattr(api, name)
    if name in _EXPORT:
        from . import api_export

        return getattr(api_export, name)
    raise AttributeError(f"module 'fusionlog' has no attribute {name!r}")
