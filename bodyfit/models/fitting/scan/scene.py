"""Separate the person from scene clutter before a raw-scan fit: floors, walls, furniture and fragments.

A scan of a person in a room holds more than the person: the floor under the feet, a wall behind, a chair,
stray objects. The fit would place the body in all of it (a seated body on a floor holding a fifth of the
points was fitted into the floor). :func:`separate_person` takes the cleaned points (M, 3) in metres, in any
orientation, and

1. estimates each point's surface normal from its nearest neighbours (:func:`point_normals`);
2. finds large planes one at a time (:func:`find_plane`): a RANSAC whose hypotheses are one point and its
   normal, scored by the points within 2 cm of the plane whose normals agree with it within 20 degrees,
   refined by least squares. A plane is removed only when the points on it fill a square at least
   :attr:`SceneConfig.plane_min_extent_m` (0.6 m) across (:func:`_plane_patch`): a floor, a wall or a
   table does; a body does not (its flattest parts, the back or the tops of the thighs of a seated body,
   fill up to about 0.35 m squares within 2 cm). Every point within 2 cm of the plane on or next to the
   grid cells of its support goes with it: the patch and what touches it, not the plane's extension;
3. splits the rest into Euclidean clusters (connected components of the graph linking points closer than
   three point spacings, :func:`euclidean_clusters`);
4. describes each cluster (:func:`describe_cluster`: its robust principal extents, the fraction of its
   normals on three perpendicular directions (a box), how well a sphere fits it) and keeps the largest
   that looks like a person (:meth:`Cluster.kind`), with the clusters of no object's kind within
   :attr:`SceneConfig.attach_m` of it or of one already joined (a foot beyond a shin cut by holes);
5. looks for furniture touching the person (a seat under a seated body is one cluster with it): planes
   found in the person's cluster at a tight tolerance (6 mm, 10 degrees) filling 0.3 m squares, which the
   body's own surface does not, are removed, and the person is picked again from what is left (step 4).

A scan with no person-like cluster raises :class:`NoPersonError`, naming what was found.

Limits: furniture that touches the person without flat faces of 0.3 m (a cushioned sofa, a chair with a
small or padded seat, a person leaning on a round pillar) stays with the person; so does a second person
touching the first (one apart is removed as a smaller person-like cluster), and a scene object of human
size and shape that is larger than the person (the largest person-like cluster wins). The body's own points
on a removed plane go with it (the soles on a floor, the thighs on a seat, the back against a wall).
The thresholds are set for scans thinned to the fitter's 1 cm grid in metres; a plane sampled much more
sparsely than the rest of the scene loses points to the statistical outlier removal and may not fill its
squares.

References: RANSAC (M. A. Fischler and R. C. Bolles, "Random sample consensus: a paradigm for model fitting
with applications to image analysis and automated cartography", Communications of the ACM 24(6), 1981), with
normals scoring the planes as in R. Schnabel, R. Wahl and R. Klein, "Efficient RANSAC for Point-Cloud Shape
Detection", Computer Graphics Forum 26(2), 2007; normals by local principal component analysis (H. Hoppe,
T. DeRose, T. Duchamp, J. McDonald and W. Stuetzle, "Surface reconstruction from unorganized points", ACM
SIGGRAPH, 1992); Euclidean clustering as in R. B. Rusu, "Semantic 3D Object Maps for Everyday Manipulation in
Human Living Environments", PhD thesis, Technische Universität München, 2009 (section 6.2); the algebraic
sphere fit of I. D. Coope, "Circle fitting by linear and nonlinear least squares", Journal of Optimization
Theory and Applications 76(2), 1993.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import pairwise
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from bodyfit.io.scans import MIN_POINTS, ScanError
from bodyfit.models.fitting.common.nearest import PointTree

_MAX_CELLS = 4_000_000  # a plane's occupancy grid at most (a 40 m square at 2 cm)
_ROW = 1 << 32  # a grid cell's key: row * _ROW + column (cells of centimetres within a billion of zero)
_BODY_PARTS = ("person", "small", "thin")  # the kinds of cluster a body cut by holes can fall into


class NoPersonError(ScanError):
    """A scan holds no person: only planes, objects (boxes, spheres, furniture) and fragments."""


@dataclass(frozen=True, kw_only=True)
class SceneConfig:
    """How :func:`separate_person` splits a scene.

    neighbours: points in each normal's neighbourhood; plane_distance_m: a point this close to a plane lies
    on it; plane_normal_deg: and its normal within this angle of the plane's counts towards the plane;
    plane_min_extent_m, plane_fill: a plane is removed when its points occupy at least ``plane_fill`` of
    the cells of some square of this side on a grid of cells twice their spacing (within ``cell_m``);
    plane_tries: RANSAC hypotheses per plane, each scored on ``plane_scored`` points at most;
    max_planes: planes removed at most; link_spacings, min_link_m: points closer than this many point
    spacings (the 90th percentile of the nearest-neighbour distance, at least min_link_m) belong to one
    cluster; attach_m: clusters of no object's kind this close to the person are kept with it (a limb cut
    off by a hole); min_person_points: fewer points are no person; person_extent_m: a person's largest
    robust principal extent lies in this range (a head and shoulders to a body with its arms raised),
    min_width_m and min_depth_m: its second and third extents are at least these; furniture_distance_m,
    furniture_normal_deg, furniture_extent_m: the tight plane search in the person's cluster (0: none);
    box_fraction: a cluster with this fraction of its normals within box_deg of three perpendicular
    directions is a box; sphere_residual: a cluster whose points lie within this fraction of a sphere's
    radius of it (root mean square) is a sphere; seed: the RANSAC's random numbers.
    """

    neighbours: int = 12
    plane_distance_m: float = 0.02
    plane_normal_deg: float = 20.0
    plane_min_extent_m: float = 0.6
    plane_fill: float = 0.85
    cell_m: tuple[float, float] = (0.02, 0.1)
    plane_tries: int = 128
    plane_scored: int = 8000
    max_planes: int = 8
    link_spacings: float = 3.0
    min_link_m: float = 0.025
    attach_m: float = 0.25
    min_person_points: int = MIN_POINTS
    person_extent_m: tuple[float, float] = (0.2, 2.6)
    min_width_m: float = 0.1
    min_depth_m: float = 0.03
    furniture_distance_m: float = 0.006
    furniture_normal_deg: float = 10.0
    furniture_extent_m: float = 0.3
    box_fraction: float = 0.7
    box_deg: float = 15.0
    sphere_residual: float = 0.03
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("neighbours", "plane_tries", "min_person_points"):
            if getattr(self, name) < 1:
                raise ValueError(f"SceneConfig.{name} must be at least 1; got {getattr(self, name)!r}")
        lo, hi = self.person_extent_m
        if not 0 < lo < hi:
            raise ValueError(
                f"SceneConfig.person_extent_m must be 0 < low < high; got {self.person_extent_m}"
            )


@dataclass(frozen=True)
class Plane:
    """A plane n . x = offset (unit normal (3,), offset in metres) and the points removed with it."""

    normal: np.ndarray
    offset: float
    points: int

    def summary(self) -> dict[str, Any]:
        """The plane as a fit's report carries it."""
        return {"normal": [round(float(v), 4) for v in self.normal], "offset_m": round(self.offset, 4),
                "points": self.points}  # fmt: skip


