"""Deprecated: moved to :mod:`bodyfit.models.fitting.scan.limb_search`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.scan.limb_search import (
    EMPTY_WEIGHT,
    LIMB_APART_M,
    LIMB_REFINE_ITERATIONS,
    LIMB_REFINED,
    LIMB_SEARCH,
    LIMB_STARTS,
    LIMB_SWEEPS,
    LIMB_TRUNCATION_M,
    LOOSE_POINTS,
    ON_SCAN_FRACTION,
    REACH_WEIGHT,
    Grids,
    Hypotheses,
    LimbSearch,
    Mapper,
    distinct,
    grid_vertices,
    search_grids,
)

__all__ = [
    "EMPTY_WEIGHT",
    "LIMB_APART_M",
    "LIMB_REFINED",
    "LIMB_REFINE_ITERATIONS",
    "LIMB_SEARCH",
    "LIMB_STARTS",
    "LIMB_SWEEPS",
    "LIMB_TRUNCATION_M",
    "LOOSE_POINTS",
    "ON_SCAN_FRACTION",
    "REACH_WEIGHT",
    "Grids",
    "Hypotheses",
    "LimbSearch",
    "Mapper",
    "distinct",
    "grid_vertices",
    "search_grids",
]
