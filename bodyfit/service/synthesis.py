"""Synthesis requests: the parameters of B bodies, checked for every transport before the model runs
(shapes, dtypes, finite values after the float32 cast, DOF ranges, plausible shape and root, the batch
limit)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.rig.subject import Subject
from bodyfit.models.skeleton.model import RANGE_TOLERANCE
from bodyfit.service.errors import InvalidInputError, LimitExceededError
from bodyfit.service.validation import check_plausible, float_array, invalid_input

Coordinates = np.ndarray | Mapping[str, float | Sequence[float] | np.ndarray] | None


@dataclass(frozen=True)
class SynthRequest:
    """shape (B, n_shape) or None (the mean body); coordinates (B, n_dof) in ``dof_names`` order, or a
    mapping DOF name -> value or (B,) values (missing DOFs are 0), or None (zero pose); root (B, 3) metres
    or None; skeleton: also pose the bone mesh; batch: B when nothing else gives it; measurements: instead
    of shape, build the body from these ({name: value}, docs/anthropometry.md) for ``sex`` (male, female or
    None), all B bodies with that shape (:meth:`bodyfit.service.core.BodyService.with_built_shape`);
    subject: instead of shape or measurements, a subject file (its ``.npz`` bytes or a :class:`Subject`):
    all B bodies are that person's (:mod:`bodyfit.service.personal`)."""

    shape: np.ndarray | None = None
    coordinates: Coordinates = None
    root: np.ndarray | None = None
    skeleton: bool = False
    batch: int | None = None
    measurements: Mapping[str, float] | None = None
    sex: str | None = None
    subject: bytes | Subject | None = None


def rows_array(value: Sequence[Sequence[float]] | None, field: str) -> np.ndarray | None:
    """A (B, N) float64 matrix of nested lists (a JSON body's arrays); None stays None.

    Raises:
        InvalidInputError: rows of different lengths (naming ``field``).
    """
    if value is None:
        return None
    rows = {len(row) for row in value}
    if len(rows) > 1:
        raise InvalidInputError(
            f"the rows of {field} have different lengths {sorted(rows)}; send a (B, N) matrix", field
        )
    return np.asarray(value, np.float64)


def synthesis_parameters(
    request: SynthRequest, model: BodyModel, max_batch: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated float32 (B, n_dof), (B, 3), (B, n_shape): shapes, dtypes (an array must hold floats),
    finite values (after the cast to float32), DOF ranges, and plausible shape coefficients
    (:data:`SHAPE_LIMIT_SD`) and root (:data:`ROOT_LIMIT_M`)."""
    skel = model.skeleton
    batch = batch_of(request)
    if batch > max_batch:
        raise LimitExceededError(
            f"{batch} bodies asked for in one call; the limit is {max_batch}: split it",
            field="batch",
        )
    with invalid_input("coordinates"):
        coords = request.coordinates
        if coords is None:
            q = np.zeros((batch, skel.n_dof))
        elif isinstance(coords, Mapping):
            q = skel.coordinates({k: np.asarray(v) for k, v in coords.items()}, batch=batch)
        else:
            q = float_array(coords, "coordinates")
    root = None if request.root is None else float_array(request.root, "root")
    shape = None if request.shape is None else float_array(request.shape, "shape")
    check_plausible(shape, root)
    out = _plainly_valid(model, q, root, shape)
    if out is None:
        # Something is off: the model's own checks raise with the detailed message. In float64: the
        # values are checked as sent, and every value that passes is small enough for float32.
        with invalid_input("coordinates"):
            qt, _, _ = skel.validate(q, None, dtype=torch.float64)
        with invalid_input("root"):
            _, rt, _ = skel.validate(
                qt, np.zeros((len(qt), 3)) if root is None else root, dtype=torch.float64
            )
        with invalid_input("shape"):
            ct = model.validate_shape(shape, len(qt), torch.float64)
        assert rt is not None
        out = qt.numpy().astype(np.float32), rt.numpy().astype(np.float32), ct.numpy().astype(np.float32)
    for name, value in zip(("coordinates", "root", "shape"), out, strict=True):
        if not np.isfinite(value).all():  # after the cast: float32 overflows where float64 does not
            raise InvalidInputError(
                f"{name} holds values beyond float32's range (about 3.4e38); send values within their "
                "ranges (GET /v1/model)",
                field=name,
            )
    return out


def _plainly_valid(
    model: BodyModel, q: np.ndarray, root: np.ndarray | None, shape: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """float32 (q, root, shape) when the inputs pass every check, else None (a numpy fast path: the
    model's checks go through torch and cost a quarter of a millisecond per request). Finiteness is
    checked after the cast to float32, so that a value float64 holds but float32 does not fails."""
    skel = model.skeleton
    if q.ndim != 2 or q.shape[1] != skel.n_dof:
        return None
    B = len(q)
    r = np.zeros((B, 3)) if root is None else root
    c = np.zeros((B, model.n_shape)) if shape is None else shape
    if r.shape != (B, 3) or c.shape != (B, model.n_shape):
        return None
    lo, hi = skel.ranges[:, 0] - RANGE_TOLERANCE, skel.ranges[:, 1] + RANGE_TOLERANCE
    if not ((q >= lo) & (q <= hi)).all():  # NaN fails too
        return None
    with np.errstate(over="ignore"):
        out = q.astype(np.float32), r.astype(np.float32), c.astype(np.float32)
    if not all(np.isfinite(a).all() for a in out):
        return None
    return out


def batch_of(request: SynthRequest) -> int:
    """B: the rows of the first array given, else ``request.batch``, else 1.

    Raises:
        InvalidInputError: an array with no rows (0 bodies) or a batch below 1.
    """
    sources: list[tuple[str, int]] = []
    for name, value in (("shape", request.shape), ("root", request.root)):
        if value is not None and np.ndim(value) >= 1:
            sources.append((name, len(value)))
    coords = request.coordinates
    if coords is not None and not isinstance(coords, Mapping) and np.ndim(coords) >= 1:
        sources.append(("coordinates", len(coords)))
    if isinstance(coords, Mapping):
        lengths = [np.size(v) for v in coords.values() if np.ndim(v) >= 1]
        if lengths:
            sources.append(("coordinates", max(lengths)))
    if sources:
        name, rows = sources[0]
        if rows < 1:
            raise InvalidInputError(
                f"{name} has no rows, so 0 bodies were asked for; send at least one row (B >= 1), or leave "
                f"{name} out",
                field=name,
            )
        return rows
    if request.batch is not None and request.batch < 1:
        raise InvalidInputError(f"batch must be at least 1; got {request.batch}", field="batch")
    return request.batch or 1
