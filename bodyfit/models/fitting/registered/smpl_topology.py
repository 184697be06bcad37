"""SMPL's 6,890-vertex topology: a dense correspondence to our template, so any SMPL-topology mesh fits as
a registered mesh.

Built once (asset build) by fitting our model, as a raw scan with a known orientation and a T-pose start,
to two CC BY 4.0 bodies in SMPL topology (``data/smpl_ccby``: human_man.obj, human_woman.obj; Max Planck
Society via SMPL, see data/smpl_ccby/README.md), refining non-rigidly, and locating each of our vertices on
the SMPL surface (face + barycentric coordinates). Where the two bodies disagree or the surfaces are far
apart (our eyes and mouth interior, which SMPL lacks) a vertex gets weight 0 and is left out of fits.

At fit time an SMPL-topology mesh is turned into our frame (SMPL is +Y up and faces +Z; we face +X with +Z
to the body's right; a mesh in another orientation gives its own rotation), interpolated at our vertices and
fitted by :class:`RegisteredFitter` with those weights. :func:`fit_smpl_mesh` answers in the mesh's own
frame, with the map to the parameters' frame alongside, as every mesh fit does.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse

from bodyfit.io.scans import load_scan, sample_surface
from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import ShapeError
from bodyfit.models.fitting.common.surface import closest_on_surface, point_to_surface
from bodyfit.models.fitting.registered.fitter import BodyFit, RegisteredFitter
from bodyfit.models.fitting.scan.fitter import Progress, ScanFit, ScanFitter
from bodyfit.models.skeleton.model import check_finite

SMPL_VERTICES = 6890
SMPL_TO_BODY = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # body = SMPL_TO_BODY @ smpl
ASSET = "smpl_topology.npz"
SOURCE_DIR = Path(__file__).resolve().parents[4] / "data" / "smpl_ccby"
SOURCES = ("human_man.obj", "human_woman.obj")
MAX_GAP_M = 0.015  # our vertex further than this from the SMPL surface: not used in fits
SCAN_SAMPLES = 40_000


@dataclass(frozen=True)
class TopologyMap:
    """Our V vertices as points on another topology's surface.

    faces: (F_other, 3) the other topology's faces; face: (V,) a face per vertex of ours; bary: (V, 3)
    barycentric coordinates in it; weight: (V,) 1 where the correspondence is trusted, else 0.
    """

    faces: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    weight: np.ndarray

    def transfer(self, other: np.ndarray) -> np.ndarray:
        """Meshes (B, N_other, 3) in the other topology -> (B, V, 3) points at our vertices."""
        B, N, _ = other.shape
        flat = np.moveaxis(np.asarray(other), 0, 1).reshape(N, B * 3)  # one sparse product for every mesh
        return np.moveaxis((self.matrix(N) @ flat).reshape(-1, B, 3), 1, 0)

    def matrix(self, n_other: int) -> sparse.csr_matrix:
        """(V, n_other) sparse interpolation matrix: three barycentric weights per row."""
        rows = np.repeat(np.arange(len(self.face)), 3)
        return sparse.csr_matrix(
            (self.bary.ravel(), (rows, self.faces[self.face].ravel())), shape=(len(self.face), n_other)
        )

    def save(self, path: Path) -> None:
        np.savez_compressed(path, faces=self.faces, face=self.face, bary=self.bary, weight=self.weight)

    @classmethod
    def load(cls, path: Path) -> TopologyMap:
        with np.load(path) as d:
            return cls(d["faces"], d["face"], d["bary"], d["weight"])


def t_pose(model: BodyModel) -> np.ndarray:
    """(n_dof,) the bind pose with the arms raised sideways to horizontal and the elbows straight."""
    skel = model.skeleton
    q = model.bind_coordinates.copy()
    for side in ("r", "l"):
        q[skel.dof_index(f"arm_add_{side}")] = -np.pi / 2
        q[skel.dof_index(f"elbow_flex_{side}")] = 0.0
    return q


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) in metres and triangle faces (F, 3) of a Wavefront OBJ in metres."""
    mesh = load_scan(path, units="m")
    if mesh.faces is None:
        raise ShapeError(f"{path} has no faces; a mesh in SMPL topology is needed")
    return mesh.points, mesh.faces


def build_smpl_topology(
    model: BodyModel, sources: list[tuple[np.ndarray, np.ndarray]]
) -> tuple[TopologyMap, dict[str, Any]]:
    """Fit every source (SMPL-topology vertices (6890, 3) in SMPL's frame, faces) as a scan, and locate our
    registered vertices on its surface; per vertex keep the source where it lies closest.

    Returns:
        the map and build metrics per source (scan fit report, mean gap of our registration to the SMPL
        surface, vertices trusted).
    """
    fitter = ScanFitter(model)
    faces = sources[0][1]
    best_gap = np.full(model.n_vertices, np.inf)
    face = np.zeros(model.n_vertices, np.int64)
    bary = np.zeros((model.n_vertices, 3))
    metrics: dict[str, Any] = {}
    for k, (verts, f) in enumerate(sources):
        body = verts @ SMPL_TO_BODY.T
        points, _ = sample_surface(body, f, SCAN_SAMPLES, seed=k)
        fit = fitter.fit(np.concatenate([points, body]), orientation=np.eye(3), start=t_pose(model))
        fk, bk, gap = closest_on_surface(fit.registration, body, f)
        better = gap < best_gap
        face[better], bary[better], best_gap[better] = fk[better], bk[better], gap[better]
        metrics[f"source_{k}"] = {
            "scan_to_model_mm": round(fit.report.distances.mean, 3),
            "registration_gap_mm": round(float(np.mean(gap)) * 1000, 3),
        }
    weight = (best_gap < MAX_GAP_M).astype(np.float64)
    metrics["trusted_vertices"] = int(weight.sum())
    return TopologyMap(faces, face, bary, weight), metrics


