"""Synthetic scan corruptions: make clean body samples look like real captures.

Pure functions on numpy arrays; randomness only through the ``np.random.Generator`` passed in, so a seed
gives the same scan. Units are metres throughout; world frame +Y up (see :mod:`bodyfit.models`).

* :func:`add_noise`: Gaussian jitter; :func:`add_outliers`: stray points in the inflated bounding box;
* :func:`remove_patches`: holes (occlusions, dark or shiny clothing);
* :func:`depth_camera_view`: one depth camera's partial view of a mesh (a numpy z-buffer);
* :func:`clothing_offset`: loose clothing as a smooth outward offset of the mesh;
* :func:`random_rigid`: arbitrary orientation and placement.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from bodyfit.models.fitting.common.surface import vertex_normals

_NEAR = 1e-3  # m: triangles closer to the camera plane than this are dropped
_CHUNK = 2_000_000  # candidate pixel tests per vectorised block


def add_noise(points: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) points plus isotropic Gaussian noise of standard deviation ``sigma`` metres per coordinate
    (e.g. 0.005); returns a new (N, 3) array."""
    p = np.asarray(points, np.float64)
    return p + rng.normal(0.0, sigma, p.shape)


def add_outliers(
    points: np.ndarray, fraction: float, rng: np.random.Generator, margin: float = 0.3
) -> tuple[np.ndarray, np.ndarray]:
    """Add ``round(fraction * N)`` points uniform in the bounding box grown by ``margin`` metres per side.

    Args:
        points: (N, 3); fraction: outliers per input point (e.g. 0.05).
    Returns:
        all points (N + K, 3) in random order, and ``is_outlier`` (N + K,) bool.
    """
    p = np.asarray(points, np.float64)
    k = round(fraction * len(p))
    lo, hi = p.min(axis=0) - margin, p.max(axis=0) + margin
    out = np.concatenate([p, rng.uniform(lo, hi, (k, 3))])
    flag = np.concatenate([np.zeros(len(p), bool), np.ones(k, bool)])
    order = rng.permutation(len(out))
    return out[order], flag[order]


