"""Deprecated: moved to :mod:`bodyfit.models.fitting.common.surface`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.common.surface import (
    NormalOperators,
    closest_on_surface,
    closest_on_triangles,
    coarse_faces,
    face_incidence,
    laplacian,
    point_to_surface,
    point_triangle_distance,
    vertex_faces,
    vertex_normals,
)

__all__ = [
    "NormalOperators",
    "closest_on_surface",
    "closest_on_triangles",
    "coarse_faces",
    "face_incidence",
    "laplacian",
    "point_to_surface",
    "point_triangle_distance",
    "vertex_faces",
    "vertex_normals",
]
