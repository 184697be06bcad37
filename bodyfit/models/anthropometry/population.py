"""Shape priors of real populations: draws of bodies whose measurements are distributed as a survey's people.

A population is a mixture over its people: each person ``i`` of the survey, with measurements ``m_i``
(NaN where not taken), defines the Gaussian posterior over the shape coefficients under the prior of the
person's sex, ``N(mu_s, I)`` (the mean ANSUR II body of the sex, :func:`~bodyfit.models.anthropometry.
inverse.sex_prior_mean`, with the model's own spread), and Gaussian measurement errors ``W^-1/2``,
linearised at the mean body:

    c | m_i  ~  N(c_i, (J^T W J + I)^-1),

with ``c_i`` the body built from ``m_i`` (:func:`~bodyfit.models.anthropometry.inverse.fit_measurements`).
A draw picks a person (by survey weight), then a body from that person's posterior: what the survey
measured is kept, what it did not measure varies as the model's population does. NHANES people (five
measurements each) are built to a tenth of the usual tolerances (:data:`NHANES_TOLERANCE`): at the usual
ones the prior holds the built men's hip circumference 13 mm above and their waist 11 mm below the
survey's (median over 200), which alone moves the Kolmogorov-Smirnov statistic of those measurements to
0.07-0.10. Building a prior from bodies fitted to a population's data is the first round of the bootstrap
of BLiSS (S. Muralikrishnan, C.-H. P. Huang, D. Ceylan and N. J. Mitra, "BLiSS: Bootstrapped Linear Shape
Space", International Conference on 3D Vision (3DV), 2024), with measurements instead of scans; the
model's shape space itself is not re-learned here.

The people's bodies are built once (:func:`build_populations`; ``python benchmarks/anthropometry.py
populations``) and stored with the package in ``populations.npz``; :func:`sample` draws from them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bodyfit.models.anthropometry.definitions import MEASUREMENTS
from bodyfit.models.anthropometry.inverse import (
    MAX_SD,
    NAMES,
    TOLERANCE,
    fit_measurements,
    mean_jacobian,
    sex_prior_mean,
)
from bodyfit.models.anthropometry.ranges import SEXES
from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import BodyfitError

POPULATIONS = ("nhanes", "ansur", "anny")
"""``nhanes``: US adults (NHANES 2017-2020); ``ansur``: US Army personnel (ANSUR II, 2012); ``anny``: the
model's own standard-normal coefficients (anny's synthetic population)."""
POPULATION_FILE = Path(__file__).with_name("populations.npz")
_TOL = np.array([TOLERANCE[MEASUREMENTS[n].kind] for n in NAMES])
NHANES_TOLERANCE = 0.1
"""NHANES people's bodies are built to this fraction of :data:`~bodyfit.models.anthropometry.inverse.
TOLERANCE` (see the module docstring)."""


class PopulationError(BodyfitError):
    """An unknown population or sex, or a population file built for another shape space."""


@dataclass(frozen=True)
class Population:
    """The people of one survey and sex: ``shapes`` (N, n_shape) their bodies' coefficients, ``weights`` (N,)
    summing to one, ``spread`` (n_shape, n_shape) the Cholesky factor of the posterior covariance a
    person's body is drawn with."""

    shapes: np.ndarray
    weights: np.ndarray
    spread: np.ndarray


def shape_space_probe(model: BodyModel) -> np.ndarray:
    """(5, k, 3) every 97th skin vertex of the mean body and four unit bodies in the measuring posture: a
    population file stores it and is refused for a model whose probe differs by more than 0.1 mm (a shape
    space it was not built for)."""
    import torch

    from bodyfit.models.anthropometry.measure import body_in_pose

    probes = torch.cat([torch.zeros(1, model.n_shape), torch.eye(model.n_shape)[:4]]).double()
    with torch.no_grad():
        vertices, _ = body_in_pose(model, probes)
    return vertices[:, ::97].numpy()


def posterior_spread(model: BodyModel, given: np.ndarray, tolerance: np.ndarray) -> np.ndarray:
    """(n_shape, n_shape) Cholesky factor of ``(J^T W J + I)^-1``: the spread of bodies around one built
    from the measurements ``given`` (M,) bool with errors ``tolerance`` (M,), under the model's own
    spread, with the Jacobian at the mean body (the measurements are nearly linear in the coefficients)."""
    _, J = mean_jacobian(model)
    Jw = J[given] / tolerance[given, None]
    return np.linalg.cholesky(np.linalg.inv(Jw.T @ Jw + np.eye(model.n_shape)))


def build_population(
    model: BodyModel,
    rows: np.ndarray,
    sex: str,
    tolerance: float = 1.0,
    weights: np.ndarray | None = None,
    steps: int = 8,
) -> Population:
    """The bodies of a survey's people of one sex.

    Args:
        rows: (N, M) measurements in :data:`~bodyfit.models.anthropometry.inverse.NAMES` order, NaN where
            not taken; the measurements taken must be the same for every person.
        sex: "male" or "female".
        tolerance: the fraction of :data:`~bodyfit.models.anthropometry.inverse.TOLERANCE` the bodies are
            built to.
        weights: (N,) the people's survey weights, default equal.
        steps: Gauss-Newton steps per body.
    """
    given = np.isfinite(rows)
    if not (given == given[:1]).all():
        raise PopulationError("every person of a population needs the same measurements")
    tol = tolerance * _TOL
    shapes, _ = fit_measurements(model, rows, sex_prior_mean(model, sex), steps=steps, tolerance=tol)
    w = np.ones(len(rows)) if weights is None else np.asarray(weights, np.float64)
    return Population(shapes, w / w.sum(), posterior_spread(model, given[0], tol))


def build_populations(
    model: BodyModel,
    ansur: dict[str, np.ndarray],
    nhanes: dict[str, np.ndarray],
    path: Path = POPULATION_FILE,
    steps: int = 8,
) -> dict[str, Population]:
    """Build and write the ``ansur`` and ``nhanes`` populations of both sexes (see the module docstring).

    Args:
        ansur, nhanes: sex -> (N, M) measurement rows in ``NAMES`` order (NaN where the survey has no
            column); NHANES rows with a measurement missing are left out. The sexes given are built.
        steps: Gauss-Newton steps per body.
    Returns:
        "{population}_{sex}" -> :class:`Population`, as written to ``path``.
    """
    out: dict[str, Population] = {}
    for sex in ansur:
        out[f"ansur_{sex}"] = build_population(model, ansur[sex], sex, steps=steps)
        rows = nhanes[sex]
        taken = np.isfinite(rows).any(0)
        complete = rows[np.isfinite(rows[:, taken]).all(1)]
        out[f"nhanes_{sex}"] = build_population(model, complete, sex, NHANES_TOLERANCE, steps=steps)
    arrays: dict[str, np.ndarray] = {"probe": shape_space_probe(model)}
    for key, p in out.items():
        arrays |= {f"{key}_shapes": p.shapes.astype(np.float32), f"{key}_weights": p.weights}
        arrays[f"{key}_spread"] = p.spread
    np.savez_compressed(path, allow_pickle=False, **arrays)
    return out


def load_populations(model: BodyModel, path: Path = POPULATION_FILE) -> dict[str, Population]:
    """The populations stored at ``path``, checked against the model's shape space; read once per model
    and path.

    Raises:
        PopulationError: no file, or one built for another shape space.
    """
    key = f"anthropometry.populations:{path.resolve()}"
    return model.derived(key, lambda: _read_populations(model, path))


def _read_populations(model: BodyModel, path: Path) -> dict[str, Population]:
    if not path.exists():
        raise PopulationError(f"no population file at {path}: python benchmarks/anthropometry.py populations")
    with np.load(path, allow_pickle=False) as f:
        keys = {k.rsplit("_", 1)[0] for k in f.files if k != "probe"}
        probe = f["probe"]
        people = {
            k: Population(f[f"{k}_shapes"].astype(np.float64), f[f"{k}_weights"], f[f"{k}_spread"])
            for k in keys
        }
    ours = shape_space_probe(model)
    if probe.shape != ours.shape or not np.allclose(probe, ours, atol=1e-4):
        raise PopulationError(
            f"{path.name} was built for another shape space; rebuild it: "
            "python benchmarks/anthropometry.py populations"
        )
    return people


def sample(
    model: BodyModel,
    n: int,
    sex: str | None = None,
    population: str = "nhanes",
    seed: int = 0,
) -> np.ndarray:
    """(n, n_shape) shape coefficients of bodies drawn from a real population (see the module docstring).

    Args:
        model: the body model.
        n: how many bodies.
        sex: "male", "female", or None for both, half and half (each body's sex drawn at random).
        population: one of :data:`POPULATIONS`; "anny" is the model's standard normal.
        seed: the random generator's seed.
    Raises:
        PopulationError: an unknown population or sex, or no population file for this shape space.
    """
    if population not in POPULATIONS:
        raise PopulationError(f"population must be one of {', '.join(POPULATIONS)}; got {population!r}")
    if sex is not None and sex not in SEXES:
        raise PopulationError(f"sex must be 'male', 'female' or None; got {sex!r}")
    rng = np.random.default_rng(seed)
    if population == "anny":
        return rng.standard_normal((n, model.n_shape))
    people = load_populations(model)
    sexes = np.full(n, sex) if sex is not None else rng.choice(SEXES, n)
    out = np.empty((n, model.n_shape))
    for s in SEXES:
        rows = np.flatnonzero(sexes == s)
        p = people[f"{population}_{s}"]
        picked = rng.choice(len(p.shapes), len(rows), p=p.weights)
        out[rows] = p.shapes[picked] + rng.standard_normal((len(rows), model.n_shape)) @ p.spread.T
    # The heaviest people are built at the bound of the shape space; their spread stays inside it.
    return np.clip(out, -MAX_SD, MAX_SD)
