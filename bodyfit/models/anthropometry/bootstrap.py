"""A shape space grown from measurements: BLiSS's bootstrap with survey rows in place of scans.

BLiSS (S. Muralikrishnan, C.-H. P. Huang, D. Ceylan and N. J. Mitra, "BLiSS: Bootstrapped Linear Shape
Space", International Conference on 3D Vision (3DV), 2024, sections 3.2-3.4) grows a linear shape space
from unregistered scans: project each scan into the current space, refine the projection beyond the space
(a neural deformation there), accept the refinements within the round's smallest error plus one standard
deviation, re-learn the PCA from the accepted bodies with the ones it had, and repeat.

Here a person is a row of measurements. The refinement beyond the space is a build
(:func:`~bodyfit.models.anthropometry.inverse.fit_measurements`) in the space widened by smooth
displacement fields of the skin (:func:`smooth_fields`: the lowest vibration modes of the mesh, a
band-limited deformation as in B. Vallet and B. Lévy, "Spectral geometry processing with manifold
harmonics", Computer Graphics Forum 27(2), 2008), with a standard-normal prior on them as on the space's own
coefficients. The accepted bodies' bind-pose meshes, mirrored to symmetry, join the model's own population,
and the space is recomputed from them (:func:`~bodyfit.models.spaces.population.recompute_space`: bone PCA,
bone correctives, identity PCA, joint regressor).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh

from bodyfit.models.anthropometry.definitions import MEASUREMENTS
from bodyfit.models.anthropometry.inverse import NAMES, TOLERANCE, fit_measurements, sex_prior_mean
from bodyfit.models.body.model import BodyModel
from bodyfit.models.spaces.population import (
    Population,
    recompute_space,
    rest_meshes,
    sample_population,
    segment_scales,
    symmetric,
)

FIELD_SIZE = 0.01
"""Largest displacement (metres) of one smooth field at one coefficient: a standard deviation of the
widened space moves the skin by up to a centimetre."""
_TOL = np.array([TOLERANCE[MEASUREMENTS[n].kind] for n in NAMES])


def smooth_fields(model: BodyModel, modes: int) -> np.ndarray:
    """Symmetric smooth displacement fields (F, V, 3) of the model's skin: the ``modes`` lowest non-constant
    eigenvectors of the mesh's graph Laplacian, each along x, y and z, averaged with its mirror image
    across the sagittal plane (the antisymmetric ones vanish), orthogonalised and scaled to
    :data:`FIELD_SIZE` at their largest."""
    faces = np.asarray(model.faces)
    V = model.n_vertices
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    adjacency = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(V, V)).tocsr()
    adjacency = ((adjacency + adjacency.T) > 0).astype(np.float64)
    laplacian = sp.diags(np.asarray(adjacency.sum(1)).ravel()) - adjacency
    # A fixed start vector: ARPACK's random one would change the fields from run to run.
    start = np.random.default_rng(0).standard_normal(V)
    _, vectors = eigsh(laplacian.tocsc(), k=modes + 1, sigma=-1e-3, which="LM", v0=start)
    mirror = np.asarray(model.data["mirror"])
    flip = np.array([1.0, 1.0, -1.0])
    fields = []
    for k in range(1, modes + 1):
        for axis in range(3):
            f = np.zeros((V, 3))
            f[:, axis] = vectors[:, k]
            fields.append(0.5 * (f + f[mirror] * flip))
    flat = np.stack(fields).reshape(len(fields), -1)
    q, r = np.linalg.qr(flat.T)
    keep = np.abs(np.diag(r)) > 1e-6 * np.abs(np.diag(r)).max()
    out = q[:, keep].T.reshape(-1, V, 3)
    return out * (FIELD_SIZE / np.linalg.norm(out, axis=2).max(1))[:, None, None]


def widened(model: BodyModel, fields: np.ndarray) -> BodyModel:
    """The model with ``fields`` (F, V, 3) appended to its identity basis: coefficients
    [bone, identity, fields]."""
    data = dict(model.data)
    data["identity_basis"] = np.concatenate([data["identity_basis"], fields.astype(np.float32)])
    data["heldout_shape"] = np.zeros((1, model.n_shape + len(fields)), np.float32)
    return BodyModel(model.skeleton, data)


def accepted(misfit: np.ndarray) -> np.ndarray:
    """(N,) bool: misfits (N,) within the round's smallest plus one standard deviation (BLiSS 3.4)."""
    return np.asarray(misfit <= misfit.min() + misfit.std())


@dataclass
class BootstrapResult:
    """``data``: the grown space's ``body.npz`` arrays; ``rounds``: per round, the people accepted and their
    median misfit (RMS of the residuals in tolerances)."""

    data: dict[str, np.ndarray]
    rounds: list[dict[str, float]] = field(default_factory=list)


def bootstrap_space(
    model: BodyModel,
    rows: dict[str, np.ndarray],
    rounds: int = 2,
    modes: int = 40,
    n_identity: int | None = None,
    n_population: int = 200,
    seed: int = 0,
) -> BootstrapResult:
    """Grow the model's shape space from survey rows (see the module docstring).

    Args:
        model: the :class:`~bodyfit.models.body.model.BodyModel` to grow from.
        rows: sex -> (N, M) measurements in :data:`~bodyfit.models.anthropometry.inverse.NAMES` order, NaN
            where not taken.
        rounds: bootstrap rounds.
        modes: Laplacian modes of the smooth fields (about 1.5 fields per mode survive the symmetry).
        n_identity: identity coefficients of the grown space (default the model's).
        n_population: bodies of the model's own space kept in every round's population (seed ``seed``).
    Returns:
        :class:`BootstrapResult`.
    """
    own = sample_population(model, n_population, seed)
    current = model
    result = BootstrapResult(dict(model.data))
    for _ in range(rounds):
        fields = smooth_fields(current, modes)
        wide = widened(current, fields)
        meshes, scales, misfits = [], [], []
        for sex, t in rows.items():
            mean = np.concatenate([sex_prior_mean(current, sex), np.zeros(len(fields))])
            shapes, achieved = fit_measurements(wide, t, mean)
            misfit = np.sqrt(np.nanmean(((achieved - t) / _TOL) ** 2, axis=1))
            keep = accepted(misfit)
            meshes.append(rest_meshes(wide.data, shapes[keep]))
            scales.append(segment_scales(wide.data, shapes[keep]))
            misfits.append(misfit)
        grown = Population(
            symmetric(np.concatenate(meshes), np.asarray(model.data["mirror"])), np.concatenate(scales)
        )
        result.data = recompute_space(model, own + grown, n_identity=n_identity)
        result.rounds.append(
            {"accepted": len(grown), "median_misfit": float(np.median(np.concatenate(misfits)))}
        )
        current = BodyModel(model.skeleton, result.data)
    return result
