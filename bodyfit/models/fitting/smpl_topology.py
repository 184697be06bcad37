"""Deprecated: moved to :mod:`bodyfit.models.fitting.registered.smpl_topology`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.registered.smpl_topology import (
    ASSET,
    MAX_GAP_M,
    SCAN_SAMPLES,
    SMPL_TO_BODY,
    SMPL_VERTICES,
    SOURCE_DIR,
    SOURCES,
    TopologyMap,
    build_smpl_topology,
    fit_smpl_meshes,
    read_obj,
    refine_smpl_fit,
    smpl_map,
    t_pose,
)

__all__ = [
    "ASSET",
    "MAX_GAP_M",
    "SCAN_SAMPLES",
    "SMPL_TO_BODY",
    "SMPL_VERTICES",
    "SOURCES",
    "SOURCE_DIR",
    "TopologyMap",
    "build_smpl_topology",
    "fit_smpl_meshes",
    "read_obj",
    "refine_smpl_fit",
    "smpl_map",
    "t_pose",
]