@dataclass(frozen=True)
class Cluster:
    """One Euclidean cluster: its point indices (K,), robust principal extents (3,) descending (m), the
    fraction of its normals on a box's three directions and the relative residual of a sphere fit."""

    index: np.ndarray
    extents: np.ndarray
    box: float
    sphere: float

    def kind(self, cfg: SceneConfig) -> str:
        """What the cluster looks like: "person", "box", "sphere", "plane" (flat), "thin" (a rod or a
        strip), "small" (too few points or too short) or "large" (longer than a person)."""
        e = self.extents
        if len(self.index) < cfg.min_person_points or e[0] < cfg.person_extent_m[0]:
            return "small"
        if e[0] > cfg.person_extent_m[1]:
            return "large"
        if e[1] < cfg.min_width_m:
            return "thin"
        if e[2] < cfg.min_depth_m:
            return "plane"
        if self.box >= cfg.box_fraction:
            return "box"
        if self.sphere <= cfg.sphere_residual:
            return "sphere"
        return "person"


@dataclass(frozen=True)
class SceneSplit:
    """What :func:`separate_person` found: ``keep`` (M,) the person's points, the planes removed, the
    clusters removed (their kinds) and the person's robust principal extents (3,) (m)."""

    keep: np.ndarray
    planes: list[Plane] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    extents: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def summary(self) -> dict[str, Any]:
        """The removal summary a fit's report carries: the planes (normal, offset, points), the clusters
        removed (how many of each kind: "box", "small" fragments, ...), the cleaned points removed and
        kept, and the person's extents."""
        return {
            "planes": [p.summary() for p in self.planes],
            "clusters_removed": len(self.removed),
            "removed_kinds": {k: self.removed.count(k) for k in sorted(set(self.removed))},
            "points_removed": int((~self.keep).sum()),
            "points_kept": int(self.keep.sum()),
            "person_extent_m": [round(float(v), 3) for v in self.extents],
        }


