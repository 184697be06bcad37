"""Sequence-level numbers of a sequence fit: its :class:`SequenceStats`, and what the frame pass accumulates
chunk by chunk to give them without holding the sequence (:class:`JitterSum`, :class:`FrameTotals`): the
distances to the input and the frame-to-frame jitter (second difference in time) of the fit and the input."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from bodyfit.models.fitting.common.report import DistanceStats


@dataclass(frozen=True)
class SequenceStats:
    """Sequence-level numbers.

    frames; seconds (wall, whole fit); fps = frames / seconds; mean_mm: mean per-vertex distance over all
    frames; jitter_input_mm / jitter_fit_mm: mean over frames and vertices of the second difference in
    time ``|x[t+1] - 2 x[t] + x[t-1]|`` (mm); jitter_ratio: fit over input (1 = as smooth as the input);
    shape_keyframes: the frames the shape was fitted on. Where jitter is undefined it is None, never NaN,
    and ``jitter_note`` says why: the second difference needs three frames (no vertex seen, weight > 0, in
    three consecutive frames: both None), and the ratio needs an input that moves (a still input has
    jitter 0: the ratio is None, the fit's own jitter is kept).
    """

    frames: int
    seconds: float
    fps: float
    mean_mm: float
    jitter_input_mm: float | None
    jitter_fit_mm: float | None
    jitter_ratio: float | None
    shape_keyframes: tuple[int, ...]
    jitter_note: str | None = None

    @classmethod
    def measured(
        cls,
        frames: int,
        seconds: float,
        mean_mm: float,
        jitter_input_mm: float,
        jitter_fit_mm: float,
        shape_keyframes: tuple[int, ...],
    ) -> SequenceStats:
        """The stats of a fit from its raw jitter means (NaN where :class:`JitterSum` saw no second
        difference), with the undefined ones as None and the note saying why."""
        note = None
        j_in: float | None = jitter_input_mm
        j_fit: float | None = jitter_fit_mm
        ratio: float | None = None
        if not (np.isfinite(jitter_input_mm) and np.isfinite(jitter_fit_mm)):
            j_in = j_fit = None
            note = (
                f"jitter needs three consecutive frames (a second difference in time); the sequence has "
                f"{frames}"
                if frames < 3
                else "jitter needs a vertex seen (weight > 0) in three consecutive frames; none is"
            )
        elif jitter_input_mm > 0:
            ratio = jitter_fit_mm / jitter_input_mm
        else:
            note = "the input does not move (jitter 0): jitter_ratio is undefined; jitter_fit_mm is the fit's"
        return cls(frames, seconds, frames / seconds, mean_mm, j_in, j_fit, ratio, shape_keyframes, note)

    def to_dict(self) -> dict[str, object]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


class JitterSum:
    """Running mean second difference in time of trajectories fed chunk by chunk, in time order (the
    :func:`jitter` of the whole sequence, without holding it)."""

    def __init__(self) -> None:
        self._tail: tuple[np.ndarray, np.ndarray] | None = None  # the last two frames and their masks
        self._total = 0.0
        self._count = 0

    def add(self, x: np.ndarray, weights: np.ndarray | None = None) -> None:
        """The next frames x (k, N, 3) metres, with weights (k, N) (None: all count)."""
        seen = np.ones(x.shape[:2], bool) if weights is None else np.asarray(weights) > 0
        if self._tail is not None:  # the differences across the join with the previous chunk
            prev_x, prev_seen = self._tail
            self._sum(np.concatenate([prev_x, x[:2]]), np.concatenate([prev_seen, seen[:2]]))
            x_end, seen_end = np.concatenate([prev_x, x[-2:]]), np.concatenate([prev_seen, seen[-2:]])
        else:
            x_end, seen_end = x, seen
        self._sum(x, seen)
        self._tail = (x_end[-2:].copy(), seen_end[-2:].copy())

    def _sum(self, x: np.ndarray, seen: np.ndarray) -> None:
        if len(x) < 3:
            return
        d = x[2:] - x[1:-1]
        d -= x[1:-1]
        d += x[:-2]
        acc = lengths(d)
        ok = seen[2:] & seen[1:-1] & seen[:-2]
        acc = acc if ok.all() else acc[ok]
        self._total += float(acc.sum(dtype=np.float64))
        self._count += acc.size

    def mm(self) -> float:
        """The mean so far in mm; NaN before three frames."""
        return self._total / self._count * 1000.0 if self._count else float("nan")


class FrameTotals:
    """What the frame pass accumulates chunk by chunk: distance sums, per-frame statistics, jitter."""

    def __init__(self) -> None:
        self.distance_sum = 0.0
        self.distance_count = 0
        self.frames: list[DistanceStats] = []
        self.jitter_input = JitterSum()
        self.jitter_fit = JitterSum()

    def add(self, x: np.ndarray, fitted: np.ndarray, w: np.ndarray) -> None:
        """Input frames x (k, V, 3), fitted skins (k, V, 3), weights (k, V); float32 metres. The jitter is
        summed on a second thread meanwhile (numpy's array operations release the interpreter)."""
        with ThreadPoolExecutor(1) as pool:
            smooth = pool.submit(self._add_jitter, x, fitted, w)
            dist = lengths(fitted - x)
            seen = w > 0
            used = dist if seen.all() else dist[seen]
            self.distance_sum += float(used.sum(dtype=np.float64))
            self.distance_count += used.size
            self.frames.extend(DistanceStats.of_rows(dist, seen))
            smooth.result()

    def _add_jitter(self, x: np.ndarray, fitted: np.ndarray, w: np.ndarray) -> None:
        self.jitter_input.add(x, w)
        self.jitter_fit.add(fitted, w)


def jitter(x: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Mean second difference in time of trajectories x (T, N, 3) metres, in mm; over points with positive
    weight (T, N) in all three frames; NaN for fewer than 3 frames."""
    total = JitterSum()
    total.add(x, weights)
    return total.mm()


def lengths(d: np.ndarray) -> np.ndarray:
    """Lengths of vectors d (..., 3), in d's dtype (per component: twice as fast as einsum here)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.sqrt(x * x + y * y + z * z)
