"""One basin along time: a frame's pose fit that lands in a different local minimum from its neighbour's is
re-solved from the neighbour's pose, and the solution that explains the frame as well with the smaller
change is kept.

A body's pose fit has several local minima (an arm's flexion traded against its twist, a coordinate held at a
limit that the data pulls past), and frames fitted independently can fall into different ones while the
input barely moves: the coordinates jump, and the fitted skin moves unlike the input. So a change larger
than :attr:`BasinCheck.jump` between neighbours whose fit residual changes by more than
:attr:`BasinCheck.gap` somewhere is a question, not an answer (a jump that moves the skin with the input is
the input's own motion and is not questioned): each frame of such a pair is re-fitted from the other's pose
(a warm start from the neighbour, as a tracker would), and the re-fitted pose replaces the frame's own when
its data term is no worse, within :attr:`BasinCheck.tolerance`, and it is closer to the neighbour. A frame
whose input did move far is left alone: started from its neighbour it cannot explain its own input as well.
A run of frames in the wrong basin is walked back one frame from each end per round
(:attr:`BasinCheck.rounds`).

This is the consistency check of model-based tracking: re-initialise from the previous frame's solution and
keep the hypothesis of lower cost (C. Sminchisescu and B. Triggs, "Kinematic Jump Processes for Monocular 3D
Human Tracking", IEEE Conference on Computer Vision and Pattern Recognition (CVPR), 2003, who generate the
alternatives by flipping kinematic branches; here they come from the neighbouring frames' fits), with
closeness to the neighbour as the tie-break between hypotheses that explain the frame equally well.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


class Frames(Protocol):
    """The pose problems of a block of frames that :func:`settle` re-solves."""

    def refit(self, rows: np.ndarray, q0: np.ndarray, r0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pose fits of frames ``rows`` (k,) started from q0 (k, n_dof), r0 (k, 3): coordinates
        (k, n_dof) and roots (k, 3)."""
        ...

    def residuals(self, rows: np.ndarray, q: np.ndarray, root: np.ndarray) -> np.ndarray:
        """(k, N, 3) fitted minus input points (mm) of frames ``rows`` (k,) at coordinates q (k, n_dof) and
        roots (k, 3), each in its frame's canonical frame."""
        ...

    def losses(self, rows: np.ndarray, q: np.ndarray, root: np.ndarray) -> np.ndarray:
        """(k,) the data term of frames ``rows`` (k,) at coordinates q (k, n_dof) and roots (k, 3)."""
        ...


@dataclass(frozen=True, kw_only=True)
class BasinCheck:
    """jump: the largest change (radians) of a checked coordinate between neighbouring frames that is
    taken without question; gap: how far (mm) the fit's residual at some point may change between the two
    frames (the fitted skin moving unlike the input) before such a jump is questioned: a jump that moves the
    skin with the input is the input's own motion; rounds: how many times the pairs still jumping are
    re-solved (a run of r frames in a wrong basin needs r / 2); tolerance: how much larger (relative) a
    re-solved frame's data term may be and still be kept, for a smaller change.

    Raises:
        ValueError: a jump or gap that is not positive, rounds below zero or a negative tolerance.
    """

    jump: float = float(np.radians(5.0))
    gap: float = 20.0
    rounds: int = 4
    tolerance: float = 0.02

    def __post_init__(self) -> None:
        if not self.jump > 0:
            raise ValueError(f"BasinCheck.jump must be positive; got {self.jump!r}")
        if not self.gap > 0:
            raise ValueError(f"BasinCheck.gap must be positive; got {self.gap!r}")
        if not (isinstance(self.rounds, int) and self.rounds >= 0):
            raise ValueError(f"BasinCheck.rounds must be an integer >= 0; got {self.rounds!r}")
        if not self.tolerance >= 0:
            raise ValueError(f"BasinCheck.tolerance must be >= 0; got {self.tolerance!r}")


def jumping_pairs(q: np.ndarray, dofs: np.ndarray, jump: float) -> np.ndarray:
    """(T - 1,) True where a coordinate ``dofs`` of q (T, n_dof) changes by more than ``jump`` from frame
    t to t + 1."""
    if len(q) < 2:
        return np.zeros(0, bool)
    return np.asarray(np.abs(np.diff(q[:, dofs], axis=0)).max(axis=1) > jump)


