"""Bone geometry fitted inside the skin: one affine map per bone body, applied to its mesh in the body frame.

The skeleton's bodies are placed inside every body from joint centres and landmarks (:mod:`skeleton_fit`), but
the bone meshes come from one OpenSim subject (Rajagopal2015): a skull, hand or foot of another shape pokes
through a skin that its joints fit well, and the hand's mesh sits turned about the forearm against the skin's
hand (the wrist landmarks fix the joint centre, not the palm's plane). As SKEL scales each bone mesh and
orients it with a per-bone rotation that aligns it with the limb's skin, apart from the joint transforms
(M. Keller, K. Werling, S. Shin, S. Delp, S. Pujades, C. K. Liu and M. J. Black, "From Skin to Skeleton:
Towards Biomechanically Accurate 3D Digital Humans", ACM Transactions on Graphics 42(6) (SIGGRAPH Asia), 2023,
section 5.2, eq. 8-9), every bone body's mesh gets a map v -> A v + t in its body frame, before the segment
scaling, about the centroid c of its vertices (v -> A (v - c) + c + t), with A a rotation times a scaling
of bounded anisotropy,

    A = R(w) diag(exp(m + a tanh(u))),   |a tanh(u)| < a = ANISOTROPY,

fitted once at build time over sampled bodies in the bind pose and in poses across the coordinate ranges:
minimise over w, m, u, t

    mean_p relu((x_p - y_p) . n_p + margin)^2 + alpha m^2 + beta |w - w0|^2 + gamma |t - t0|^2,

where x_p are the body's mapped, scaled and posed bone vertices and (y_p, n_p) the nearest vertex of the
skin's envelope (the skin with its oral and nasal pockets closed, :func:`geometry.skin_envelope`) in the
skin the body drives, and its outward normal, found again each round. The hands start from the rotation
that aligns the principal axes of their bone mesh with those of the skin's hand (:func:`principal_alignment`):
the wrist landmarks fix the joint centre, not the palm's plane, so the hand body's frame sits turned about
the forearm against the skin's hand. Then every separate bone of a body (a phalanx, a rib, a vertebra;
:func:`bone_pieces`) gets a map of the same form after its body's (:func:`fit_piece_geometry`), so that the
flexed fingers of the source hand come to lie in the skin's straight ones. Joint centres and frames are not
changed: only the drawn bone surface moves. Minimised by L-BFGS (D. C. Liu and J. Nocedal, "On the limited
memory BFGS method for large scale optimization", Mathematical Programming 45, 1989).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from bodyfit.models.body.geometry import skin_envelope
from bodyfit.models.skeleton.bones import BoneMesh

MARGIN = 0.002  # metres of skin kept at least over every bone vertex
ANISOTROPY = 0.15  # largest log-scale difference of one axis from the body's mean log scale
SCALE_WEIGHT = 2e-3  # alpha: against the mean log scale m (shrinking), m^2 per unit^2: 10% costs 20 mm^2
ROTATION_WEIGHT = 1e-4  # beta: against turning away from the start rotation, m^2 per rad^2
SHIFT_WEIGHT = 1e-3  # gamma: against moving the centroid from its start, m^2 per m^2
ROUNDS = 5
STRIDE = 3  # every 3rd bone vertex takes part
ALIGNED_BODIES = ("hand_r", "hand_l")  # bodies started from the skin's principal axes


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N, V, 3) of meshes (N, V, 3) with triangles (F, 3), pointing away
    from each mesh's centroid on the whole."""
    tri = vertices[:, faces]  # (N, F, 3, 3)
    n = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    out = np.zeros_like(vertices)
    by_vertex = out.transpose(1, 0, 2)  # (V, N, 3) view: each triangle's normal added to its corners
    for k in range(3):
        np.add.at(by_vertex, faces[:, k], n.transpose(1, 0, 2))
    out /= np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-12)
    centre = vertices.mean(axis=1, keepdims=True)
    outward = np.sign(np.sum((vertices - centre) * out, axis=(1, 2)))
    return out * outward[:, None, None]


