"""One scan registered in a shape space: projection into the space, non-rigid refinement, unposing (BLiSS
sections 3.2-3.4).

The scan's pose comes from its first fit (``bodyfit batch-fit``) and is kept: each round re-projects only the
shape into the current space (BLiSS eq. 1 with the pose held), then refines the posed body non-rigidly onto
the scan (:func:`~bodyfit.models.fitting.common.nonrigid.refine_nonrigid`, in the role of BLiSS's neural
Jacobian fields), keeps only the refinement's offsets along the body's normals, and brings the refined
registration back to the bind pose by inverting each vertex's blended skinning transform, where the shape
space is learned.

BLiSS: S. Muralikrishnan, C.-H. P. Huang, D. Ceylan and N. J. Mitra, "BLiSS: Bootstrapped Linear Shape
Space", International Conference on 3D Vision (3DV), 2024.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import BodyfitError
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.nonrigid import NonRigidConfig, refine_nonrigid
from bodyfit.models.fitting.common.surface import vertex_normals
from bodyfit.models.spaces.population import rest_meshes, segment_scales, space_basis


@dataclass(frozen=True)
class PosedScan:
    """A scan and its first fit: ``points`` (N, 3) in the model's frame (metres), the fit's ``coordinates``
    (n_dof,), ``root`` (3,) and ``shape`` (n_shape,) in the space it was fitted in; ``faces`` (F, 3) the
    scan's triangles when it is a mesh (None for a point cloud)."""

    name: str
    points: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    shape: np.ndarray
    faces: np.ndarray | None = None


@dataclass(frozen=True)
class Registration:
    """A scan registered in a space: the bind-pose mesh (V, 3) with its skeleton's segment scales
    (n_seg, 3), the posed registration (V, 3) in the model's frame and its Chamfer distance (mm) to the
    scan."""

    name: str
    bind: np.ndarray
    scales: np.ndarray
    posed: np.ndarray
    chamfer_mm: float


def read_fit(scan: Path, fit: Path, units: str = "auto") -> PosedScan:
    """A scan file and its ``bodyfit batch-fit`` result (``.npz``: shape, coordinates, root, to_model), the
    scan's points carried into the model's frame by ``to_model``.

    Raises:
        BodyfitError: the fit lacks an array (not a batch-fit output).
    """
    from bodyfit.io.scans import load_scan

    with np.load(fit) as npz:
        missing = [k for k in ("shape", "coordinates", "root", "to_model") if k not in npz.files]
        if missing:
            raise BodyfitError(f"{fit} is not a bodyfit batch-fit result (no {', '.join(missing)})")
        arrays = {k: np.asarray(npz[k], np.float64) for k in ("shape", "coordinates", "root", "to_model")}
    loaded = load_scan(scan, units=units, drop_nonfinite=True)
    points = np.asarray(loaded.points, np.float64)
    R, t = arrays["to_model"][:3, :3], arrays["to_model"][:3, 3]
    return PosedScan(
        scan.stem,
        points @ R.T + t,
        arrays["coordinates"].reshape(-1),
        arrays["root"].reshape(-1),
        arrays["shape"].reshape(-1),
        None if loaded.faces is None else np.asarray(loaded.faces, np.int64),
    )


def in_topology(model: BodyModel, scan: PosedScan) -> bool:
    """Whether the scan is a mesh in the model's topology: its vertices (V, 3) and its faces those of the
    model's template. Such a mesh's correspondence to the template is exact, so it is unposed as it is
    (:func:`seed_registrations`) instead of being projected and refined through a fit."""
    return (
        scan.faces is not None
        and scan.points.shape == (model.n_vertices, 3)
        and np.array_equal(scan.faces, np.asarray(model.faces))
    )