def point_normals(points: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normals (M, 3) of points (M, 3) by local PCA over each point's ``neighbours`` nearest (the
    eigenvector of the smallest eigenvalue; sign arbitrary), the neighbours' indices (M, k) and the distance
    to the nearest other point (M,)."""
    k = min(neighbours, len(points) - 1)
    d, idx = PointTree(points).query(points, k=k + 1)
    local = points[idx] - points[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", local, local)
    _, vectors = np.linalg.eigh(cov)
    return vectors[:, :, 0], idx, d[:, 1]


def _plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3) two unit vectors across the unit ``normal``."""
    u = np.cross(normal, np.eye(3)[int(np.argmin(np.abs(normal)))])
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u)])


def _cell_keys(flat: np.ndarray, cell: float, dilate: bool = False) -> np.ndarray:
    """One int64 key (K,) per grid cell (of side ``cell``) that in-plane coordinates (K, 2) fall in; with
    ``dilate``, the unique keys of those cells and their eight neighbours."""
    ij = np.floor(flat / cell).astype(np.int64)
    keys = ij[:, 0] * _ROW + ij[:, 1]
    if dilate:
        steps = np.array([a * _ROW + b for a in (-1, 0, 1) for b in (-1, 0, 1)])
        keys = np.unique((np.unique(keys)[:, None] + steps[None]).ravel())
    return keys