def apply_bone_geometry(
    bones: BoneMesh, geometry: np.ndarray, pieces: np.ndarray | None = None
) -> np.ndarray:
    """Bone vertices (V, 3) in their body frames after their affine maps: geometry (n_body, 3, 4) per body,
    or (n_piece, 3, 4) per piece with ``pieces`` (V,) (:func:`bone_pieces`)."""
    index = bones.vertex_body if pieces is None else pieces
    A, t = geometry[index, :, :3], geometry[index, :, 3]
    return np.einsum("vij,vj->vi", A, bones.vertices) + t


def rotation_matrix(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of rotation vectors w (..., 3) (Rodrigues' formula)."""
    theta = torch.sqrt((w**2).sum(-1, keepdim=True) + 1e-24)[..., None]  # (..., 1, 1)
    k = w[..., None, :] / theta[..., 0]  # (..., 1, 3)
    kx, ky, kz = k[..., 0, 0], k[..., 0, 1], k[..., 0, 2]
    zero = torch.zeros_like(kx)
    K = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], -1).reshape(*w.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=w.dtype).expand_as(K)
    return eye + torch.sin(theta) * K + (1 - torch.cos(theta)) * (K @ K)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of a rotation matrix (3, 3)."""
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_matrix(R).as_rotvec())


def principal_alignment(bone: np.ndarray, skin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid map (R (3, 3), t (3,)) that puts the centroid and principal axes of the points ``bone``
    (P, 3) on those of ``skin`` (Q, 3); of the four proper sign choices of the axes, the one whose mapped
    points lie nearest the skin points (mean nearest distance)."""
    cb, cs = bone.mean(axis=0), skin.mean(axis=0)
    Ub = np.linalg.svd(bone - cb, full_matrices=False)[2]  # rows: axes, largest variance first
    Us = np.linalg.svd(skin - cs, full_matrices=False)[2]
    tree, best = cKDTree(skin), None
    for signs in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        S = np.diag([signs[0], signs[1], signs[0] * signs[1]])
        R = Us.T @ S @ Ub
        if np.linalg.det(R) < 0:
            R = Us.T @ S @ np.diag([1.0, 1.0, -1.0]) @ Ub
        cost = tree.query((bone - cb) @ R.T + cs)[0].mean()
        if best is None or cost < best[0]:
            best = (cost, R)
    assert best is not None
    R = best[1]
    return R, cs - R @ cb


def skin_regions(weights: np.ndarray, parent: list[int], bodies: list[int], floor: float = 0.3) -> np.ndarray:
    """(len(bodies), V) bool: the skin each body's bone mesh lies under, the vertices weighted at least
    ``floor`` to the body and its kin together (weights (V, n_body), parent (n_body,)): two generations up
    and three down, so that a spine held by the lumbar body reaches the neck's skin, while a limb keeps
    away from its twin and from the other limbs."""
    out = np.zeros((len(bodies), len(weights)), bool)
    for k, b in enumerate(bodies):
        near, up = {b}, b
        for _ in range(2):
            up = parent[up] if up >= 0 else -1
            if up >= 0:
                near.add(up)
        level = {b}
        for _ in range(3):
            level = {c for c, p in enumerate(parent) if p in level}
            near |= level
        out[k] = weights[:, sorted(near)].sum(axis=1) >= floor
    return out


