"""Mesh geometry helpers (numpy, pure)."""

from __future__ import annotations

import numpy as np


def _solid_angles(tri: np.ndarray, points: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Signed solid angle / (4 pi) of every triangle tri (F, 3, 3) seen from points (P, 3), summed over the
    triangles: (P,). Van Oosterom and Strackee's formula (see :func:`winding_number`)."""
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        d = tri[None] - points[s : s + chunk, None, None]  # (p, F, 3, 3)
        a, b, c = d[:, :, 0], d[:, :, 1], d[:, :, 2]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("pfi,pfi->pf", a, b) * lc
            + np.einsum("pfi,pfi->pf", b, c) * la
            + np.einsum("pfi,pfi->pf", c, a) * lb
        )
        out[s : s + chunk] = 2.0 * np.arctan2(num, den).sum(axis=1) / (4.0 * np.pi)
    return out


def winding_number(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, chunk: int = 256
) -> np.ndarray:
    """Generalised winding number of points with respect to a closed triangle mesh.

    A. Jacobson, L. Kavan and O. Sorkine-Hornung, "Robust Inside-Outside Segmentation using Generalized
    Winding Numbers", ACM Transactions on Graphics 32(4) (SIGGRAPH), 2013. About 1 inside, 0 outside, for a
    consistently oriented closed surface (either orientation: the sign is dropped). Solid angles by A. Van
    Oosterom and J. Strackee, "The Solid Angle of a Plane Triangle", IEEE Transactions on Biomedical
    Engineering BME-30(2), 1983.

    Args:
        vertices: (V, 3); faces: (F, 3); points: (P, 3).
    Returns:
        (P,) winding numbers.
    """
    return np.abs(_solid_angles(vertices[faces], points, chunk))