def find_plane(
    points: np.ndarray, normals: np.ndarray, pool: np.ndarray, cfg: SceneConfig, rng: np.random.Generator
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """The plane with most support among ``points`` (M, 3) with ``normals`` (M, 3), its hypotheses drawn
    from the indices ``pool``: unit normal (3,), offset (n . x on it) and the support (indices of the points
    within ``cfg.plane_distance_m`` whose normals agree), refined by a least-squares fit to the support;
    None when the pool is empty."""
    if not len(pool):
        return None
    cos = np.cos(np.radians(cfg.plane_normal_deg))
    seeds = rng.choice(pool, min(cfg.plane_tries, len(pool)), replace=False)
    score = rng.choice(len(points), min(len(points), cfg.plane_scored), replace=False)  # a subset
    n_s, p_s = normals[seeds], points[seeds]
    dist = np.abs(points[score] @ n_s.T - np.sum(n_s * p_s, axis=1))
    agree = np.abs(normals[score] @ n_s.T) > cos
    best = int(np.argmax(((dist < cfg.plane_distance_m) & agree).sum(axis=0)))
    normal, offset = n_s[best], float(n_s[best] @ p_s[best])
    for _ in range(2):  # least squares on the support, then the support again
        support = np.flatnonzero(
            (np.abs(points @ normal - offset) < cfg.plane_distance_m) & (np.abs(normals @ normal) > cos)
        )
        if len(support) < 3:
            break
        centre = points[support].mean(axis=0)
        normal = np.linalg.svd(points[support] - centre, full_matrices=False)[2][2]
        offset = float(normal @ centre)
    return normal, offset, support


def _plane_patch(flat: np.ndarray, cell: float, cfg: SceneConfig) -> bool:
    """Whether the points on a plane, in-plane coordinates (K, 2), hold a large flat patch: some square of
    side ``cfg.plane_min_extent_m`` on a grid of ``cell`` has at least ``cfg.plane_fill`` of its cells
    occupied.
    A floor, a wall or a seat is such a patch; a body's points near one of its tangent planes are not (the
    strips along a limb or the trunk where it touches the plane are about 0.1-0.2 m wide)."""
    if len(flat) < 3:
        return False
    ij = np.floor((flat - flat.min(axis=0)) / cell).astype(np.int64)
    side = max(round(cfg.plane_min_extent_m / cell), 1)
    size = ij.max(axis=0) + 1
    if (size < side).any() or size.prod() > _MAX_CELLS:
        return bool((size >= side).all())  # a patch too large for the grid is a plane
    grid = np.zeros(tuple(size), np.float64)
    grid[ij[:, 0], ij[:, 1]] = 1.0
    return bool(uniform_filter(grid, side, mode="constant").max() >= cfg.plane_fill - 1e-9)


def remove_planes(
    points: np.ndarray, normals: np.ndarray, nearest: np.ndarray, cfg: SceneConfig
) -> tuple[np.ndarray, list[Plane]]:
    """Find and remove large planes (:func:`find_plane`, :func:`_plane_patch`) from ``points`` (M, 3) with
    ``normals`` (M, 3): returns which points are left (M,) bool and the planes. Each plane removes every
    point left within ``cfg.plane_distance_m`` of it whose cell on the plane's grid (or a neighbouring
    one) holds its support: the patch's edges and what touches it, not the plane's whole extension.
    A candidate that is no large patch takes its support out of the hypotheses' pool; the search ends
    after three such in a row."""
    rng = np.random.default_rng(cfg.seed)
    left = np.ones(len(points), bool)
    pool = np.ones(len(points), bool)
    planes: list[Plane] = []
    misses = 0
    while len(planes) < cfg.max_planes and misses < 3 and left.sum() > cfg.min_person_points:
        idx = np.flatnonzero(left)
        found = find_plane(points[idx], normals[idx], np.flatnonzero(pool[idx]), cfg, rng)
        if found is None:
            break
        normal, offset, support = found
        basis = _plane_basis(normal).T
        # a grid fine enough to tell a patch's shape, coarse enough that a sparse floor fills its cells
        cell = (
            float(np.clip(2.0 * np.percentile(nearest[idx[support]], 90), *cfg.cell_m))
            if len(support)
            else 1.0
        )
        # the patch is what lies on the plane, whatever its normals: where a body rests on a seat, the
        # cleaned points are as often the body's as the seat's
        near = np.flatnonzero(np.abs(points[idx] @ normal - offset) < cfg.plane_distance_m)
        if not _plane_patch(points[idx[near]] @ basis, cell, cfg):
            pool[idx[support]] = False
            pool[idx[rng.choice(len(idx), 1)]] = False  # a seed that found nothing either
            misses += 1
            continue
        misses = 0
        footprint = _cell_keys(points[idx[support]] @ basis, cell, dilate=True)
        gone = idx[near[np.isin(_cell_keys(points[idx[near]] @ basis, cell), footprint)]]
        left[gone] = False
        pool[gone] = False
        planes.append(Plane(normal, offset, len(gone)))
    return left, planes


def euclidean_clusters(points: np.ndarray, radius: float) -> tuple[int, np.ndarray]:
    """The number of connected components of ``points`` (M, 3) linked when closer than ``radius`` (m), and
    each point's component (M,), largest first."""
    if not len(points):
        return 0, np.zeros(0, np.int64)
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), bool), (pairs[:, 0], pairs[:, 1])), (len(points),) * 2)
    count, labels = connected_components(graph, directed=False)
    rank = np.argsort(np.argsort(-np.bincount(labels), kind="stable"), kind="stable")
    return int(count), rank[labels]


