"""The template's pooling hierarchy and spiral sequences (pure numpy; computed once, stored in the asset).

Decimation is quadric-error half-edge collapse: M. Garland and P. S. Heckbert, "Surface Simplification Using
Quadric Error Metrics", SIGGRAPH, 1997. Each removed vertex is carried by the barycentric coordinates of its
projection on the nearest triangle of the coarser mesh, which is the up-sampling of A. Ranjan, T. Bolkart,
S. Sanyal and M. J. Black, "Generating 3D Faces using Convolutional Mesh Autoencoders", European Conference
on Computer Vision (ECCV), 2018. Spirals follow G. Bouritsas, S. Bokhnyak, S. Ploumpis, M. Bronstein and
S. Zafeiriou, "Neural 3D Morphable Models: Spiral Convolutional Networks for 3D Shape Representation Learning
and Generation", IEEE/CVF International Conference on Computer Vision (ICCV), 2019, with the fixed length of
S. Gong, L. Chen, M. Bronstein and S. Zafeiriou, "SpiralNet++: A Fast and Highly Efficient Mesh Convolution
Operator", ICCV Workshops, 2019.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Level:
    """One mesh of the hierarchy: vertices (V, 3), faces (F, 3); ``kept`` (V,) indices into the finer level
    (the finest level's are the identity)."""

    vertices: np.ndarray
    faces: np.ndarray
    kept: np.ndarray


def _plane_quadrics(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Sum of the squared-distance quadrics (4, 4) of each vertex's incident triangle planes: (V, 4, 4)."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = np.linalg.norm(n, axis=1, keepdims=True)
    n = n / np.maximum(area, 1e-20)
    p = np.concatenate([n, -(n * v[f[:, 0]]).sum(axis=1, keepdims=True)], axis=1)
    K = np.einsum("fi,fj->fij", p, p) * area[:, :, None]
    Q = np.zeros((len(v), 4, 4))
    for k in range(3):
        np.add.at(Q, f[:, k], K)
    return Q


class _Collapser:
    """Mutable state of the half-edge collapses of one decimation."""

    def __init__(self, v: np.ndarray, f: np.ndarray) -> None:
        self.v, self.f = v, f.copy()
        self.alive_face = np.ones(len(f), bool)
        self.alive = np.ones(len(v), bool)
        self.faces_of: list[set[int]] = [set() for _ in range(len(v))]
        for i, tri in enumerate(f):
            for a in tri:
                self.faces_of[a].add(i)
        self.Q = _plane_quadrics(v, f)
        self.stamp = np.zeros(len(v), np.int64)
        self.heap: list[tuple[float, int, int, int, int]] = []

    def neighbours(self, a: int) -> set[int]:
        return {int(b) for i in self.faces_of[a] for b in self.f[i]} - {a}

    def cost(self, u: int, w: int) -> float:
        """Quadric error of moving u onto w."""
        h = np.append(self.v[w], 1.0)
        return float(h @ (self.Q[u] + self.Q[w]) @ h)

    def push(self, u: int) -> None:
        for w in self.neighbours(u):
            heapq.heappush(self.heap, (self.cost(u, w), u, w, int(self.stamp[u]), int(self.stamp[w])))

    def valid(self, u: int, w: int) -> bool:
        """Link condition (two shared neighbours: the mesh stays a manifold) and no flipped triangle."""
        nu, nw = self.neighbours(u), self.neighbours(w)
        if w not in nu or len(nu & nw) != 2 or len(nu) <= 3 or len(nw) <= 3:
            return False
        for i in self.faces_of[u]:
            tri = self.f[i]
            if w in tri:
                continue
            p = self.v[tri]
            before = np.cross(p[1] - p[0], p[2] - p[0])
            p = np.where((tri == u)[:, None], self.v[w], p)
            after = np.cross(p[1] - p[0], p[2] - p[0])
            if float(before @ after) <= 0.2 * float(np.linalg.norm(before) * np.linalg.norm(after)):
                return False
        return True

    def collapse(self, u: int, w: int) -> None:
        for i in list(self.faces_of[u]):
            if w in self.f[i]:
                self.alive_face[i] = False
                for a in self.f[i]:
                    self.faces_of[a].discard(i)
            else:
                self.f[i][self.f[i] == u] = w
                self.faces_of[w].add(i)
        self.faces_of[u] = set()
        self.alive[u] = False
        self.Q[w] += self.Q[u]
        for a in [w, *self.neighbours(w)]:
            self.stamp[a] += 1
        for a in [w, *self.neighbours(w)]:
            self.push(a)


def decimate(vertices: np.ndarray, faces: np.ndarray, n_target: int) -> Level:
    """Quadric half-edge collapses down to ``n_target`` vertices; kept vertices keep their positions.

    Args:
        vertices: (V, 3); faces: (F, 3) a closed manifold triangle mesh.
    Returns:
        the coarse :class:`Level` (``kept`` indexes ``vertices``).
    """
    c = _Collapser(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    for u in range(len(vertices)):
        c.push(u)
    n = len(vertices)
    while n > n_target and c.heap:
        _, u, w, su, sw = heapq.heappop(c.heap)
        if not (c.alive[u] and c.alive[w]) or su != c.stamp[u] or sw != c.stamp[w] or not c.valid(u, w):
            continue
        c.collapse(u, w)
        n -= 1
    kept = np.flatnonzero(c.alive)
    remap = -np.ones(len(vertices), np.int64)
    remap[kept] = np.arange(len(kept))
    return Level(c.v[kept], remap[c.f[c.alive_face]], kept)


def upsampling(fine: np.ndarray, coarse: Level, k_near: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric weights carrying the coarse mesh onto the fine vertices (V_f, 3).

    Kept vertices copy themselves; every other vertex is projected on the nearest of the triangles around
    its ``k_near`` nearest coarse vertices.

    Returns:
        index (V_f, 3) coarse vertex indices and weights (V_f, 3) summing to 1.
    """
    from scipy.spatial import cKDTree

    index = np.zeros((len(fine), 3), np.int64)
    weight = np.zeros((len(fine), 3))
    faces_of: list[list[int]] = [[] for _ in range(len(coarse.vertices))]
    for i, tri in enumerate(coarse.faces):
        for a in tri:
            faces_of[a].append(i)
    _, near = cKDTree(coarse.vertices).query(fine, k=k_near)
    own = -np.ones(len(fine), np.int64)
    own[coarse.kept] = np.arange(len(coarse.kept))
    for i, p in enumerate(fine):
        if own[i] >= 0:
            index[i], weight[i] = own[i], (1.0, 0.0, 0.0)
            continue
        cand = sorted({t for a in near[i] for t in faces_of[a]})
        found = [_closest_on_triangle(p, coarse.vertices[coarse.faces[t]]) for t in cand]
        k = int(np.argmin([d for d, _ in found]))
        index[i], weight[i] = coarse.faces[cand[k]], found[k][1]
    return index, weight


def _closest_on_triangle(p: np.ndarray, tri: np.ndarray) -> tuple[float, np.ndarray]:
    """Squared distance from p (3,) to the triangle (3, 3) and the barycentric coordinates (3,) of the
    closest point (found on the plane, then on the edges if it falls outside)."""
    a, b, c = tri
    e0, e1, d = b - a, c - a, p - a
    M = np.array([[e0 @ e0, e0 @ e1], [e0 @ e1, e1 @ e1]])
    s, t = np.linalg.solve(M + 1e-18 * np.eye(2), [e0 @ d, e1 @ d])
    bary = np.array([1.0 - s - t, s, t])
    if (bary >= 0).all():
        return float(np.sum((bary @ tri - p) ** 2)), bary
    best: tuple[float, np.ndarray] | None = None
    for i, j in ((0, 1), (1, 2), (2, 0)):
        e = tri[j] - tri[i]
        x = float(np.clip((p - tri[i]) @ e / max(float(e @ e), 1e-20), 0.0, 1.0))
        w = np.zeros(3)
        w[i], w[j] = 1.0 - x, x
        dist = float(np.sum((w @ tri - p) ** 2))
        if best is None or dist < best[0]:
            best = (dist, w)
    assert best is not None
    return best


def _ordered_ring(a: int, faces_of: list[list[int]], faces: np.ndarray) -> list[int]:
    """One-ring of vertex a in the order of the triangles' orientation (a closed fan)."""
    nxt = {}
    for t in faces_of[a]:
        tri = list(faces[t])
        k = tri.index(a)
        nxt[tri[(k + 1) % 3]] = tri[(k + 2) % 3]
    start = min(nxt)
    ring, b = [start], nxt[start]
    while b != start and b in nxt and len(ring) < len(nxt):
        ring.append(b)
        b = nxt[b]
    return ring + sorted(set(nxt) - set(ring))


def spirals(vertices: np.ndarray, faces: np.ndarray, length: int) -> np.ndarray:
    """Spiral sequence of every vertex: itself, then its rings outwards, each ring in the mesh's
    orientation, starting from the neighbour highest along +y (a fixed reference direction, so the
    sequences are ordered alike across the body), cut to ``length``.

    Returns:
        (V, length) vertex indices.
    """
    faces_of: list[list[int]] = [[] for _ in range(len(vertices))]
    for i, tri in enumerate(faces):
        for a in tri:
            faces_of[a].append(i)
    rings = [_ordered_ring(a, faces_of, faces) for a in range(len(vertices))]
    out = np.zeros((len(vertices), length), np.int64)
    for a in range(len(vertices)):
        first = rings[a]
        k = int(np.argmax(vertices[first, 1]))
        seq, seen, frontier = [a], {a}, first[k:] + first[:k]
        while len(seq) < length and frontier:
            new = [b for b in frontier if b not in seen]
            seen.update(new)
            seq.extend(new)
            frontier = [c for b in new for c in rings[b] if c not in seen]
            frontier = list(dict.fromkeys(frontier))
        out[a] = (seq + [a] * length)[:length]
    return out
