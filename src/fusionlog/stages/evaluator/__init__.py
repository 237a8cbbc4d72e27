"""The state kind's evaluator as parts with one interface (`parts.Part`: add a block, merge
what was computed elsewhere, summarise): the Monte Carlo metrics, the exact analysis, NIS and
availability, the PCRB, sample runs and the plane view, composed by `StateEvaluator`."""

from .exact_part import exact_setup
from .state_evaluator import SensorLog, StateEvaluator

__all__ = ["SensorLog", "StateEvaluator", "exact_setup"]
