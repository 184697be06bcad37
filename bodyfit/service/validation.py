"""Checks of request content that every transport shares, run by the service core before any work:
plausible parameters, registered frames that are whole human-sized bodies, parameters that are real
numbers, and results that are finite before anything encodes them. Each raises
:class:`InvalidInputError` naming the field, what is wrong and the fix."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np

from bodyfit.io.scans import Scan
from bodyfit.models.errors import BodyfitError
from bodyfit.models.fitting.scan.config import ScanFitConfig
from bodyfit.models.fitting.scan.phases import PreparedScan, prepare_scan
from bodyfit.models.fitting.scan.scene import NoPersonError
from bodyfit.service.errors import InvalidInputError

SHAPE_LIMIT_SD = 10.0
"""Largest accepted |shape coefficient|. Coefficients are in population standard deviations (a standard
normal draw is a plausible body). On the first bone coefficient (stature) -10 and +10 give bodies 0.72 m
and 2.72 m tall, the shortest and tallest adults on record; beyond that the linear basis only extrapolates
to no human (1e6 gives a body 100 km tall), so a larger value is a mistake (another model's betas, wrong
units), never a person."""
ROOT_LIMIT_M = 100.0
"""Largest accepted |root| (pelvis position) per axis, metres: a capture volume spans metres to tens of
metres, and float32, which synthesis runs in, still resolves 0.01 mm there. Farther is a unit mistake or an
unset value (1e308 overflows float32)."""
BODY_MIN_EXTENT_M, BODY_MAX_EXTENT_M = 0.3, 4.0
"""The longest side of the bounding box of a whole body in our topology (a registered frame or mesh), metres:
the shortest body the shape limits allow (0.72 m) curled up spans more than 0.3 m; the tallest (2.72 m) with
its arms raised less than 4 m. Millimetres (about 1,700) and centimetres (about 170) fall outside."""
_FLAT = 1e-3  # a frame whose smallest spread is below this fraction of its largest is flat (as for scans)


SCAN_MIN_EXTENT_M = 0.1
"""The smallest scan the raw-scan fit can use (a head and shoulders), metres: the fit thins scans to a 1 cm
grid, so anything smaller leaves too few points (a scan in metres read as millimetres spans 2 mm)."""


def check_plausible(shape: np.ndarray | None, root: np.ndarray | None) -> None:
    """Refuse shape coefficients beyond +-:data:`SHAPE_LIMIT_SD` and roots beyond +-:data:`ROOT_LIMIT_M`
    (any array shapes; NaN and infinities pass here and fail the finiteness checks, which name them).

    Raises:
        InvalidInputError: naming the field, the range, the value and where it is.
    """
    for name, value, limit, what in (
        ("shape", shape, SHAPE_LIMIT_SD, "shape coefficients are in population standard deviations"),
        ("root", root, ROOT_LIMIT_M, "root is the pelvis position in metres"),
    ):
        if value is None:
            continue
        outside = np.isfinite(value) & (np.abs(value) > limit)
        if outside.any():
            where = [int(k) for k in np.argwhere(outside)[0]]
            bad = float(value[tuple(where)])
            fix = (
                "a standard normal draw is a plausible body; +-10 spans the shortest to the tallest adults"
                if name == "shape"
                else "send metres, with the body near the origin"
            )
            raise InvalidInputError(
                f"{what} and must lie within [-{limit:g}, {limit:g}]; got {bad:.6g} at index {where} "
                f"({int(outside.sum())} value(s) outside): {fix}",
                field=name,
            )


def check_frames(
    frames: np.ndarray,
    weights: np.ndarray | None = None,
    n_vertices: int | None = None,
    field: str = "frames",
    chunk: int = 256,
) -> None:
    """Check, before any fitting, that ``frames`` (T, V, 3) are T whole bodies in metres: the one check of
    registered sequences for every transport (and of single meshes in our or SMPL's topology).

    In order: a float dtype; shape (T, n_vertices, 3) with T >= 1; every value finite once cast to float32
    (what the fit computes in); weights (T, V) finite and non-negative with a positive one per frame; then
    per frame, over the vertices with positive weight: not all zeros, not on one point, a line or a plane,
    the bounding box's longest side within [:data:`BODY_MIN_EXTENT_M`, :data:`BODY_MAX_EXTENT_M`] (the
    message suggests the unit that fits), and the centre within :data:`ROOT_LIMIT_M` of the origin. Frames
    are checked ``chunk`` at a time (memory), and the first bad one is named.

    Raises:
        InvalidInputError: naming ``field``, what is wrong, the first bad frame and the fix.
    """
    one = frames.ndim == 3 and len(frames) == 1 and field != "frames"

    def frame(t: int) -> str:
        return "the mesh" if one else f"frame {t}"

    if frames.dtype.kind != "f":
        raise InvalidInputError(f"frames must be floats (metres); got {frames.dtype}", field=field)
    V = frames.shape[1] if frames.ndim == 3 else -1
    if frames.ndim != 3 or frames.shape[2] != 3 or len(frames) == 0 or n_vertices not in (None, V):
        size = n_vertices or "V"
        raise InvalidInputError(
            f"frames must have shape (T, {size}, 3) with T >= 1 (meshes in our topology, metres); got "
            f"{frames.shape}",
            field=field,
        )
    T = len(frames)
    w = None if weights is None else _checked_weights(weights, T, V, frame)
    for lo in range(0, T, chunk):
        with np.errstate(over="ignore"):
            x = np.asarray(frames[lo : lo + chunk], np.float32)
        finite = np.isfinite(x).all(axis=(1, 2))
        if not finite.all():
            t = lo + int(np.argmin(finite))
            raise InvalidInputError(
                f"{frame(t)} holds NaN or infinite values (or values beyond float32's range, 3.4e38); every "
                "vertex needs a finite position in metres: give a vertex nothing saw any finite position "
                "and weight 0",
                field=field,
            )
        seen = None if w is None else w[lo : lo + chunk] > 0
        _check_bodies(x, None if seen is None or seen.all() else seen, lo, frame, field)


def _checked_weights(weights: np.ndarray, T: int, V: int, frame: Callable[[int], str]) -> np.ndarray:
    """Returns the weights (T, V) as float64 once they are numbers, finite, non-negative and positive
    somewhere in every frame (``frame`` names frame t in messages)."""
    w = np.asarray(weights)
    if w.dtype.kind not in "fiub":
        raise InvalidInputError(f"weights must be numbers (0 = missing); got {w.dtype}", field="weights")
    if w.shape != (T, V):
        raise InvalidInputError(
            f"weights must have one value per frame and vertex, shape {(T, V)}; got {w.shape}",
            field="weights",
        )
    w = w.astype(np.float64)
    if not np.isfinite(w).all() or (w < 0).any():
        raise InvalidInputError(
            "weights must be finite and non-negative (0 marks a missing vertex)", field="weights"
        )
    empty = np.flatnonzero(w.max(axis=1) <= 0)
    if len(empty):
        raise InvalidInputError(
            f"{frame(int(empty[0]))} has no vertex with a positive weight ({len(empty)} such frames); "
            "drop the frames nothing was seen in",
            field="weights",
        )
    return w


def _check_bodies(
    x: np.ndarray, seen: np.ndarray | None, lo: int, frame: Callable[[int], str], field: str
) -> None:
    """The per-frame checks of :func:`check_frames` on frames lo.. (k, V, 3) float32 with the vertices
    ``seen`` (k, V) (at least one per frame; None: all). Kept cheap per frame: per-axis reductions on strided
    views (numpy reduces the middle axis of (k, V, 3) slowly), and the spread on every 8th vertex (a body's
    subset is no more flat than the body)."""
    if seen is None:
        k, V = x.shape[:2]
        flat = x.reshape(k, V * 3)
        zero = ~flat.any(axis=1)
        axes = [flat[:, i::3] for i in range(3)]
        extent = np.max([a.max(axis=1) - a.min(axis=1) for a in axes], axis=0)
        centre = (np.ones(V, np.float32) @ x).astype(np.float64) / V
        spread = x[:, ::8]
        n = np.full((k, 1), spread.shape[1])
        d = spread - centre[:, None].astype(np.float32)
    else:
        mask = seen[..., None]
        n = seen.sum(axis=1)[:, None]
        zero = ~np.where(mask, x, 0.0).any(axis=(1, 2))
        centre = np.where(mask, x, 0.0).sum(axis=1, dtype=np.float64) / n
        d = np.where(mask, x - centre[:, None].astype(np.float32), 0.0).astype(np.float32)
        extent = (np.where(mask, x, -np.inf).max(axis=1) - np.where(mask, x, np.inf).min(axis=1)).max(axis=1)
    if zero.any():
        t = lo + int(np.argmax(zero))
        raise InvalidInputError(
            f"{frame(t)} holds only zeros: an empty frame, not a body; drop it or fill it with the body's "
            "vertices in metres",
            field=field,
        )
    cov = (np.swapaxes(d, 1, 2) @ d).astype(np.float64) / n[..., None]  # batched BLAS
    sv = np.sqrt(np.clip(np.linalg.eigvalsh(cov), 0.0, None))[:, ::-1]  # descending
    for bad, what in (
        (sv[:, 0] == 0, "all its vertices are at one point"),
        (sv[:, 1] < _FLAT * sv[:, 0], "its vertices lie on a line"),
        (sv[:, 2] < _FLAT * sv[:, 0], "its vertices lie on a plane"),
    ):
        if bad.any():
            t = lo + int(np.argmax(bad))
            raise InvalidInputError(
                f"{frame(t)} is collapsed: {what} (degenerate), so it cannot be a body; send the body's "
                "vertices in metres",
                field=field,
            )
    small, large = extent < BODY_MIN_EXTENT_M, extent > BODY_MAX_EXTENT_M
    if small.any() or large.any():
        t = int(np.argmax(small | large))
        e = float(extent[t])
        if 300.0 <= e <= 4000.0:
            hint = "it looks like millimetres: divide by 1000"
        elif 30.0 <= e < 300.0:
            hint = "it looks like centimetres: divide by 100"
        elif e < BODY_MIN_EXTENT_M:
            hint = "too small for a body: send metres"
        else:
            hint = "too large for a body: send metres, one body per frame"
        raise InvalidInputError(
            f"{frame(lo + t)} spans {e:.4g} (in the units sent) along its longest side; a whole body in "
            f"metres spans {BODY_MIN_EXTENT_M:g} to {BODY_MAX_EXTENT_M:g}: {hint}",
            field=field,
        )
    far = np.abs(centre).max(axis=1) > ROOT_LIMIT_M
    if far.any():
        t = int(np.argmax(far))
        raise InvalidInputError(
            f"{frame(lo + t)} is centred {float(np.abs(centre[t]).max()):.4g} m from the origin; bodies must "
            f"be within {ROOT_LIMIT_M:g} m of it: move the sequence near the origin",
            field=field,
        )


def check_finite_result(what: str, arrays: Mapping[str, np.ndarray | None], fix: str, field: str) -> None:
    """Refuse a result holding NaN or infinite values before anything encodes it: JSON has no NaN, and a
    NaN body is no answer. ``arrays`` name -> array (None: absent).

    Raises:
        InvalidInputError: naming ``field`` and the array, with ``fix`` (what in the input to check).
    """
    for name, value in arrays.items():
        if value is None:
            continue
        a = np.asarray(value)
        if a.dtype.kind in "fc" and not np.isfinite(a).all():
            n = int(a.size - np.isfinite(a).sum())
            raise InvalidInputError(
                f"the {what} came out with {n:,} NaN or infinite values in {name}, so there is no result to "
                f"return; {fix}",
                field=field,
            )


def float_array(value: Any, field: str) -> np.ndarray:
    """A parameter as float64; a numpy array must already hold floats (int and bool arrays are refused, as
    on every transport: an array with a dtype must say it holds real numbers)."""
    if isinstance(value, np.ndarray) and value.dtype.kind != "f":
        raise InvalidInputError(
            f"{field} must hold floats (float32 or float64); got {value.dtype}", field=field
        )
    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{field} must be a (B, N) array of numbers ({exc})", field=field) from None


@contextmanager
def invalid_input(field_name: str) -> Iterator[None]:
    """Turn the model layer's typed errors into :class:`InvalidInputError` naming ``field_name``."""
    try:
        yield
    except BodyfitError as exc:
        raise InvalidInputError(str(exc), field=field_name) from exc