def _box_fraction(normals: np.ndarray, deg: float, rng: np.random.Generator) -> float:
    """The largest fraction of unit ``normals`` (K, 3) (sign ignored) within ``deg`` of three perpendicular
    directions: the first the best of a sample of the normals themselves, the second the best of those
    perpendicular to it (within ``deg``), the third across both. Near 1 for a box, far below for a body."""
    cos, sin = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    normals = normals[rng.choice(len(normals), min(len(normals), 5000), replace=False)]  # enough to count
    sample = normals[:200]  # already in random order
    near = np.abs(normals @ sample.T) > cos  # (K, S)
    first = int(np.argmax(near.sum(axis=0)))
    d1 = sample[first]
    across = np.flatnonzero(np.abs(sample @ d1) < sin)
    if not len(across):
        return float(near[:, first].mean())
    second = across[int(np.argmax((near[:, across] & ~near[:, [first]]).sum(axis=0)))]
    d2 = sample[second] - (sample[second] @ d1) * d1
    d2 /= np.linalg.norm(d2)
    d3 = np.cross(d1, d2)
    on = (np.abs(normals @ np.stack([d1, d2, d3]).T) > cos).any(axis=1)
    return float(on.mean())


def _sphere_residual(points: np.ndarray) -> float:
    """The root-mean-square distance of ``points`` (K, 3) from their least-squares sphere, over its radius
    (the algebraic fit: |x|^2 = 2 c . x + (r^2 - |c|^2) is linear in c and the constant)."""
    p = points - points.mean(axis=0)
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(a, np.sum(p * p, axis=1), rcond=None)
    centre = sol[:3]
    radius = np.sqrt(max(sol[3] + centre @ centre, 1e-12))
    return float(np.sqrt(np.mean((np.linalg.norm(p - centre, axis=1) - radius) ** 2)) / radius)


def robust_extents(points: np.ndarray) -> np.ndarray:
    """The extents (3,) of ``points`` (K, 3) along their principal axes, descending: the spread between the
    1st and 99th percentiles, so a few stray points do not set them."""
    p = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(p, full_matrices=False)
    along = p @ axes.T
    return np.sort(np.percentile(along, 99, axis=0) - np.percentile(along, 1, axis=0))[::-1]


def describe_cluster(
    points: np.ndarray, normals: np.ndarray, index: np.ndarray, cfg: SceneConfig, rng: np.random.Generator
) -> Cluster:
    """A :class:`Cluster` of ``points[index]`` (K, 3) with their ``normals``: the box and sphere tests run
    on clusters with enough points to be a person only."""
    p = points[index]
    extents = robust_extents(p) if len(index) >= 4 else np.zeros(3)
    if len(index) < cfg.min_person_points:
        return Cluster(index, extents, 0.0, 1.0)
    return Cluster(index, extents, _box_fraction(normals[index], cfg.box_deg, rng), _sphere_residual(p))


def _describe(cluster: Cluster, kind: str) -> str:
    """A cluster as the error message names it: its kind, extents and points."""
    e = " x ".join(f"{v:.2f}" for v in cluster.extents)
    return f"{kind} ({e} m, {len(cluster.index):,} points)"


def _no_person(
    planes: list[Plane], clusters: list[Cluster], kinds: list[str], total: int, cfg: SceneConfig
) -> NoPersonError:
    """The error for a scan of ``total`` cleaned points where nothing looked like a person: what was found."""
    found = [f"{len(planes)} large plane(s) ({sum(p.points for p in planes):,} points)"] if planes else []
    big = [_describe(c, k) for c, k in zip(clusters, kinds, strict=True) if k != "small"]
    found += big[:5] + [f"{len(big) - 5} more object(s)"] * (len(big) > 5)
    small = sum(k == "small" for k in kinds)
    if small:
        found.append(f"{small} fragment(s) too small for a body")
    lo, hi = cfg.person_extent_m
    return NoPersonError(
        f"no person found in the scan: its {total:,} cleaned points hold {'; '.join(found) or 'nothing'}; "
        f"a person is a cluster of at least {cfg.min_person_points} points {lo:g}-{hi:g} m long, not a "
        "plane, a box, a rod or a sphere: send a scan with the person in it"
    )


def _clusters(
    p: np.ndarray,
    normals: np.ndarray,
    idx: np.ndarray,
    radius: float,
    cfg: SceneConfig,
    rng: np.random.Generator,
) -> list[Cluster]:
    """The Euclidean clusters (:func:`euclidean_clusters` at ``radius``) of the points ``p[idx]``, largest
    first, described (:func:`describe_cluster`; their indices into ``p``)."""
    count, labels = euclidean_clusters(p[idx], radius)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(count + 1))
    return [describe_cluster(p, normals, idx[order[a:b]], cfg, rng) for a, b in pairwise(bounds)]