def chamfer_mm(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance (mm) between point sets a (N, 3) and b (M, 3) in metres: the mean of both
    directions' mean nearest-point distances."""
    d_ab = PointTree(b).query(a)[0]
    d_ba = PointTree(a).query(b)[0]
    return float(0.5 * (d_ab.mean() + d_ba.mean()) * 1e3)


def initial_shape(data: dict[str, np.ndarray], bind: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (n_shape,) of a bind-pose mesh (V, 3) in a space (its template span): where
    the projection into a new space starts from the scan's last registration."""
    mean, basis = space_basis(data)
    coef, *_ = np.linalg.lstsq(basis.T, np.asarray(bind, np.float64).reshape(-1) - mean, rcond=None)
    return np.asarray(coef)


def project_shape(
    model: BodyModel, scan: PosedScan, start: np.ndarray, rounds: int = 10, steps: int = 10
) -> np.ndarray:
    """Shape coefficients (n_shape,) of the body in ``model``'s space closest to the scan in the scan's fitted
    pose (BLiSS eq. 1 with the pose held): iterated closest points (both directions, pairs over 5 cm
    dropped) with L-BFGS on the coefficients and a weak N(0, 1) prior, from ``start`` (n_shape,): ``rounds``
    passes of closest points, ``steps`` L-BFGS iterations each. Each pass moves the body only as far as its
    pairs allow; on a raw scan (noise, holes) the coefficients are still changing after three passes and
    settle within about ten.

    The closest-point scheme is that of P. J. Besl and N. D. McKay, "A Method for Registration of 3-D
    Shapes", IEEE Transactions on Pattern Analysis and Machine Intelligence 14(2), 1992; L-BFGS that of D. C.
    Liu and J. Nocedal, "On the limited memory BFGS method for large scale optimization", Mathematical
    Programming 45, 1989.
    """
    decoder = model.decoder(torch.float64)
    q = torch.as_tensor(scan.coordinates[None])
    root = torch.as_tensor(scan.root[None])
    c = torch.tensor(start[None], dtype=torch.float64, requires_grad=True)
    tree = PointTree(scan.points)
    for _ in range(rounds):
        with torch.no_grad():
            v = decoder(c, q, root)[0][0].numpy()
        pairs = _closest_pairs(v, scan.points, tree)
        _fit_pairs(lambda shape: decoder(shape, q, root)[0][0], c, torch.as_tensor(scan.points), pairs, steps)
    return np.asarray(c.detach().numpy()[0])


def _closest_pairs(
    v: np.ndarray, points: np.ndarray, tree: PointTree, reach: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Closest-point pairs (vertex index, point index) of vertices (V, 3) and scan points (N, 3) both ways:
    each vertex to its nearest point and each point to its nearest vertex, pairs over ``reach`` m dropped;
    (K, 2) vertex -> point pairs and (M, 2) point -> vertex pairs."""
    d_m, near = tree.query(v, reach)
    keep_m = np.flatnonzero(np.isfinite(d_m))
    d_s, owner = PointTree(v).query(points, reach)
    keep_s = np.flatnonzero(np.isfinite(d_s))
    return np.stack([keep_m, near[keep_m]], 1), np.stack([owner[keep_s], keep_s], 1)


def _fit_pairs(
    skin: Callable[[torch.Tensor], torch.Tensor],
    c: torch.Tensor,
    points: torch.Tensor,
    pairs: tuple[np.ndarray, np.ndarray],
    steps: int,
) -> None:
    """L-BFGS steps on the coefficients ``c`` (1, n_shape) (in place) for the squared distances of the
    ``pairs`` (:func:`_closest_pairs`) between the skin ``skin(c)`` (V, 3) and ``points`` (N, 3)."""
    to_point, to_vertex = (torch.as_tensor(p) for p in pairs)
    opt = torch.optim.LBFGS([c], max_iter=steps, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        verts = skin(c)
        loss = ((verts[to_point[:, 0]] - points[to_point[:, 1]]) ** 2).sum(1).mean()
        loss = loss + ((verts[to_vertex[:, 0]] - points[to_vertex[:, 1]]) ** 2).sum(1).mean()
        loss = loss + 1e-6 * (c**2).sum()
        loss.backward()
        return loss

    opt.step(closure)


def unpose(model: BodyModel, shape: np.ndarray, scan: PosedScan, posed: np.ndarray) -> np.ndarray:
    """The bind-pose mesh (V, 3) that ``model`` with ``shape`` (n_shape,) skins, in the scan's pose, onto the
    posed mesh (V, 3): the template plus the rest offsets D with A_i D_i = posed_i - skin_i, A_i each
    vertex's blended skinning rotation (linear blend skinning is affine in the rest position)."""
    decoder = model.decoder(torch.float64, "lbs")
    q = torch.as_tensor(scan.coordinates[None])
    with torch.no_grad():
        skin, _, frames, _ = decoder(torch.as_tensor(shape[None]), q, torch.as_tensor(scan.root[None]))
    A = decoder.blended_rotations(frames, q)[0]  # (V, 3, 3)
    D = np.linalg.solve(A, (np.asarray(posed, np.float64) - skin[0].numpy())[..., None])[..., 0]
    return np.asarray(rest_meshes(model.data, shape[None])[0] + D)


def register(
    model: BodyModel,
    scan: PosedScan,
    start: np.ndarray,
    nonrigid: NonRigidConfig | None = None,
) -> Registration:
    """Register ``scan`` in ``model``'s space (see the module docstring): the shape projected from ``start``
    (n_shape,), refined non-rigidly, its offsets kept across the surface (:func:`across_surface`) and
    unposed."""
    shape = project_shape(model, scan, start)
    with torch.no_grad():
        v = model.decoder(torch.float64, "lbs")(
            torch.as_tensor(shape[None]),
            torch.as_tensor(scan.coordinates[None]),
            torch.as_tensor(scan.root[None]),
        )[0][0].numpy()
    posed = across_surface(v, refine_nonrigid(v, model.faces, scan.points, nonrigid), model.faces)
    bind = unpose(model, shape, scan, posed)
    scales = segment_scales(model.data, shape[None])[0]
    return Registration(scan.name, bind, scales, posed, chamfer_mm(posed, scan.points))


def across_surface(body: np.ndarray, refined: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The refined registration (V, 3) with its offsets from the projected ``body`` (V, 3) kept only along
    the body's vertex normals (``faces`` (F, 3)).

    A raw scan fixes where the surface is, not which vertex lies where on it: the offsets' part along the
    surface is correspondence drift (closest points pull vertices along holes' rims and noisy patches),
    which the re-learned PCA would take for shape. Soft tissue the space misses lies across the surface.
    """
    normals = vertex_normals(body, faces)
    offsets = np.asarray(refined, np.float64) - body
    return np.asarray(body + (offsets * normals).sum(1, keepdims=True) * normals)


def seed_registrations(model: BodyModel, meshes: list[PosedScan]) -> tuple[np.ndarray, np.ndarray]:
    """Registered meshes in the model's topology (their ``points`` (V, 3): the mesh's vertices in the model's
    frame, with their first fit) unposed to the bind pose as they are: meshes (N, V, 3) and the segment
    scales (N, n_seg, 3) of their fitted shapes.

    Raises:
        BodyfitError: a mesh does not have the model's vertex count (not in its topology).
    """
    wrong = [m.name for m in meshes if m.points.shape != (model.n_vertices, 3)]
    if wrong:
        raise BodyfitError(
            f"seed registrations must be meshes in the body model's topology ({model.n_vertices} vertices): "
            f"{', '.join(wrong)} are not"
        )
    bind = np.stack([unpose(model, m.shape, m, m.points) for m in meshes])
    return bind, segment_scales(model.data, np.stack([m.shape for m in meshes]))
