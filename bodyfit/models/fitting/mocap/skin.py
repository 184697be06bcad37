"""The skin of a marker-calibrated subject: identity coefficients from the markers' positions.

:func:`~.fitter.fit_markers` calibrates the skeleton (segment scales) and poses it; the skin (the identity
coefficients c_s of ``V = V_mean + c_b P_bc + c_s P_s``) is left at the population mean. Here the markers
seen on a few frames spread over the motion set c_s, as MoSh does (M. Loper, N. Mahmood and M. J. Black,
"MoSh: Motion and Shape Capture from Sparse Markers", ACM Transactions on Graphics 33(6), SIGGRAPH Asia
2014): every skin-mounted marker sits a fixed distance :data:`MARKER_OFFSET` outside the posed skin along
its normal. The surface point under each marker is latent: it is the skin point nearest the marker, found
again after each solve.

The skeleton stays the calibrated one: the bone coefficients c_b are the least-squares fit of the calibrated
scales and the remainder goes to the decoder's segment scale offsets
(:meth:`~bodyfit.models.body.model.BodyModel.scaled_decoder`), so the skin's skeleton has exactly the
scales that the OpenSim files carry, and c_s moves the skin only.

At a fixed pose the skinned vertices are linear in c_s (linear blend skinning of a linear template), so each
solve is one regularised linear least-squares problem: point-to-plane residuals ``n . (p - v(c)) - d`` over
the markers and frames, and the shape prior ``|c_s|^2`` (the coefficients are in population standard
deviations, so this is the 1/SD^2 prior that keeps unobserved regions at the mean).

The identity can instead be the code of the spiral identity decoder (:mod:`bodyfit.models.decoders`): its
rest offsets are carried into the pose by each vertex's blended skinning rotation, and the decoder is
linearised about the current code (Gauss-Newton with the same residuals and the prior |code|^2).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from scipy.spatial import cKDTree

from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.errors import ShapeError
from bodyfit.models.fitting.common.surface import vertex_normals

if TYPE_CHECKING:
    from bodyfit.models.decoders.asset import SpiralAsset

# m: a 14 mm marker (the common gait-lab size) has its centre 7 mm off its base, and the base with its
# double-sided tape adds about 2.5 mm: the marker centre sits 9.5 mm outside the skin along the normal.
MARKER_OFFSET = 0.0095
SKIN_FRAMES = 8  # frames of the motion whose markers set the skin
RESIDUAL_SIGMA = 0.005  # m: marker scatter about the skin (soft tissue, placement, noise) per frame
MAX_GAP = 0.04  # m: a marker farther than this from the skin plane or its foot is not on the skin
ITERATIONS = 4  # re-finding the surface points under the markers


class MarkerSkinError(ShapeError):
    """Inputs the skin step cannot use: shapes that disagree or too few markers on the skin."""


@dataclass(frozen=True)
class MarkerSkin:
    """The subject's body: shape (n_shape,) = [c_b, c_s]; scale_offsets (n_seg, 3) that make the decoder's
    scales the calibrated ones; frames (K,) the frames used; used (K, M) bool: the markers taken as on the
    skin; residual_mm: their mean distance from ``MARKER_OFFSET`` off the skin after the fit. With the
    spiral decoder: code (d,) its identity code and rest_offsets (V, 3) its identity offsets (m), c_s = 0."""

    shape: np.ndarray
    scale_offsets: np.ndarray
    frames: np.ndarray
    used: np.ndarray
    residual_mm: float
    code: np.ndarray | None = None
    rest_offsets: np.ndarray | None = None

    def decoder(self, model: BodyModel) -> BodyDecoder:
        """The float32 decoder whose skeleton is the calibrated one (carrying the spiral offsets if any)."""
        decoder = model.scaled_decoder(self.scale_offsets)
        return decoder if self.rest_offsets is None else decoder.with_offsets(self.rest_offsets)

    def vertices(
        self, model: BodyModel, coordinates: np.ndarray, root: np.ndarray, chunk: int = 64
    ) -> np.ndarray:
        """Skin vertices (T, V, 3) float32 of coordinates (T, n_dof) and roots (T, 3), ``chunk`` frames at a
        time."""
        q = np.asarray(coordinates, np.float64)
        r = np.asarray(root, np.float64)
        if q.ndim != 2 or r.shape != (len(q), 3):
            raise MarkerSkinError(
                f"coordinates (T, n_dof) and root (T, 3) expected; got {q.shape}, {r.shape}"
            )
        posed = self.decoder(model).posed(torch.as_tensor(self.shape[None], dtype=torch.float32))
        out = np.empty((len(q), model.n_vertices, 3), np.float32)
        with torch.no_grad():
            for a in range(0, len(q), chunk):
                qt = torch.as_tensor(q[a : a + chunk], dtype=torch.float32)
                out[a : a + chunk] = posed(qt, torch.as_tensor(r[a : a + chunk], dtype=torch.float32)).numpy()
        return out


def bone_coefficients(model: BodyModel, scales: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bone coefficients c_b (n_bone,) whose scales ``s_mean + c_b P_b`` are nearest (least squares) the
    calibrated ``scales`` (n_seg, 3), and the remainder (n_seg, 3) as segment scale offsets."""
    mean = np.asarray(model.data["scale_mean"], np.float64)
    basis = np.asarray(model.data["scale_basis"], np.float64).reshape(model.n_bone, -1)
    s = np.asarray(scales, np.float64)
    if s.shape != mean.shape or not np.isfinite(s).all():
        raise MarkerSkinError(f"scales must be finite with shape {mean.shape}; got {s.shape}")
    c, *_ = np.linalg.lstsq(basis.T, (s - mean).reshape(-1), rcond=None)
    return c, s - mean - (c @ basis).reshape(mean.shape)


