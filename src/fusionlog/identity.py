"""Public API for identity fusion (Challa & Koks, Sadhana 2004): Bayes and Dempster-Shafer.

A thin re-export of the evidence modules of :mod:`fusionlog.core.identity` (``bayes``,
``dempster``, ``masses``); see there for the equations.
"""

from fusionlog.core.identity.bayes import bayes_fusion, bayes_fusion_posteriors
from fusionlog.core.identity.dempster import (
    MASS_TOL,
    MAX_FRAME_SIZE,
    ArrayCombination,
    belief_array,
    dempster_combine_array,
    plausibility_array,
)
from fusionlog.core.identity.masses import (
    Combination,
    array_to_mass,
    belief,
    dempster_combine,
    mass_to_array,
    plausibility,
    subset_index,
)

__all__ = [
    "MASS_TOL",
    "MAX_FRAME_SIZE",
    "ArrayCombination",
    "Combination",
    "array_to_mass",
    "bayes_fusion",
    "bayes_fusion_posteriors",
    "belief",
    "belief_array",
    "dempster_combine",
    "dempster_combine_array",
    "mass_to_array",
    "plausibility",
    "plausibility_array",
    "subset_index",
]