def _pick_person(
    p: np.ndarray, clusters: list[Cluster], kinds: list[str], cfg: SceneConfig
) -> tuple[np.ndarray, list[str], Cluster] | None:
    """The person among ``clusters`` of ``p`` (their ``kinds``): the indices kept (the largest person-like
    cluster and the body parts within ``cfg.attach_m`` of it), the kinds of the clusters removed and the
    person's cluster; None when no cluster looks like a person."""
    people = [k for k, kind in enumerate(kinds) if kind == "person"]
    if not people:
        return None
    person = clusters[people[0]]  # clusters come largest first
    # parts of the body cut off by holes, or fragments of it: no object, within reach of the person or of
    # a part already joined to it (a foot beyond a cut shin)
    parts = [k for k, kind in enumerate(kinds) if kind in _BODY_PARTS and k != people[0]]
    kept = {people[0]}
    owner = np.concatenate([np.full(len(clusters[k].index), k) for k in parts]) if parts else np.zeros(0, int)
    candidates = np.concatenate([clusters[k].index for k in parts]) if parts else np.zeros(0, int)
    frontier = person.index  # each round tests what is left against what joined in the last one
    while len(candidates) and len(frontier):
        near = PointTree(p[frontier]).query(p[candidates], cfg.attach_m)[0] < cfg.attach_m
        joined = np.unique(owner[near])
        kept.update(joined.tolist())
        frontier = np.concatenate([clusters[k].index for k in joined]) if len(joined) else np.zeros(0, int)
        stay = ~np.isin(owner, joined)
        owner, candidates = owner[stay], candidates[stay]
    removed = [kind for k, kind in enumerate(kinds) if k not in kept]
    return np.concatenate([clusters[k].index for k in sorted(kept)]), removed, person


def separate_person(points: np.ndarray, cfg: SceneConfig | None = None) -> SceneSplit:
    """Split cleaned scan points (M, 3, metres, any orientation) into the person and the rest (see the
    module docstring): large planes removed, the rest clustered, the largest person-like cluster kept with
    the body parts within ``cfg.attach_m`` of it; then furniture flat faces touching it
    (:attr:`SceneConfig.furniture_distance_m`) removed, and the person picked again from what is left.

    Raises:
        NoPersonError: no cluster looks like a person (the message names what was found).
    """
    cfg = cfg or SceneConfig()
    p = np.asarray(points, np.float64)
    rng = np.random.default_rng(cfg.seed)
    normals, _, nearest = point_normals(p, cfg.neighbours)
    spacing = float(np.percentile(nearest, 90))
    radius = max(cfg.link_spacings * spacing, cfg.min_link_m)
    left, planes = remove_planes(p, normals, nearest, cfg)
    clusters = _clusters(p, normals, np.flatnonzero(left), radius, cfg, rng)
    kinds = [c.kind(cfg) for c in clusters]
    found = _pick_person(p, clusters, kinds, cfg)
    if found is None:
        raise _no_person(planes, clusters, kinds, len(p), cfg)
    kept, removed, person = found
    if cfg.furniture_distance_m > 0:
        tight = replace(
            cfg,
            plane_distance_m=cfg.furniture_distance_m,
            plane_normal_deg=cfg.furniture_normal_deg,
            plane_min_extent_m=cfg.furniture_extent_m,
        )
        left, faces = remove_planes(p[kept], normals[kept], nearest[kept], tight)
        if faces:
            clusters = _clusters(p, normals, kept[left], radius, cfg, rng)
            again = _pick_person(p, clusters, [c.kind(cfg) for c in clusters], cfg)
            if again is not None:  # else the faces were the person's own: keep the first answer
                kept, person, planes = again[0], again[2], planes + faces
                removed += again[1]
    keep = np.zeros(len(p), bool)
    keep[kept] = True
    return SceneSplit(keep, planes, removed, person.extents)


def raw_points_kept(raw: np.ndarray, cleaned: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Which raw scan points (N, 3) go with the person (N,) bool: those whose nearest cleaned point (of
    ``cleaned`` (M, 3)) is kept (``keep`` (M,)); a stray point goes with what it is nearest to."""
    if keep.all():
        return np.ones(len(raw), bool)
    return keep[PointTree(cleaned).query(raw)[1]]