class _Placement:
    """Every ``STRIDE``-th bone vertex in N posed bodies, after a first map per body: x = M v + o for the
    vertex v (P, 3) of group ``group`` (P,) and body ``body`` (P,), M (N, P, 3, 3), o (N, P, 3)."""

    def __init__(
        self,
        local: np.ndarray,
        group: np.ndarray,
        body: np.ndarray,
        M: np.ndarray,
        o: np.ndarray,
        centre: dict,
    ):
        self.local, self.group, self.body = torch.as_tensor(local), group, body
        self.M, self.o = torch.as_tensor(M), torch.as_tensor(o)
        self.centre = (
            centre  # group -> (3,) centroid of its vertices, the point its map turns and scales about
        )

    @classmethod
    def of(
        cls, bones: BoneMesh, group: np.ndarray, frames: np.ndarray, scales: np.ndarray, geometry: np.ndarray
    ) -> _Placement:
        """Bone vertices grouped by ``group`` (V_bone,), placed by body frames (N, n_body, 4, 4), scales
        (N, n_body, 3) and first maps ``geometry`` (n_body, 3, 4) applied in the body frames."""
        pick = np.arange(0, len(bones.vertices), STRIDE)
        body = bones.vertex_body[pick]
        R, s = frames[:, body, :3, :3], scales[:, body]
        A, t = geometry[body, :, :3], geometry[body, :, 3]
        M = np.einsum("npij,npj,pjk->npik", R, s, A)
        o = np.einsum("npij,npj->npi", R, s * t[None]) + frames[:, body][..., :3, 3]
        centre = {
            int(g): bones.vertices[group == g].mean(axis=0).astype(np.float64) for g in np.unique(group)
        }
        return cls(np.asarray(bones.vertices[pick], np.float64), group[pick], body, M, o, centre)

    def placed(self, A: torch.Tensor, t: torch.Tensor, sel: np.ndarray | slice = slice(None)) -> torch.Tensor:
        """(N, P', 3) positions of the points ``sel`` under maps A (P', 3, 3), t (P', 3)."""
        v = torch.einsum("pij,pj->pi", A, self.local[sel]) + t
        return torch.einsum("npij,pj->npi", self.M[:, sel], v) + self.o[:, sel]