def settle(
    q: np.ndarray,
    root: np.ndarray,
    frames: Frames,
    check: BasinCheck,
    dofs: np.ndarray,
    before: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Frames q (k, n_dof), root (k, 3) with the frames of jumping pairs re-solved from their neighbours
    (module docstring).

    Args:
        frames: the frames' pose problems (:class:`Frames`).
        dofs: the coordinates checked (indices).
        before: the pose (q (n_dof,), root (3,)) of the frame just before these, final: only the first
            frame may be re-solved from it.
    Returns:
        coordinates (k, n_dof), roots (k, 3) (copies) and how many re-solved frames were kept.
    """
    q, root = q.copy(), root.copy()
    kept = 0
    loss: dict[int, float] = {}
    fresh = np.ones(len(q), bool)  # frames not yet tested against their neighbours as they stand
    for _ in range(check.rounds):
        rows, q0, r0, source = _candidates(q, root, frames, check, dofs, before, fresh)
        fresh[:] = False
        if not len(rows):
            break
        need = np.array(sorted(set(rows.tolist()) - loss.keys()), np.int64)
        if len(need):
            loss.update(zip(need.tolist(), frames.losses(need, q[need], root[need]).tolist(), strict=True))
        q_new, r_new = frames.refit(rows, q0, r0)
        l_new = frames.losses(rows, q_new, r_new)
        changed = 0
        for i in np.argsort(l_new, kind="stable"):  # best candidate first when a frame has two
            t = int(rows[i])
            near_now = np.abs(q[t, dofs] - source[i, dofs]).max()
            near_new = np.abs(q_new[i, dofs] - source[i, dofs]).max()
            if l_new[i] <= loss[t] * (1.0 + check.tolerance) and near_new < near_now:
                q[t], root[t], loss[t] = q_new[i], r_new[i], float(l_new[i])
                fresh[t] = True
                changed += 1
        kept += changed
        if not changed:
            break
    return q, root, kept


def _questioned(
    q: np.ndarray, root: np.ndarray, frames: Frames, check: BasinCheck, dofs: np.ndarray, fresh: np.ndarray
) -> np.ndarray:
    """(k - 1,) the pairs (t, t + 1) of q (k, n_dof), root (k, 3) with a frame in ``fresh`` (k,) (a pair
    tested as it stands has its answer) whose coordinates ``dofs`` jump while the fit's residual changes by
    more than ``check.gap`` somewhere (the skin moved unlike the input)."""
    pairs = np.flatnonzero(jumping_pairs(q, dofs, check.jump) & (fresh[:-1] | fresh[1:]))
    if not len(pairs):
        return pairs
    rows = np.unique(np.r_[pairs, pairs + 1])
    at = np.searchsorted(rows, pairs)
    res = frames.residuals(rows, q[rows], root[rows])
    change = np.linalg.norm(res[at + 1] - res[at], axis=-1).max(axis=1)
    return pairs[change > check.gap]


def _candidates(
    q: np.ndarray,
    root: np.ndarray,
    frames: Frames,
    check: BasinCheck,
    dofs: np.ndarray,
    before: tuple[np.ndarray, np.ndarray] | None,
    fresh: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For every questioned pair (:func:`_questioned`; the pair of ``before`` and the first frame when its
    coordinates jump and the first frame is fresh: the residual of ``before`` is not at hand), each of its
    frames (of q, root) started from the other's pose: the frames (n,), the starts q0 (n, n_dof) and
    r0 (n, 3), and the neighbour each start came from (n, n_dof)."""
    pairs = _questioned(q, root, frames, check, dofs, fresh)
    right, left = pairs + 1, pairs  # the later frame from the earlier one, and the other way round
    rows = np.r_[right, left]
    q0, r0 = np.r_[q[left], q[right]], np.r_[root[left], root[right]]
    if before is not None and fresh[0] and jumping_pairs(np.stack([before[0], q[0]]), dofs, check.jump)[0]:
        rows = np.r_[0, rows]
        q0, r0 = np.r_[before[0][None], q0], np.r_[before[1][None], r0]
    return rows.astype(np.int64), q0, r0, q0
