"""Triangle-mesh geometry for scan fitting: normals, point-to-surface distances, the mesh Laplacian.

Pure functions (numpy and scipy; torch for the per-triangle arithmetic) on (V, 3) vertices and (F, 3)
counter-clockwise faces, in whatever length unit the caller uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import dijkstra

from bodyfit.models.fitting.common.nearest import PointTree


def face_incidence(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, F) sparse matrix, 1 where vertex v is a corner of face f: ``incidence @ x`` sums per-face rows
    x (F, ...) onto each face's corners."""
    f = np.asarray(faces, np.int64)
    corners = f.reshape(-1)
    owner = np.repeat(np.arange(len(f)), 3)
    return sp.csr_matrix((np.ones(len(corners)), (corners, owner)), shape=(n_vertices, len(f)))


@dataclass(frozen=True)
class NormalOperators:
    """The sparse matrices :func:`vertex_normals` applies, for meshes sharing faces (F, 3) and V vertices:
    edges (2F, V), each face's edges b - a (rows 0..F-1) and c - a (rows F..2F-1) from its corners; incidence
    (V, F) from :func:`face_incidence`. Both in ``dtype`` (a fitting loop's float32, or float64)."""

    edges: sp.csr_matrix
    incidence: sp.csr_matrix

    @classmethod
    def of(cls, faces: np.ndarray, n_vertices: int, dtype: type = np.float64) -> NormalOperators:
        f = np.asarray(faces, np.int64)
        F = len(f)
        rows = np.repeat(np.arange(2 * F), 2)
        cols = np.concatenate([f[:, [0, 1]], f[:, [0, 2]]]).reshape(-1)
        signs = np.tile([-1.0, 1.0], 2 * F)
        edges = sp.csr_matrix((signs, (rows, cols)), shape=(2 * F, n_vertices))
        return cls(edges.astype(dtype), face_incidence(f, n_vertices).astype(dtype))


def vertex_normals(
    vertices: np.ndarray, faces: np.ndarray, operators: NormalOperators | None = None
) -> np.ndarray:
    """Area-weighted unit vertex normals (..., V, 3) of meshes (..., V, 3) sharing faces (F, 3); zero for
    unused vertices. ``operators``: :class:`NormalOperators` of the faces, when the caller keeps them.
    Float32 vertices (a fitting loop's) are computed in float32, others in float64. The edges and the sums
    onto the corners are sparse products over the vertices of all meshes at once, which is faster than
    fancy-indexing the corners."""
    v = np.asarray(vertices)
    v = v if v.dtype == np.float32 else v.astype(np.float64)
    ops = NormalOperators.of(faces, v.shape[-2]) if operators is None else operators
    F, batch = len(faces), v.shape[:-2]
    columns = np.moveaxis(v, -2, 0).reshape(v.shape[-2], -1)  # (V, ... * 3)
    e = (ops.edges.astype(v.dtype, copy=False) @ columns).reshape(2, F, *batch, 3)
    cross = np.cross(e[0], e[1])  # (F, ..., 3): twice each face's area along its normal
    summed = ops.incidence.astype(v.dtype, copy=False) @ cross.reshape(F, -1)
    acc = np.moveaxis(summed.reshape(-1, *batch, 3), 0, -2)
    norm = np.linalg.norm(acc, axis=-1, keepdims=True)
    return np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0)


def coarse_faces(vertices: np.ndarray, faces: np.ndarray, subset: np.ndarray) -> np.ndarray:
    """Faces (F', 3) of a coarser mesh on the vertices ``subset`` (S,) of a mesh (V, 3), (F, 3), numbered as
    in ``subset``: every vertex goes to the subset vertex nearest along the mesh's edges (its region), and
    each face whose corners lie in three different regions gives the triangle of those regions, oriented
    as the face (the dual of the regions, once per triangle). On a subset spread over the surface (a
    farthest-point sample) the coarse mesh's normals (:func:`vertex_normals`) follow the fine one's, and are
    a function of the subset's vertices alone. The regions come from one multi-source shortest-path search
    (E. W. Dijkstra, "A note on two problems in connexion with graphs", Numerische Mathematik 1, 1959)."""
    f = np.asarray(faces, np.int64)
    V = len(vertices)
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    graph = sp.csr_matrix((length, (edges[:, 0], edges[:, 1])), shape=(V, V))
    _, _, source = dijkstra(graph, directed=False, indices=subset, min_only=True, return_predecessors=True)
    position = np.full(V, -1, np.int64)
    position[subset] = np.arange(len(subset))
    # (F, 3); -1 on a part of the mesh no subset vertex reaches (dijkstra marks it with a negative source)
    region = np.where(source >= 0, position[np.maximum(source, 0)], -1)[f]
    split = (region[:, 0] != region[:, 1]) & (region[:, 1] != region[:, 2]) & (region[:, 2] != region[:, 0])
    tri = region[split & (region >= 0).all(1)]
    _, first = np.unique(np.sort(tri, axis=1), axis=0, return_index=True)
    return tri[np.sort(first)]