class _SkinTargets:
    """Nearest envelope vertex and its outward normal to posed bone points (N, P, 3), each point's search kept
    to its body's skin region (:func:`skin_regions`) so that a limb crossing another in a pose is not taken
    for its skin."""

    def __init__(
        self,
        skins: np.ndarray,
        faces: np.ndarray,
        cavity: np.ndarray | None,
        weights: np.ndarray | None,
        parent: list[int] | None,
    ) -> None:
        self.skins, self.faces, self.cavity = skins, faces, cavity
        self.weights, self.parent = weights, parent

    def __call__(self, x: np.ndarray, body: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Targets y and normals n (N, P, 3) of points x (N, P, 3) of bodies ``body`` (P,)."""
        bodies = [int(b) for b in np.unique(body)]
        regions = None
        if self.weights is not None and self.parent is not None:
            regions = skin_regions(self.weights, self.parent, bodies)
        ys, ns = np.empty_like(x), np.empty_like(x)
        for i, (skin, p) in enumerate(zip(self.skins, x)):
            V, F = (skin, self.faces) if self.cavity is None else skin_envelope(skin, self.faces, self.cavity)
            used = np.zeros(len(V), bool)
            used[F.ravel()] = True
            normal = vertex_normals(V[None], F)[0]
            for k, b in enumerate(bodies):
                sel = body == b
                allowed = used.copy()
                if regions is not None:
                    allowed[: len(skin)] &= regions[k]
                cand = np.flatnonzero(allowed)
                idx = cand[cKDTree(V[cand]).query(p[sel])[1]]
                ys[i, sel], ns[i, sel] = V[idx], normal[idx]
        return torch.as_tensor(ys), torch.as_tensor(ns)


class _Map:
    """One group's map A = R(w) diag(exp(m + a tanh(u))), t, started from a rigid map (3, 4)."""

    def __init__(self, start: np.ndarray) -> None:
        self.w0 = torch.as_tensor(rotation_vector(start[:, :3]))
        self.w = self.w0.clone().requires_grad_(True)
        self.m = torch.zeros(1, dtype=torch.float64, requires_grad=True)
        self.u = torch.zeros(3, dtype=torch.float64, requires_grad=True)
        self.t0 = torch.as_tensor(start[:, 3].copy())
        self.t = self.t0.clone().requires_grad_(True)

    def matrix(self) -> torch.Tensor:
        return rotation_matrix(self.w) * torch.exp(self.m + ANISOTROPY * torch.tanh(self.u))[None, :]

    def fit(
        self, place: _Placement, sel: np.ndarray, y: torch.Tensor, n: torch.Tensor, iterations: int
    ) -> None:
        """One round of L-BFGS on the points ``sel`` of ``place`` with their targets y and normals n
        (N, P', 3)."""
        opt = torch.optim.LBFGS(
            [self.w, self.m, self.u, self.t], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe"
        )

        def closure() -> torch.Tensor:
            opt.zero_grad()
            x = place.placed(self.matrix().expand(len(sel), 3, 3), self.t.expand(len(sel), 3), sel)
            depth = ((x - y) * n).sum(-1) + MARGIN
            loss = (torch.relu(depth) ** 2).mean() + SCALE_WEIGHT * (self.m**2).sum()
            loss = (
                loss
                + ROTATION_WEIGHT * ((self.w - self.w0) ** 2).sum()
                + SHIFT_WEIGHT * ((self.t - self.t0) ** 2).sum()
            )
            loss = loss * 1e6  # in mm^2: L-BFGS's change tolerance is absolute
            loss.backward()
            return loss

        opt.step(closure)


def _fit_groups(
    place: _Placement, groups: np.ndarray, start: np.ndarray, targets: _SkinTargets, iterations: int
) -> np.ndarray:
    """Maps (G, 3, 4) of the groups ``groups`` (G,) sorted, fitted in :data:`ROUNDS` rounds (targets found
    again each round, then one L-BFGS run per group), from rigid start maps (G, 3, 4)."""
    centre = np.stack([place.centre[int(g)] for g in groups])  # maps about each group's centroid c:
    # v -> A (v - c) + c + t', so that turning and scaling a small bone does not swing it about a far origin
    start = start.copy()
    start[:, :, 3] += np.einsum("gij,gj->gi", start[:, :, :3], centre) - centre
    params = [_Map(s) for s in start]
    slot = np.searchsorted(groups, place.group)
    place.local = place.local - torch.as_tensor(centre[slot])
    place.o = place.o + torch.einsum("npij,pj->npi", place.M, torch.as_tensor(centre[slot]))
    members = [np.flatnonzero(slot == k) for k in range(len(groups))]
    for _ in range(ROUNDS):
        with torch.no_grad():
            A = torch.stack([p.matrix() for p in params])[slot]
            t = torch.stack([p.t for p in params])[slot]
            x = place.placed(A, t).numpy()
        y, n = targets(x, place.body)
        for p, sel in zip(params, members):
            if len(sel):
                p.fit(place, sel, y[:, sel], n[:, sel], iterations)
    out = np.empty((len(groups), 3, 4))
    with torch.no_grad():
        for k, p in enumerate(params):
            mat = p.matrix().numpy()
            out[k, :, :3], out[k, :, 3] = mat, p.t.numpy() + centre[k] - mat @ centre[k]
    return out


def fit_bone_geometry(
    bones: BoneMesh,
    body_names: list[str],
    skins: np.ndarray,
    faces: np.ndarray,
    frames: np.ndarray,
    scales: np.ndarray,
    iterations: int = 60,
    cavity: np.ndarray | None = None,
    start: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    parent: list[int] | None = None,
) -> np.ndarray:
    """Fit the affine maps of every body that carries bone vertices.

    Args:
        bones: the bone mesh; body_names: the skeleton's bodies.
        skins: (N, V, 3) posed bodies (the bind pose and others); faces: (F, 3).
        frames: (N, n_body, 4, 4) their skeletons' body frames; scales: (N, n_body, 3) each body's segment
            scale (the scale of its segment, per body).
        cavity: (F,) bool faces of the skin's pockets (:func:`geometry.cavity_faces`), or None.
        start: (n_body, 3, 4) rigid start maps (rotation | translation), or None for the identity.
        weights, parent: the skin's weights (V, n_body) and the bodies' parents (n_body,), to keep each
            body's bone points to its own skin (:func:`skin_regions`); None searches the whole skin.
    Returns:
        (n_body, 3, 4) float64: [A | t] per body, identity for the bodies without bone vertices.
    """
    out = np.tile(np.eye(3, 4), (len(body_names), 1, 1))
    start = out.copy() if start is None else start
    fitted = np.unique(bones.vertex_body)
    place = _Placement.of(bones, bones.vertex_body, frames, scales, out)
    targets = _SkinTargets(skins, faces, cavity, weights, parent)
    out[fitted] = _fit_groups(place, fitted, start[fitted], targets, iterations)
    return out


def fit_piece_geometry(
    bones: BoneMesh,
    pieces: np.ndarray,
    geometry: np.ndarray,
    skins: np.ndarray,
    faces: np.ndarray,
    frames: np.ndarray,
    scales: np.ndarray,
    iterations: int = 40,
    cavity: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    parent: list[int] | None = None,
) -> np.ndarray:
    """Refine the body maps ``geometry`` (n_body, 3, 4) of :func:`fit_bone_geometry` per piece: every
    separate bone of a body (``pieces`` (V_bone,), :func:`bone_pieces`) gets its own map of the same form
    after its body's, so that a finger's phalanges or a rib follow the skin's finger or chest. Other
    arguments as :func:`fit_bone_geometry`. Returns (n_piece, 3, 4) float64: each piece's whole map."""
    n_piece = int(pieces.max()) + 1
    body_of_piece = np.zeros(n_piece, np.int64)
    body_of_piece[pieces] = bones.vertex_body
    place = _Placement.of(bones, pieces, frames, scales, geometry)
    targets = _SkinTargets(skins, faces, cavity, weights, parent)
    groups = np.arange(n_piece)
    local = _fit_groups(place, groups, np.tile(np.eye(3, 4), (n_piece, 1, 1)), targets, iterations)
    body = geometry[body_of_piece]
    out = np.empty((n_piece, 3, 4))
    out[:, :, :3] = body[:, :, :3] @ local[:, :, :3]
    out[:, :, 3] = np.einsum("gij,gj->gi", body[:, :, :3], local[:, :, 3]) + body[:, :, 3]
    return out


def bone_pieces(bones: BoneMesh) -> np.ndarray:
    """(V_bone,) int: the index of every bone vertex's piece, a connected part of the mesh within one body
    (one bone: a phalanx, a rib, a vertebra), numbered in order of first vertex."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f, n = bones.faces, len(bones.vertices)
    rows, cols = np.concatenate([f[:, 0], f[:, 1], f[:, 2]]), np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    same = bones.vertex_body[rows] == bones.vertex_body[cols]
    graph = coo_matrix((np.ones(int(same.sum())), (rows[same], cols[same])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    _, first, piece = np.unique(label, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return order[piece].astype(np.int64)


def aligned_start(
    bones: BoneMesh,
    body_names: list[str],
    skin: np.ndarray,
    weights: np.ndarray,
    frames: np.ndarray,
    scales: np.ndarray,
) -> np.ndarray:
    """Start maps (n_body, 3, 4) for :func:`fit_bone_geometry`: for :data:`ALIGNED_BODIES`, the rigid map in
    the body frame that aligns the bone mesh's principal axes with those of the skin the body drives
    (vertices weighted at least 0.9 to it) in one body (skin (V, 3), weights (V, n_body), frames
    (n_body, 4, 4), scales (n_body, 3)); the identity for the others."""
    out = np.tile(np.eye(3, 4), (len(body_names), 1, 1))
    for name in ALIGNED_BODIES:
        if name not in body_names:
            continue
        b = body_names.index(name)
        world = skin[weights[:, b] >= 0.9]
        local = (world - frames[b, :3, 3]) @ frames[b, :3, :3] / scales[b]
        R, t = principal_alignment(np.asarray(bones.vertices[bones.vertex_body == b], np.float64), local)
        out[b, :, :3], out[b, :, 3] = R, t
    return out
