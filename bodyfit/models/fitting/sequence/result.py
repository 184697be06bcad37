"""What a sequence fit gives: the whole :class:`SequenceFit`, and the :class:`SequenceFrames` blocks it
streams while it runs."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bodyfit.models.fitting.common.report import FitReport
from bodyfit.models.fitting.sequence.stats import SequenceStats


@dataclass(frozen=True)
class SequenceFrames:
    """Frames ``start:stop`` (k = stop - start) of a sequence fit, final: the same numbers the whole
    :class:`SequenceFit` will hold for them.

    coordinates: (k, n_dof), the pelvis angles unwrapped over time as in :attr:`SequenceFit.coordinates`;
    root: (k, 3) metres; vertices: (k, V, 3) float32 metres, the registration (given whether or not the fit
    keeps its vertices); joints: (k, J, 3) metres, float64; error_mm: (k,) each frame's mean distance to its
    input mesh over the vertices of positive weight (its report's ``distances.mean``).
    """

    start: int
    stop: int
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    error_mm: np.ndarray


@dataclass(frozen=True)
class SequenceFit:
    """One person over T frames.

    shape: (n_shape,) for every frame; offsets: (V, 3) the person's rest-pose offsets (metres) when the
    fit was asked for them, else None (the skin is then the shape space's); coordinates: (T, n_dof), the
    pelvis angles unwrapped over time (see :meth:`coordinates_in_range`); root: (T, 3); vertices:
    (T, V, 3) float32, the registration, or None when the fit was asked not to keep them; joints:
    (T, J, 3); reports: one :class:`FitReport` per frame; stats: :class:`SequenceStats`.
    """

    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray | None
    joints: np.ndarray
    reports: list[FitReport]
    stats: SequenceStats
    offsets: np.ndarray | None = None
    dof_names: tuple[str, ...] = field(default=(), repr=False)
    _in_range: np.ndarray | None = field(default=None, repr=False)

    def registration(self, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """Fitted vertices of frames lo:hi (k, V, 3) float32.

        Raises:
            ValueError: the fit was run without keeping its vertices.
        """
        if self.vertices is None:
            raise ValueError("this fit did not keep its vertices; fit with keep_vertices=True")
        return self.vertices[lo:hi]

    def coordinates_in_range(self) -> np.ndarray:
        """(T, n_dof) with the pelvis angles folded into [-pi, pi]: valid input to :meth:`BodyModel.forward`
        (the same poses)."""
        assert self._in_range is not None
        return self._in_range