def remove_patches(
    points: np.ndarray, fraction: float, rng: np.random.Generator, patch_radius: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Cut holes: remove ``round(fraction * N)`` points in spherical patches.

    Patches grow around random seeds (each a still-kept point) and take the nearest kept points within
    ``patch_radius`` metres, until the target count is removed; the last patch stops at the target.

    Args:
        points: (N, 3); fraction: in [0, 1] (e.g. 0.3).
    Returns:
        the kept points (M, 3) and ``keep`` (N,) bool with ``points[keep]`` those kept.
    """
    p = np.asarray(points, np.float64)
    target = min(round(fraction * len(p)), len(p))
    keep = np.ones(len(p), bool)
    tree = cKDTree(p)
    removed = 0
    while removed < target:
        seed = rng.choice(np.flatnonzero(keep))
        near = np.asarray(tree.query_ball_point(p[seed], patch_radius), np.int64)
        near = near[keep[near]]
        near = near[np.argsort(np.linalg.norm(p[near] - p[seed], axis=1))][: target - removed]
        keep[near] = False
        removed += len(near)
    return p[keep], keep


def depth_camera_view(
    vertices: np.ndarray,
    faces: np.ndarray,
    camera_position: Sequence[float] | np.ndarray,
    look_at: Sequence[float] | np.ndarray,
    resolution: tuple[int, int] = (120, 160),
    fov_deg: float = 60.0,
    rng: np.random.Generator | None = None,
    up: Sequence[float] = (0.0, 1.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """A single-view depth capture of a mesh: the nearest surface point seen through each pixel.

    A pinhole camera at ``camera_position`` looks at ``look_at`` with ``up`` (world) as image up; the
    mesh is rasterised into a perspective z-buffer (per pixel, the nearest triangle under the pixel's sample
    point; perspective-correct depth) and each covered pixel is back-projected onto its triangle. Triangles
    with a vertex behind the camera's near plane (1 mm) are dropped: keep the mesh in front of the camera.

    Args:
        vertices: (V, 3) metres; faces: (F, 3) indices.
        camera_position, look_at: (3,) metres.
        resolution: (height, width) pixels; fov_deg: vertical field of view in degrees.
        rng: when given, each pixel samples a random point inside itself instead of its centre.
        up: (3,) world direction shown as image up.
    Returns:
        points (M, 3) on the visible surface, in world coordinates (one per covered pixel),
        and face (M,) the triangle each lies on.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    eye = np.asarray(camera_position, np.float64)
    fwd = np.asarray(look_at, np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-9:  # looking along ``up``: any right-angle image up will do
        right = np.cross(fwd, np.eye(3)[np.argmin(np.abs(fwd))])
    right /= np.linalg.norm(right)
    rot = np.stack([right, np.cross(fwd, right), fwd])  # rows: camera x (right), y (down), z (forward)
    h, w = resolution
    focal = 0.5 * h / math.tan(math.radians(fov_deg) / 2.0)
    cam = (v - eye) @ rot.T
    tri = cam[f]  # (F, 3, 3)
    ok = (tri[:, :, 2] > _NEAR).all(axis=1)
    ids = np.flatnonzero(ok)
    z = tri[ids, :, 2]
    sx = focal * tri[ids, :, 0] / z + 0.5 * w  # (n, 3) image coordinates; pixel (i, j) spans [j, j + 1)
    sy = focal * tri[ids, :, 1] / z + 0.5 * h
    off = rng.random((2, h, w)) if rng is not None else np.full((2, h, w), 0.5)
    x0 = np.maximum(np.floor(sx.min(axis=1)), 0).astype(np.int64)
    x1 = np.minimum(np.floor(sx.max(axis=1)), w - 1).astype(np.int64)
    y0 = np.maximum(np.floor(sy.min(axis=1)), 0).astype(np.int64)
    y1 = np.minimum(np.floor(sy.max(axis=1)), h - 1).astype(np.int64)
    area2 = (sx[:, 1] - sx[:, 0]) * (sy[:, 2] - sy[:, 0]) - (sx[:, 2] - sx[:, 0]) * (sy[:, 1] - sy[:, 0])
    sel = np.flatnonzero((x1 >= x0) & (y1 >= y0) & (np.abs(area2) > 1e-12))
    box = (x0[sel], y0[sel], x1[sel] - x0[sel] + 1, y1[sel] - y0[sel] + 1)  # corner and size per triangle
    cum = np.cumsum(box[2] * box[3])
    hits = []  # (pixel, depth, triangle) per block of triangles, each reduced to the nearest per pixel
    start = 0
    while start < len(sel):
        stop = max(int(np.searchsorted(cum, cum[start] + _CHUNK, side="right")), start + 1)
        part = slice(start, stop)
        tris = sel[part]
        corner_size = (box[0][part], box[1][part], box[2][part], box[3][part])
        hits.append(_block_hits(tris, *corner_size, sx[tris], sy[tris], z[tris], area2[tris], off))
        start = stop
    if not hits:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    pix, depth, face = _nearest(*(np.concatenate(a) for a in zip(*hits)))
    row, col = pix // w, pix % w
    rx, ry = (col + off[0, row, col] - 0.5 * w) / focal, (row + off[1, row, col] - 0.5 * h) / focal
    local = np.stack([rx, ry, np.ones(len(pix))], axis=1) * depth[:, None]
    return local @ rot + eye, ids[face]


def _block_hits(
    tris: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    bw: np.ndarray,
    bh: np.ndarray,
    sx: np.ndarray,
    sy: np.ndarray,
    z: np.ndarray,
    area2: np.ndarray,
    off: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Test n triangles against every pixel of their boxes (corner x0, y0 and size bw, bh: (n,) each).

    sx, sy, z: (n, 3) image coordinates and depths of the corners; area2: (n,) signed doubled areas;
    off: (2, h, w) sample point inside each pixel. Returns the nearest hit per pixel as flat pixel index,
    depth and entry of ``tris`` (K,) each.
    """
    w = off.shape[2]
    n_pix = bw * bh
    t = np.repeat(np.arange(len(tris)), n_pix)
    local = np.arange(len(t)) - np.repeat(np.cumsum(n_pix) - n_pix, n_pix)
    row, col = y0[t] + local // bw[t], x0[t] + local % bw[t]
    px, py = col + off[0, row, col], row + off[1, row, col]
    ax, ay = sx[t, 0], sy[t, 0]
    ex1, ey1, ex2, ey2 = sx[t, 1] - ax, sy[t, 1] - ay, sx[t, 2] - ax, sy[t, 2] - ay
    wb = ((px - ax) * ey2 - ex2 * (py - ay)) / area2[t]
    wc = (ex1 * (py - ay) - (px - ax) * ey1) / area2[t]
    wa = 1.0 - wb - wc
    inside = (wa >= 0) & (wb >= 0) & (wc >= 0)
    t, zt = t[inside], z[t[inside]]
    depth = 1.0 / (wa[inside] / zt[:, 0] + wb[inside] / zt[:, 1] + wc[inside] / zt[:, 2])
    return _nearest(row[inside] * w + col[inside], depth, tris[t])


def _nearest(
    pix: np.ndarray, depth: np.ndarray, face: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep, for each pixel in (K,) ``pix``, the entry with the smallest depth."""
    order = np.lexsort((depth, pix))
    pix, depth, face = pix[order], depth[order], face[order]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    return pix[first], depth[first], face[first]


def clothing_offset(
    vertices: np.ndarray,
    faces: np.ndarray,
    rng: np.random.Generator,
    max_offset: float = 0.03,
    n_centres: int = 6,
    length_scale: float = 0.2,
    bare: np.ndarray | None = None,
    cuff: float = 0.03,
) -> tuple[np.ndarray, np.ndarray]:
    """Loose clothing: push vertices outward along their normals by a smooth non-negative field.

    The field is a sum of Gaussians (standard deviation ``length_scale`` metres, Euclidean distance) around
    ``n_centres`` random vertices with random weights in [0.3, 1], scaled so its maximum is ``max_offset``.
    With ``bare`` (V,) bool, the skin the cloth leaves bare (a face, the hands): the centres lie on the
    clothed vertices, and the field falls to zero at the bare skin over ``cuff`` metres (times
    1 - exp(-d^2 / (2 cuff^2)), d a vertex's distance to the nearest bare vertex), as a collar or a cuff
    closes on the skin.

    Args:
        vertices: (V, 3) metres; faces: (F, 3) counter-clockwise seen from outside.
    Returns:
        displaced vertices (V, 3) and the offset (V,) in metres, in [0, max_offset] (0 on ``bare``).
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    normals = vertex_normals(v, f)
    clothed = np.arange(len(v)) if bare is None else np.flatnonzero(~np.asarray(bare, bool))
    centres = v[clothed[rng.choice(len(clothed), size=n_centres)]]
    weights = rng.uniform(0.3, 1.0, n_centres)
    d2 = ((v[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2)  # (V, n_centres)
    field = np.exp(-0.5 * d2 / length_scale**2) @ weights
    if bare is not None and np.any(bare):
        to_bare = cKDTree(v[np.asarray(bare, bool)]).query(v)[0]
        field = field * (1.0 - np.exp(-0.5 * (to_bare / cuff) ** 2))
    offset = max_offset * field / field.max()
    return v + offset[:, None] * normals, offset


def random_rigid(
    points: np.ndarray, rng: np.random.Generator, max_angle: float = math.pi, translation: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Rotate about a uniformly random axis by an angle uniform in [0, max_angle] radians (about the
    origin), then translate by a random direction times a length uniform in [0, translation] metres.

    Args:
        points: (N, 3).
    Returns:
        the moved points (N, 3) and the (4, 4) transform T with ``moved = points @ T[:3, :3].T + T[:3, 3]``.
    """
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0.0, max_angle)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    direction = rng.normal(size=3)
    t = direction / np.linalg.norm(direction) * rng.uniform(0.0, translation)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot, t
    return np.asarray(points, np.float64) @ rot.T + t, T
