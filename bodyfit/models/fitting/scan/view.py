"""Single-view scans: is a point cloud one sensor's view, and from which side was it seen?

A depth camera sees one layer of surface along its line of sight; a full scan of a closed body has (at
least) two layers, front and back, along every direction. :func:`view_direction` projects the points along
candidate directions onto a grid of cells and measures the fraction of points in cells that hold more
than one layer (a depth spread beyond ``layer_gap``): a single view has a direction where almost no cell
does. Its sign is the side the sensor was on: seen from the sensor, a body's surface bulges towards it
(:func:`depth_bulge`).

Used by :mod:`~bodyfit.models.fitting.scan.fitter` to fit partial scans with only the surface the sensor could
see: the back of the body, which has no points, is not pulled into the front's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ViewConfig:
    """directions: candidate lines of sight (a Fibonacci sphere's half); cell: grid size across them (m);
    layer_gap: depth spread within a cell that counts as two layers (m); max_layered: the largest fraction
    of points in layered cells that still counts as a single view; max_points: points used (an even
    subsample of larger scans); coarse_directions, coarse_reject: a first pass over this many directions
    settles a scan as full when even its least layered one exceeds ``coarse_reject`` (full scans lie far
    above it, single views far below). The directions are a Fibonacci lattice (Á. González, "Measurement of
    areas on a sphere using Fibonacci and latitude-longitude lattices", Mathematical Geosciences 42(1),
    2010)."""

    directions: int = 200
    cell: float = 0.03
    layer_gap: float = 0.06
    max_layered: float = 0.12
    max_points: int = 6000
    coarse_directions: int = 50
    coarse_reject: float = 0.5


def _half_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread over the half sphere z >= 0 (a Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def _basis(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit ``direction`` and two unit vectors across it, (3,) each."""
    d = direction / np.linalg.norm(direction)
    u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    return d, u, np.cross(d, u)


def layered_fraction(points: np.ndarray, direction: np.ndarray, cell: float, gap: float) -> float:
    """Fraction of points (N, 3) in grid cells (across the unit ``direction``) whose depth spread along it
    exceeds ``gap``."""
    d, u, w = _basis(direction)
    ij = np.floor(np.stack([points @ u, points @ w], 1) / cell).astype(np.int64)
    ij -= ij.min(0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.argsort(key, kind="stable")
    key, depth = key[order], (points @ d)[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    spread = np.maximum.reduceat(depth, starts) - np.minimum.reduceat(depth, starts)
    counts = np.diff(np.r_[starts, len(key)])
    return float(counts[spread > gap].sum() / len(key))


def view_direction(points: np.ndarray, config: ViewConfig | None = None) -> np.ndarray | None:
    """The unit direction (3,) from the scanned body towards the sensor when ``points`` (N, 3, metres) look
    like a single view, else None (a full or multi-view scan)."""
    cfg = config or ViewConfig()
    p = np.asarray(points, np.float64)
    if len(p) > cfg.max_points:
        p = p[:: len(p) // cfg.max_points]
    p = p - p.mean(0)
    coarse = _half_sphere(cfg.coarse_directions)
    if min(layered_fraction(p, d, cfg.cell, cfg.layer_gap) for d in coarse) > cfg.coarse_reject:
        return None
    dirs = _half_sphere(cfg.directions)
    fractions = np.array([layered_fraction(p, d, cfg.cell, cfg.layer_gap) for d in dirs])
    best = int(np.argmin(fractions))
    if fractions[best] > cfg.max_layered:
        return None
    d = dirs[best]
    return d if depth_bulge(p, d, cfg.cell / 2) > 0 else -d


@dataclass(frozen=True)
class Silhouette:
    """A single view's silhouette: where the sensor saw the body, on an image-plane grid across its line
    of sight. A point of the body projecting outside it lay in space the sensor saw empty (it would have
    been seen there, as nothing in front of it was); inside it, the point may be seen or hidden behind
    what was seen. The grid is orthographic (the sensor's perspective is ignored, which the margin
    absorbs at a body's size and range).

    axes: (2, 3) the image plane's unit axes; lo: (2,) the grid's corner along them (m); cell: grid size
    (m); outside: (I, J) each cell's distance (m) to the silhouette, 0 inside it.
    """

    axes: np.ndarray
    lo: np.ndarray
    cell: float
    outside: np.ndarray

    @staticmethod
    def of(points: np.ndarray, direction: np.ndarray, cell: float = 0.02, margin: int = 2) -> Silhouette:
        """From a single view's points (N, 3) and its line of sight (3,); the silhouette is grown by
        ``margin`` cells (sparse sampling at grazing angles, perspective)."""
        from scipy.ndimage import binary_dilation, distance_transform_edt

        _, u, w = _basis(direction)
        axes = np.stack([u, w])
        uv = points @ axes.T
        lo = uv.min(0) - (margin + 1) * cell
        ij = np.floor((uv - lo) / cell).astype(np.int64)
        seen = np.zeros(tuple(ij.max(0) + margin + 2), bool)
        seen[ij[:, 0], ij[:, 1]] = True
        seen = binary_dilation(seen, iterations=margin)
        return Silhouette(axes, lo, cell, distance_transform_edt(~seen) * cell)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(...,) how far (m) each of ``points`` (..., 3) projects outside the silhouette (0 inside)."""
        uv = points @ self.axes.T
        hi = self.lo + self.cell * np.array(self.outside.shape)
        ij = np.floor((np.clip(uv, self.lo, hi - 1e-9) - self.lo) / self.cell).astype(np.int64)
        beyond = np.linalg.norm(uv - np.clip(uv, self.lo, hi), axis=-1)  # off the grid
        return self.outside[ij[..., 0], ij[..., 1]] + beyond


def depth_bulge(points: np.ndarray, direction: np.ndarray, cell: float) -> float:
    """How much the surface seen along ``direction`` bulges towards +direction: the mean over interior grid
    cells (size ``cell`` across it) of the cell's depth minus its 5 x 5 neighbourhood's. A body seen from
    +direction is a height field that is concave towards the camera (limbs and trunk are round), so this
    is positive; seen from the other side, negative. The image-plane grid, unlike 3D neighbours, is not
    biased by the denser sampling a depth camera gives at grazing angles."""
    from scipy.ndimage import uniform_filter

    d, u, w = _basis(direction)
    ij = np.floor(np.stack([points @ u, points @ w], 1) / cell).astype(np.int64)
    ij -= ij.min(0)
    shape = tuple(ij.max(0) + 1)
    total, count = np.zeros(shape), np.zeros(shape)
    np.add.at(total, (ij[:, 0], ij[:, 1]), points @ d)
    np.add.at(count, (ij[:, 0], ij[:, 1]), 1.0)
    occupied = count > 0
    depth = np.where(occupied, total / np.maximum(count, 1.0), 0.0)
    n = uniform_filter(occupied.astype(float), 5, mode="constant") * 25 - occupied
    around = (uniform_filter(depth, 5, mode="constant") * 25 - depth) / np.maximum(n, 1.0)
    interior = occupied & (n >= 20)
    return float((depth - around)[interior].mean()) if interior.any() else 0.0
