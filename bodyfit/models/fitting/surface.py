"""Triangle-mesh geometry for scan fitting: normals, point-to-surface distances, the mesh Laplacian.

Pure numpy / scipy functions on (V, 3) vertices and (F, 3) counter-clockwise faces, in whatever length unit
the caller uses.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bodyfit.models.fitting.nearest import PointTree


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) of a (V, 3) / (F, 3) mesh; zero for unused vertices."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    owner = faces.reshape(-1)
    acc = np.stack([np.bincount(owner, np.repeat(cross[:, k], 3), len(vertices)) for k in range(3)], axis=1)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0)


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


def _segment_distance2(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distance (...,) from points p to segments ab, all (..., 3)."""
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    d = p - (a + t[..., None] * ab)
    return (d * d).sum(-1)


def point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance (...,) from points p (..., 3) to triangles tri (..., 3, 3): to the plane when the projection
    falls inside, else to the nearest edge."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    n = np.cross(b - a, c - a)
    n2 = np.maximum((n * n).sum(-1), 1e-300)
    ap = p - a
    # Barycentric coordinates of the projection (signed sub-areas over the full area).
    u = (np.cross(c - b, p - b) * n).sum(-1) / n2
    v = (np.cross(a - c, p - c) * n).sum(-1) / n2
    w = 1.0 - u - v
    inside = (u >= 0) & (v >= 0) & (w >= 0)
    plane2 = (ap * n).sum(-1) ** 2 / n2
    edges = [_segment_distance2(p, a, b), _segment_distance2(p, b, c), _segment_distance2(p, c, a)]
    edge2 = np.minimum.reduce(edges)
    return np.sqrt(np.where(inside, plane2, edge2))


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


def point_to_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance (N,) from each point (N, 3) to the mesh surface (see :func:`closest_on_surface`)."""
    return closest_on_surface(points, vertices, faces)[2]


def laplacian(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, V) uniform graph Laplacian L = I - D^-1 A of the mesh edges (rows of isolated vertices zero)."""
    f = np.asarray(faces, np.int64)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n_vertices, n_vertices)).tocsr()
    A.data[:] = 1.0  # each edge once, however many faces share it
    deg = np.asarray(A.sum(axis=1)).ravel()
    inv = np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)
    return (sp.diags((deg > 0).astype(float)) - sp.diags(inv) @ A).tocsr()