def vertex_faces(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V, K) the faces around every vertex, padded with -1 (K = the largest vertex degree)."""
    f = np.asarray(faces, np.int64)
    owner = f.reshape(-1)
    face_of = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(owner, kind="stable")
    owner, face_of = owner[order], face_of[order]
    counts = np.bincount(owner, minlength=n_vertices)
    out = np.full((n_vertices, max(int(counts.max()), 1)), -1, np.int64)
    slot = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    out[owner, slot] = face_of
    return out


def _segment_distance2(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distance (...,) from points p to segments ab, all (..., 3)."""
    ab = b - a
    t = (((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-300)).clamp(0.0, 1.0)
    d = p - (a + t[..., None] * ab)
    return (d * d).sum(-1)


def point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance (...,) from points p (..., 3) to triangles tri (..., 3, 3), broadcast against each other: to
    the plane when the projection falls inside, else to the nearest edge (float64, in torch's threads)."""
    P = torch.as_tensor(p, dtype=torch.float64)
    T = torch.as_tensor(tri, dtype=torch.float64)
    a, b, c = T[..., 0, :], T[..., 1, :], T[..., 2, :]
    n = torch.linalg.cross(b - a, c - a)
    n2 = (n * n).sum(-1).clamp_min(1e-300)
    # Barycentric coordinates of the projection (signed sub-areas over the full area).
    u = (torch.linalg.cross(c - b, P - b) * n).sum(-1) / n2
    v = (torch.linalg.cross(a - c, P - c) * n).sum(-1) / n2
    inside = (u >= 0) & (v >= 0) & (u + v <= 1)
    plane2 = ((P - a) * n).sum(-1) ** 2 / n2
    edge2 = torch.minimum(
        torch.minimum(_segment_distance2(P, a, b), _segment_distance2(P, b, c)), _segment_distance2(P, c, a)
    )
    return torch.where(inside, plane2, edge2).sqrt().numpy()


def closest_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (..., 3) of the point of each triangle tri (..., 3, 3) closest to p (..., 3):
    the projection when it falls inside, else the nearest point of the nearest edge."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    n = np.cross(b - a, c - a)
    n2 = np.maximum((n * n).sum(-1), 1e-300)
    u = (np.cross(c - b, p - b) * n).sum(-1) / n2
    v = (np.cross(a - c, p - c) * n).sum(-1) / n2
    inside = np.stack([u, v, 1.0 - u - v], -1)
    best = inside
    best_d2 = np.where(
        (inside >= 0).all(-1), ((p - np.einsum("...k,...kd->...d", inside, tri)) ** 2).sum(-1), np.inf
    )
    for i, j in ((0, 1), (1, 2), (2, 0)):
        e = tri[..., j, :] - tri[..., i, :]
        t = np.clip(((p - tri[..., i, :]) * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-300), 0.0, 1.0)
        w = np.zeros((*p.shape[:-1], 3))
        w[..., i], w[..., j] = 1.0 - t, t
        d2 = ((p - np.einsum("...k,...kd->...d", w, tri)) ** 2).sum(-1)
        better = d2 < best_d2
        best = np.where(better[..., None], w, best)
        best_d2 = np.where(better, d2, best_d2)
    return best


def closest_on_surface(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point (N, 3), the closest surface point among the triangles around its nearest vertex
    (exact except where a far vertex's triangle passes closer, which needs a badly shaped mesh).

    Returns:
        face index (N,), barycentric coordinates in that face (N, 3), distance (N,).
    """
    ring = vertex_faces(faces, len(vertices))
    _, nearest = PointTree(vertices).query(points)
    tri_all = vertices[faces]
    face = np.zeros(len(points), np.int64)
    bary = np.zeros((len(points), 3))
    dist = np.full(len(points), np.inf)
    for k in range(ring.shape[1]):
        f = ring[nearest, k]
        ok = np.flatnonzero(f >= 0)
        w = closest_on_triangles(points[ok], tri_all[f[ok]])
        d = np.linalg.norm(points[ok] - np.einsum("nk,nkd->nd", w, tri_all[f[ok]]), axis=1)
        better = d < dist[ok]
        rows = ok[better]
        face[rows], bary[rows], dist[rows] = f[ok][better], w[better], d[better]
    return face, bary, dist


def _face_forms(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each face's barycentric coordinates u, v (of corners a, b) of a point's projection and its signed
    height above the plane as affine functions of the point p (3,): ``forms[f] @ p - offsets[f]``.
    Args: the faces' corners a, b, c (F, 3), float64. Returns forms (F, 3, 3) and offsets (F, 3)."""
    n = torch.linalg.cross(b - a, c - a)
    n2 = (n * n).sum(-1, keepdim=True).clamp_min(1e-300)
    # u = ((c - b) x (p - b)) . n / |n|^2 = (p - b) . (n x (c - b)) / |n|^2, and likewise for v
    gu = torch.linalg.cross(n, c - b) / n2
    gv = torch.linalg.cross(n, a - c) / n2
    unit = n / n2.sqrt()
    offsets = torch.stack([(b * gu).sum(-1), (c * gv).sum(-1), (a * unit).sum(-1)], 1)
    return torch.stack([gu, gv, unit], 1), offsets


def point_to_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance (N,) from each point (N, 3) to the mesh surface: to the nearest of the triangles around its
    nearest vertex, as in :func:`closest_on_surface` (float64, in torch's threads). A point whose projection
    falls inside a triangle is at its height above the plane; otherwise the triangle's nearest point lies on
    an edge the point sees from outside (an edge whose opposite barycentric coordinate is negative), and
    only those are measured."""
    ring = vertex_faces(faces, len(vertices))[PointTree(vertices).query(points)[1]]  # (N, K)
    point, slot = np.nonzero(ring >= 0)  # point-major: each point's triangles in one run
    out = np.full(len(points), np.inf)  # inf where the nearest vertex is on no face
    if not len(point):
        return out
    V = torch.as_tensor(vertices, dtype=torch.float64)
    F = torch.as_tensor(np.asarray(faces, np.int64))
    a, b, c = (V[F[:, k]] for k in range(3))
    forms, offsets = _face_forms(a, b, c)
    f = torch.as_tensor(ring[point, slot])
    P = torch.as_tensor(points, dtype=torch.float64)[torch.as_tensor(point)]
    u, v, height = (torch.einsum("mij,mj->mi", forms[f], P) - offsets[f]).unbind(1)
    d2 = torch.where((u >= 0) & (v >= 0) & (u + v <= 1), height * height, torch.inf)
    for coordinate, (x, y) in ((u, (b, c)), (v, (c, a)), (1.0 - u - v, (a, b))):
        seen = torch.nonzero(coordinate < 0).flatten()
        d2[seen] = torch.minimum(d2[seen], _segment_distance2(P[seen], x[f[seen]], y[f[seen]]))
    starts = np.flatnonzero(np.diff(point, prepend=-1))
    out[point[starts]] = np.minimum.reduceat(d2.sqrt().numpy(), starts)
    return out


def laplacian(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, V) uniform graph Laplacian L = I - D^-1 A of the mesh edges (rows of isolated vertices zero).

    The umbrella operator of G. Taubin, "A Signal Processing Approach to Fair Surface Design", SIGGRAPH, 1995.
    """
    f = np.asarray(faces, np.int64)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n_vertices, n_vertices)).tocsr()
    A.data[:] = 1.0  # each edge once, however many faces share it
    deg = np.asarray(A.sum(axis=1)).ravel()
    inv = np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)
    return (sp.diags((deg > 0).astype(float)) - sp.diags(inv) @ A).tocsr()