def smpl_map(folder: Path | None = None) -> TopologyMap:
    """The stored SMPL-topology map (asset ``smpl_topology.npz``)."""
    from bodyfit.models.assets import assets_dir

    return TopologyMap.load((folder or assets_dir()) / ASSET)


def refine_smpl_fit(
    scanner: ScanFitter,
    fit: BodyFit,
    mesh: np.ndarray,
    faces: np.ndarray,
    index: int = 0,
    progress: Progress | None = None,
    to_body: np.ndarray | None = None,
) -> ScanFit:
    """Body ``index`` of a :func:`fit_smpl_meshes` fit refined on its mesh's surface (vertices (6890, 3) in
    SMPL's frame, or turned into ours by ``to_body`` as for :func:`fit_smpl_meshes`; faces (F, 3)) by
    :meth:`ScanFitter.refine`: point-to-plane phases from the fitted body, then the non-rigid registration;
    parameters and registration in our frame, as the fit's. The map's correspondences hold the body where
    the map is wrong (hands, feet); the surface does not: on the two CC BY bodies the mesh's vertices lie
    1.7 / 1.6 mm from the refined registration against 6.2 / 5.6 mm from the registered fit, for about
    1 s more per mesh."""
    body = np.asarray(mesh, np.float64) @ (SMPL_TO_BODY if to_body is None else to_body).T
    surface, _ = sample_surface(body, faces, SCAN_SAMPLES, seed=index)
    points = np.concatenate([body, surface])
    return scanner.refine(points, fit.shape[index], fit.coordinates[index], fit.root[index], progress)


def fit_smpl_mesh(
    registered: RegisteredFitter,
    scanner: ScanFitter,
    mesh: np.ndarray,
    faces: np.ndarray,
    to_body: np.ndarray | None = None,
    progress: Progress | None = None,
) -> ScanFit:
    """One mesh in SMPL's topology (vertices (6890, 3) metres, faces (F, 3)) placed through the map
    (:func:`fit_smpl_meshes`) and refined on its surface (:func:`refine_smpl_fit`), answered in the mesh's
    own frame: ``vertices``, ``registration`` and ``joints`` lie on the mesh as it was given, and
    ``scan_to_body`` (4, 4) maps the mesh's frame to the one the parameters pose the body in
    (``body = scan_to_body @ mesh``). ``to_body``: (3, 3) the rotation from the mesh's axes to ours (+X
    forward, +Y up, +Z right); default SMPL's convention (+Y up, facing +Z, :data:`SMPL_TO_BODY`)."""
    R = SMPL_TO_BODY if to_body is None else np.asarray(to_body, np.float64)
    placed = fit_smpl_meshes(registered, mesh, to_body=R)[0]
    fit = refine_smpl_fit(scanner, placed, mesh, faces, progress=progress, to_body=R)
    turn = np.eye(4)
    turn[:3, :3] = R
    # the refinement's frame is R @ mesh; a point x there is R.T @ x, as rows x @ R, in the mesh's
    return replace(
        fit,
        vertices=fit.vertices @ R,
        registration=fit.registration @ R,
        joints=fit.joints @ R,
        scan_to_body=fit.scan_to_body @ turn,
    )


def fit_smpl_meshes(
    fitter: RegisteredFitter,
    meshes: np.ndarray,
    topology: TopologyMap | None = None,
    to_body: np.ndarray | None = None,
) -> tuple[BodyFit, np.ndarray]:
    """Fit meshes in SMPL topology.

    Args:
        fitter: a registered-mesh fitter of our model.
        meshes: (B, 6890, 3) or (6890, 3) vertices in SMPL's frame (+Y up, facing +Z), metres.
        topology: the map (default: the stored asset).
        to_body: (3, 3) the rotation from the meshes' axes to ours (+X forward, +Y up, +Z right) for meshes
            in another orientation; default :data:`SMPL_TO_BODY`.
    Returns:
        the fit (parameters and registration in our frame) and each SMPL vertex's distance (B, 6890) to the
        fitted surface, metres.
    """
    x = np.asarray(meshes, np.float64)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[1:] != (SMPL_VERTICES, 3):
        raise ShapeError(f"SMPL-topology meshes must have shape (B, {SMPL_VERTICES}, 3); got {x.shape}")
    import torch

    check_finite("SMPL mesh vertices", torch.as_tensor(x))
    tmap = topology or smpl_map()
    body = x @ (SMPL_TO_BODY if to_body is None else np.asarray(to_body, np.float64)).T
    targets = tmap.transfer(body)
    fit = fitter.fit(targets, weights=np.repeat(tmap.weight[None], len(x), axis=0))
    faces = fitter.model.faces
    distances = np.stack([point_to_surface(body[b], fit.vertices[b], faces) for b in range(len(x))])
    return fit, distances
