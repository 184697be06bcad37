"""Fitting registered meshes (our topology, or SMPL's through :mod:`.smpl_topology`): the fitter's pipeline
is in :mod:`.fitter`, its stages and what they select in :mod:`.stages`, its rigid start in :mod:`.start`
and the Gauss-Newton metric and preconditioner of its variables in :mod:`.metric`.

Deprecated: the module ``bodyfit.models.fitting.registered`` moved to
:mod:`bodyfit.models.fitting.registered.fitter`;
this path will be removed in the next release as a module path (the names re-exported here from
:mod:`bodyfit.models.fitting.registered.fitter` go; the package stays).
"""

from bodyfit.models.fitting.registered.fitter import (
    CONFIDENT_MEAN_MM,
    CORE_DOF_PREFIXES,
    DEFAULT_STAGES,
    MIN_PART_VERTICES,
    MIN_PART_WEIGHT,
    STAGE_METRIC_DAMPING,
    TRUNK_BODIES,
    TRUNK_DOF_PREFIXES,
    UPPER_BODY_M,
    UPPER_DOF_PREFIXES,
    BodyFit,
    DataTerm,
    RegisteredFitConfig,
    RegisteredFitter,
    Stage,
    State,
    farthest_point_subset,
    vertex_term,
)

__all__ = [
    "CONFIDENT_MEAN_MM",
    "CORE_DOF_PREFIXES",
    "DEFAULT_STAGES",
    "MIN_PART_VERTICES",
    "MIN_PART_WEIGHT",
    "STAGE_METRIC_DAMPING",
    "TRUNK_BODIES",
    "TRUNK_DOF_PREFIXES",
    "UPPER_BODY_M",
    "UPPER_DOF_PREFIXES",
    "BodyFit",
    "DataTerm",
    "RegisteredFitConfig",
    "RegisteredFitter",
    "Stage",
    "State",
    "farthest_point_subset",
    "vertex_term",
]
