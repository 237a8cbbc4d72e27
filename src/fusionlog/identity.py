"""Public API for identity fusion (Challa & Koks, seed 004): Bayes and Dempster-Shafer.

A thin re-export of :mod:`fusionlog.core.identity`; see there for the equations.
"""

from fusionlog.core.identity import (
    MASS_TOL,
    MAX_FRAME_SIZE,
    ArrayCombination,
    Combination,
    array_to_mass,
    bayes_fusion,
    bayes_fusion_posteriors,
    belief,
    belief_array,
    dempster_combine,
    dempster_combine_array,
    mass_to_array,
    plausibility,
    plausibility_array,
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