def face_clusters(centroids: np.ndarray, leaf: int = 32) -> list[np.ndarray]:
    """Spatially compact groups of faces: recursive median splits of the face centroids (F, 3) along their
    longest extent until each group holds at most ``leaf`` faces. Returns the groups' face indices."""
    groups, todo = [], [np.arange(len(centroids))]
    while todo:
        idx = todo.pop()
        if len(idx) <= leaf:
            groups.append(idx)
            continue
        c = centroids[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        order = idx[np.argsort(c[:, axis], kind="stable")]
        todo += [order[: len(order) // 2], order[len(order) // 2 :]]
    return groups


def fast_winding_number(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, leaf: int = 32, beta: float = 3.0
) -> np.ndarray:
    """Generalised winding number with a far-field approximation, for many points against a large mesh.

    G. Barill, N. G. Dickson, R. Schmidt, D. I. W. Levin and A. Jacobson, "Fast Winding Numbers for Soups
    and Clouds", ACM Transactions on Graphics 37(4) (SIGGRAPH), 2018, to first order: the faces are grouped
    into compact clusters (:func:`face_clusters`); a cluster farther than ``beta`` times its radius from a
    point contributes as a dipole, its summed area vector N seen from its area-weighted centre c,
    N . (c - p) / (4 pi |c - p|^3); nearer clusters are summed exactly (:func:`winding_number`). The
    approximation's error falls with (radius / distance)^2, so points near the surface, where the value is
    close to 1/2, are computed exactly.

    Args:
        vertices: (V, 3); faces: (F, 3); points: (P, 3).
    Returns:
        (P,) winding numbers (the sign dropped, as :func:`winding_number`).
    """
    tri = np.asarray(vertices, np.float64)[faces]
    p = np.asarray(points, np.float64)
    area_vec = 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
    area = np.linalg.norm(area_vec, axis=1) + 1e-30
    groups = face_clusters(tri.mean(axis=1), leaf)
    centre = np.stack([np.average(tri[g].mean(axis=1), axis=0, weights=area[g]) for g in groups])
    normal = np.stack([area_vec[g].sum(axis=0) for g in groups])  # (C, 3)
    radius = np.array([np.linalg.norm(tri[g] - centre[i], axis=-1).max() for i, g in enumerate(groups)])
    out = np.zeros(len(p))
    for s in range(0, len(p), 512):
        d = centre[None] - p[s : s + 512, None]  # (p, C, 3)
        dist = np.linalg.norm(d, axis=-1)
        far = dist > beta * radius
        dipole = np.einsum("pci,ci->pc", d, normal) / (4.0 * np.pi * np.maximum(dist, 1e-12) ** 3)
        out[s : s + 512] = np.where(far, dipole, 0.0).sum(axis=1)
        for c in np.flatnonzero(~far.all(axis=0)):
            near = s + np.flatnonzero(~far[:, c])
            out[near] += _solid_angles(tri[groups[c]], p[near])
    return np.abs(out)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals (F, 3) of the triangles (F, 3) of a mesh (V, 3), by the right-hand rule."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def cavity_faces(
    vertices: np.ndarray, faces: np.ndarray, region: np.ndarray, step: float = 0.004, close: int = 2
) -> np.ndarray:
    """Faces (F,) bool that line a pocket of a closed surface: a cavity open to the outside only through a
    narrow mouth (the oral cavity of a body surface), inside the box around the vertices ``region`` (V,)
    bool.

    The box is voxelised at ``step``; a voxel is solid when its winding number (:func:`fast_winding_number`)
    is above 1/2. Morphological closing by a ball of ``close`` voxels shuts the narrow mouth, enclosed holes
    are filled, and the voxels filled but not solid are the cavity (P. Soille, "Morphological Image
    Analysis", Springer, 2nd ed. 2003, ch. 4 and 6: closing and hole filling by reconstruction). A face
    lines it when the point one voxel off its centre along its outward normal is a cavity voxel.
    Returns all False for a surface without such a pocket.
    """
    from scipy import ndimage

    pad = (close + 3) * step
    lo, hi = vertices[region].min(axis=0) - pad, vertices[region].max(axis=0) + pad
    axes = [np.arange(a, b + step, step) for a, b in zip(lo, hi)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    solid = (fast_winding_number(vertices, faces, grid.reshape(-1, 3)) > 0.5).reshape(grid.shape[:3])
    ball = ndimage.iterate_structure(ndimage.generate_binary_structure(3, 1), close)
    filled = ndimage.binary_fill_holes(ndimage.binary_dilation(solid, ball))
    filled = ndimage.binary_erosion(filled, ball, border_value=1)
    cavity = filled & ~solid
    probe = vertices[faces].mean(axis=1) + step * face_normals(vertices, faces)
    cell = np.round((probe - lo) / step).astype(int)
    inside_box = np.all((cell >= 0) & (cell < np.array(cavity.shape)), axis=1)
    out = np.zeros(len(faces), bool)
    c = cell[inside_box]
    out[inside_box] = cavity[c[:, 0], c[:, 1], c[:, 2]]
    return _clean_face_set(faces, out)


def _clean_face_set(
    faces: np.ndarray, selected: np.ndarray, rounds: int = 3, min_faces: int = 20
) -> np.ndarray:
    """A face set (F,) bool made one clean patch per pocket: a few rounds of majority vote over each face
    and its edge neighbours (so the patch has no pinholes or stray faces and its border is one loop), then
    connected patches smaller than ``min_faces`` dropped."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(len(faces)), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    e, o = edges[order], owner[order]
    same = np.all(e[1:] == e[:-1], axis=1)
    a, b = o[:-1][same], o[1:][same]
    n = len(faces)
    adj = coo_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()
    degree = np.asarray(adj.sum(axis=1)).ravel()
    sel = selected.copy()
    for _ in range(rounds):
        sel = (adj @ sel.astype(float) + sel) > 0.5 * (degree + 1)
    keep = adj[sel][:, sel]
    _, label = connected_components(keep, directed=False)
    sizes = np.bincount(label)
    out = np.zeros(n, bool)
    out[np.flatnonzero(sel)[sizes[label] >= min_faces]] = True
    return out


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Boundary loops of an oriented triangle mesh (F, 3): vertex index arrays, each in the order of its
    faces' boundary edges."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    present = {(int(a), int(b)) for a, b in edges}
    nxt = {a: b for a, b in present if (b, a) not in present}
    loops = []
    while nxt:
        start, loop = next(iter(nxt)), []
        v = start
        while v in nxt:
            loop.append(v)
            v = nxt.pop(v)
        loops.append(np.asarray(loop))
    return loops


def skin_envelope(
    vertices: np.ndarray, faces: np.ndarray, cavity: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The outer envelope of a closed body surface: its faces without the ``cavity`` (F,) bool faces
    (:func:`cavity_faces`), each hole left capped by a fan about its centroid. Returns vertices (V + L, 3),
    the L cap centres appended, and faces (F', 3), oriented as the surface."""
    if not cavity.any():
        return vertices, faces
    kept = faces[~cavity]
    extra, caps = [], []
    for k, loop in enumerate(boundary_loops(kept)):
        centre = len(vertices) + k
        extra.append(vertices[loop].mean(axis=0))
        caps.append(np.stack([np.roll(loop, -1), loop, np.full(len(loop), centre)], axis=1))
    return np.concatenate([vertices, np.asarray(extra)]), np.concatenate([kept, *caps])
