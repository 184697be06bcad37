"""Loose clothing on a raw scan: how far the scan stands off a fitted body over each vertex
(:func:`clothing_field`), whether that looks like clothing (:func:`looks_clothed`), and the scan moved in by
it onto the body under the cloth (:func:`under_cloth`) for the registration.

Loose clothing stands off the skin smoothly and only outwards, over large regions (a shirt over the trunk
and upper arms, trousers over the thighs), while it lies on the skin elsewhere (face, hands, where a
garment is tight). A fit that treats the cloth as skin inflates the body and places it badly; the scan fit
detects the cloth from the signed residuals of its first fit (a consistent outward offset over a large part
of the surface, which noise, holes and a single view do not give: their residuals are small or
symmetric about zero), fits the body again with a one-sided loss that keeps it inside the cloth
(:func:`.losses.chamfer_term` with ``cloth_sigma_mm``), and registers the body under the cloth: the
non-rigid refinement fits the scan points moved in along the body's normals by the clothing offset, so
that it refines the surface where the cloth lies on the skin and keeps the fitted body where it does not.
The offset itself is the clothing layer, reported alongside the registration.

The body fitted inside the clothing, close to the scan where the cloth is tight, follows A. O. Balan and
M. J. Black, "The Naked Truth: Estimating Body Shape Under Clothing", European Conference on Computer Vision
(ECCV), 2008; the clothing as a per-vertex offset layer on the body follows G. Pons-Moll, S. Pujades, S. Hu
and M. J. Black, "ClothCap: Seamless 4D Clothing Capture and Retargeting", ACM Transactions on Graphics
36(4), 2017. The offset's local median is the robust location estimate of F. R. Hampel, "The influence
curve and its role in robust estimation", Journal of the American Statistical Association 69(346), 1974.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.surface import vertex_normals


@dataclass(frozen=True)
class ClothingField:
    """How far the scan stands off a fitted body: offset (V,) metres, each vertex's outward offset (the
    median signed distance, along the points' nearest vertex normals, of the scan points nearest it;
    zero where no scan point is near); observed (V,) bool, the vertices with scan points near;
    area (V,) the surface area each vertex stands for (m^2)."""

    offset: np.ndarray
    observed: np.ndarray
    area: np.ndarray

    def clothed_fraction(self, threshold: float) -> float:
        """The share of the observed surface area over which the scan stands more than ``threshold``
        (m) outside the body."""
        seen = self.area * self.observed
        total = float(seen.sum())
        return float(seen[self.offset > threshold].sum() / total) if total > 0 else 0.0

    def bare_offset(self, bare: np.ndarray) -> float:
        """The median offset (m) over the observed vertices of ``bare`` (V,) bool, the parts cloth leaves
        bare (head, hands); 0 when none of them is observed."""
        keep = bare & self.observed
        return float(np.median(self.offset[keep])) if keep.any() else 0.0

    def summary(self, threshold: float) -> dict[str, float]:
        """The report's entries (mm, and the share of the observed surface clothed beyond ``threshold``)."""
        seen = self.observed & (self.offset > threshold)
        weights = self.area * seen
        mean = float((self.offset * weights).sum() / weights.sum()) if weights.sum() > 0 else 0.0
        return {
            "clothed_fraction": round(self.clothed_fraction(threshold), 4),
            "clothing_threshold_mm": round(threshold * 1000.0, 1),
            "clothing_mean_mm": round(mean * 1000.0, 2),
            "clothing_max_mm": round(float(self.offset[self.observed].max(initial=0.0)) * 1000.0, 2),
        }


def _areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) a third of the area of the faces around each vertex of the mesh (V, 3), (F, 3)."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.bincount(faces.ravel(), np.repeat(area / 3.0, 3), minlength=len(vertices))


def signed_offsets(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each scan point's (N, 3) signed distance (N,) from the body (V, 3), (F, 3) along the normal of its
    nearest vertex (positive outside), its distance (N,) to that vertex and the vertex (N,)."""
    normals = vertex_normals(vertices, faces)
    distance, nearest = PointTree(vertices).query(points)
    signed = ((points - vertices[nearest]) * normals[nearest]).sum(1)
    return signed, distance, nearest


BARE_BODIES = ("head", "hand")  # skeleton bodies (name prefixes) whose skin loose clothing leaves bare


def bare_vertices(model: BodyModel) -> np.ndarray:
    """(V,) bool: the template vertices whose skin loose clothing leaves bare, by the skeleton body that
    weighs most on each (:data:`BARE_BODIES`)."""
    owner = model.vertex_bodies
    bare = np.array([name.startswith(BARE_BODIES) for name in model.skeleton.body_names])
    return bare[owner]


def clothing_field(
    vertices: np.ndarray,
    faces: np.ndarray,
    points: np.ndarray,
    neighbours: int = 48,
    reach: float = 0.08,
    seen: np.ndarray | None = None,
) -> ClothingField:
    """The scan's outward offset over a fitted body (V, 3), (F, 3): for each vertex the median of the
    signed offsets (:func:`signed_offsets`) of its ``neighbours`` nearest scan points (N, 3), counted where
    at least half of them lie within ``reach`` (m) of the vertex. The median of a few dozen points spreads
    the offset over about 4 cm of a 1 cm-thinned scan, so that noise (symmetric) and stray points leave it
    near zero, while cloth (outward over whole regions) does not. ``seen``: (V,) bool, the vertices a
    single view can show (the others count as not observed)."""
    signed = signed_offsets(vertices, faces, points)[0]
    k = min(neighbours, len(points))
    d, idx = PointTree(points).query(vertices, k=k)
    d, idx = d.reshape(len(vertices), k), idx.reshape(len(vertices), k)
    near = d < reach
    values = np.where(near, signed[np.minimum(idx, len(points) - 1)], np.nan)
    observed = near.sum(1) >= k // 2
    if seen is not None:
        observed &= seen
    offset = np.zeros(len(vertices))
    if observed.any():
        offset[observed] = np.nanmedian(values[observed], axis=1)
    offset = np.where(observed, np.maximum(offset, 0.0), 0.0)
    return ClothingField(offset, observed, _areas(vertices, faces))


def looks_clothed(field: ClothingField, threshold: float, min_fraction: float) -> bool:
    """Whether the scan stands more than ``threshold`` (m) outside the body over more than
    ``min_fraction`` of the observed surface: loose clothing, not noise or a fit's small misfit."""
    return field.clothed_fraction(threshold) > min_fraction


def under_cloth(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, field: ClothingField
) -> np.ndarray:
    """The scan points (N, 3) moved in along the normal of their nearest vertex of the body (V, 3), (F, 3)
    by the clothing offset there (``field``), never past the body: where the cloth stands off the skin
    they land on the fitted body, where it lies on the skin they stay."""
    signed, _, nearest = signed_offsets(vertices, faces, points)
    normals = vertex_normals(vertices, faces)
    shift = np.clip(np.minimum(field.offset[nearest], signed), 0.0, None)
    return points - shift[:, None] * normals[nearest]