def spread_frames(observed: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` frames (sorted indices) spread evenly over a trial (T, M, 3), among those showing
    at least 80% of the most markers any frame shows."""
    seen = np.isfinite(observed).all(-1).sum(-1)
    good = np.flatnonzero(seen >= 0.8 * seen.max())
    return good[np.unique(np.linspace(0, len(good) - 1, min(count, len(good))).round().astype(int))]


def _linear_skin(
    decoder: BodyDecoder, c_b: np.ndarray, n_identity: int, q: np.ndarray, root: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The posed skin as a linear function of c_s: base (K, V, 3) at c_s = 0 and basis (n_id, K, V, 3)."""
    K = len(q)
    shapes = np.zeros((1 + n_identity, len(c_b) + n_identity))
    shapes[:, : len(c_b)] = c_b
    shapes[1:, len(c_b) :] = np.eye(n_identity)
    S = torch.as_tensor(np.repeat(shapes, K, axis=0))
    Q = torch.as_tensor(np.tile(q, (1 + n_identity, 1)))
    R = torch.as_tensor(np.tile(root, (1 + n_identity, 1)))
    with torch.no_grad():
        v = decoder(S, Q, R)[0].numpy().reshape(1 + n_identity, K, -1, 3)
    return v[0], v[1:] - v[0]


def _assemble(
    verts: np.ndarray, basis: np.ndarray, faces: np.ndarray, observed: np.ndarray, offset: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point-to-plane rows at the current skin verts (K, V, 3) for markers observed (K, M, 3): J (N, n_id)
    and b (N,) with residual ``b - J dc`` for a change dc of c_s, and used (K, M) bool."""
    normals = vertex_normals(verts, faces)
    rows_j, rows_b = [], []
    used = np.zeros(observed.shape[:2], bool)
    for k in range(len(verts)):
        seen = np.flatnonzero(np.isfinite(observed[k]).all(-1))
        if not len(seen):
            continue
        p = observed[k, seen]
        _, idx = cKDTree(verts[k]).query(p)
        n, d = normals[k, idx], p - verts[k, idx]
        along = (n * d).sum(-1)
        across = np.linalg.norm(d - along[:, None] * n, axis=-1)
        ok = (np.abs(along - offset) < MAX_GAP) & (across < MAX_GAP)
        used[k, seen[ok]] = True
        rows_b.append(along[ok] - offset)
        rows_j.append(np.einsum("mc,imc->mi", n[ok], basis[:, k, idx[ok]]))
    n_id = basis.shape[0]
    J = np.concatenate(rows_j) if rows_j else np.zeros((0, n_id))
    b = np.concatenate(rows_b) if rows_b else np.zeros(0)
    return J, b, used


Linearisation = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""Identity coefficients c (n,) -> the posed skin about them as base (K, V, 3) and basis (n, K, V, 3):
verts(c') ~ base + c' . basis."""


def fit_skin(
    model: BodyModel,
    scales: np.ndarray,
    coordinates: np.ndarray,
    root: np.ndarray,
    observed: np.ndarray,
    *,
    spiral: SpiralAsset | None = None,
    frames: int = SKIN_FRAMES,
    offset: float = MARKER_OFFSET,
    sigma: float = RESIDUAL_SIGMA,
) -> MarkerSkin:
    """The identity that puts the observed markers ``offset`` outside the posed skin.

    Args:
        model: the body model. scales: (n_seg, 3) calibrated segment scales (kept exactly).
        coordinates: (T, n_dof), root: (T, 3): the poses of the trial's frames (from the marker IK).
        observed: (T, M, 3) marker positions (m; NaN where missing), any marker set: markers that are not
            within :data:`MAX_GAP` of the skin (on wands, or mislabelled) are left out on each frame.
        spiral: None: the identity is the linear identity PCA's coefficients; a spiral decoder asset
            (:func:`~bodyfit.models.decoders.asset.load_asset`): its code (``MarkerSkin.code``), the skin then
            carrying the decoder's offsets (``MarkerSkin.rest_offsets``) on the bone-only template.
        frames: how many frames spread over the motion are used. offset: marker centre to skin (m).
        sigma: marker scatter about the skin (m) per frame: weight of the markers against the shape prior.
    Returns:
        :class:`MarkerSkin`.
    Raises:
        MarkerSkinError: shapes that disagree, non-finite poses, or fewer than 3 markers on the skin.
    """
    q, r, obs = _checked(model, coordinates, root, observed)
    c_b, offsets = bone_coefficients(model, scales)
    pick = spread_frames(obs, frames)
    decoder = model.scaled_decoder(offsets, torch.float64)
    base, basis = _linear_skin(decoder, c_b, model.n_identity, q[pick], r[pick])
    if spiral is None:
        c, used, residual = _solve(
            lambda _: (base, basis), model.n_identity, model.faces, obs[pick], offset, sigma
        )
        return MarkerSkin(np.concatenate([c_b, c]), offsets, pick, used, residual)
    with torch.no_grad():
        shape = torch.as_tensor(np.concatenate([c_b, np.zeros(model.n_identity)])[None].repeat(len(pick), 0))
        frames_k = decoder(shape, torch.as_tensor(q[pick]), torch.as_tensor(r[pick]))[2]
    turn = decoder.blended_rotations(frames_k, torch.as_tensor(q[pick]))  # (K, V, 3, 3)
    code, used, residual = _solve(
        _spiral_linearisation(spiral, base, turn), spiral.decoder.d, model.faces, obs[pick], offset, sigma
    )
    rest = spiral_offsets(spiral, code[None])[0]
    return MarkerSkin(
        np.concatenate([c_b, np.zeros(model.n_identity)]), offsets, pick, used, residual, code, rest
    )


def _checked(
    model: BodyModel, coordinates: np.ndarray, root: np.ndarray, observed: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The poses and markers of :func:`fit_skin` as float64 arrays, checked."""
    q, r, obs = (np.asarray(a, np.float64) for a in (coordinates, root, observed))
    T = len(q)
    if q.ndim != 2 or q.shape[1] != model.skeleton.n_dof or r.shape != (T, 3) or obs.shape[:1] != (T,):
        raise MarkerSkinError(
            f"coordinates (T, {model.skeleton.n_dof}), root (T, 3) and observed (T, M, 3) must share T; got "
            f"{q.shape}, {r.shape}, {obs.shape}"
        )
    if obs.ndim != 3 or obs.shape[2] != 3 or T == 0:
        raise MarkerSkinError(f"observed markers must have shape (T, M, 3) with T > 0; got {obs.shape}")
    if not (np.isfinite(q).all() and np.isfinite(r).all()):
        raise MarkerSkinError("coordinates and root must be finite")
    return q, r, obs


def spiral_offsets(spiral: SpiralAsset, code: np.ndarray) -> np.ndarray:
    """The spiral decoder's rest-pose identity offsets (B, V, 3) float64 of codes (B, d) in standard
    deviations of the training codes."""
    z = torch.as_tensor(spiral.latent_mean + np.asarray(code) * spiral.latent_std, dtype=torch.float32)
    with torch.no_grad():
        return spiral.decoder(z).double().numpy()


def _spiral_linearisation(spiral: SpiralAsset, bone_only: np.ndarray, turn: np.ndarray) -> Linearisation:
    """The posed skin about a spiral code: ``bone_only`` (K, V, 3) is the posed template without identity,
    ``turn`` (K, V, 3, 3) each vertex's blended skinning rotation, which carries a rest offset into the pose.
    The decoder's derivative is a central difference (step 0.05 SD): d forward passes instead of V."""
    d = spiral.decoder.d

    def linearise(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        step = 0.05 * np.eye(d)
        D = spiral_offsets(spiral, np.concatenate([code[None], code + step, code - step]))
        slope = (D[1 : 1 + d] - D[1 + d :]) / 0.1  # (d, V, 3)
        basis = np.einsum("kvij,nvj->nkvi", turn, slope)
        base = bone_only + np.einsum("kvij,vj->kvi", turn, D[0]) - np.einsum("n,nkvi->kvi", code, basis)
        return base, basis

    return linearise


def _solve(
    linearise: Linearisation, n: int, faces: np.ndarray, observed: np.ndarray, offset: float, sigma: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Gauss-Newton on the identity (n,) from 0: point-to-plane marker residuals (:func:`_assemble`) against
    the prior |c|^2. Returns the identity, the markers used (K, M) and their mean residual (mm)."""
    c = np.zeros(n)
    weight = 1.0 / (sigma**2 * len(observed))  # the frames see the same markers: together they count as one
    for _ in range(ITERATIONS):
        base, basis = linearise(c)
        verts = base + np.einsum("i,ikvc->kvc", c, basis)
        J, b, used = _assemble(verts, basis, faces, observed, offset)
        if used.any(axis=0).sum() < 3:
            raise MarkerSkinError("fewer than 3 markers lie on the skin: the markers do not match the poses")
        # residual b - J dc about c: minimise w |b - J dc|^2 + |c + dc|^2
        c = c + np.linalg.solve(weight * J.T @ J + np.eye(n), weight * J.T @ b - c)
    base, basis = linearise(c)
    _, b, used = _assemble(base + np.einsum("i,ikvc->kvc", c, basis), basis, faces, observed, offset)
    return c, used, float(np.abs(b).mean() * 1000)