def check_scan(scan: Scan, whole_body: bool) -> Scan | PreparedScan:
    """Check, before any fitting, that ``scan`` can be the body it is fitted as: with ``whole_body`` (a mesh
    in our topology or SMPL's) a whole body (:func:`check_frames`), else at least
    :data:`SCAN_MIN_EXTENT_M` across with a person in it (a raw scan: cleaned and split from its scene as
    the fit does it, :func:`bodyfit.models.fitting.scan.phases.prepare_scan` with the default
    :class:`~bodyfit.models.fitting.scan.config.ScanFitConfig`; a room, a box or a chair alone is refused).
    Returns the scan ready to fit: a mesh as it is, a raw scan as that preparation (which a fit with the
    same settings does not redo).

    Raises:
        InvalidInputError: what is wrong (degenerate, not human-sized, the wrong units, no person found) and
            the fix.
    """
    read_as = " read in millimetres (units=mm)" if scan.source_units == "mm" else ""
    if whole_body:
        try:
            check_frames(scan.points[None], field="file")
        except InvalidInputError as exc:
            if not read_as:
                raise
            raise InvalidInputError(
                f"{exc.detail} (the mesh was{read_as}: send units=m or auto when the file is in metres)",
                field="units",
            ) from None
        return scan
    extent = float(np.ptp(scan.points, axis=0).max())
    if extent < SCAN_MIN_EXTENT_M:
        raise InvalidInputError(
            f"the scan{read_as} spans only {extent * 1000:.3g} mm; a body or a body part (a head and "
            f"shoulders) spans at least {SCAN_MIN_EXTENT_M:g} m: send units=m (or auto) when the file is "
            "in metres, units=mm only when it is in millimetres",
            field="units" if read_as else "file",
        )
    try:
        return prepare_scan(scan, ScanFitConfig())
    except NoPersonError as exc:
        raise InvalidInputError(str(exc), field="file") from None
