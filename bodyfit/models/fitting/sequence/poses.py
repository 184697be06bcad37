"""The pose-only fits of a sequence's frames with the person's shape frozen: each frame its own problem, in
the frame's canonical frame (:mod:`.frames`), the frames split over threads."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from bodyfit.models.body.model import PosedSkin
from bodyfit.models.fitting.registered.fitter import RegisteredFitter, Stage, vertex_term
from bodyfit.models.fitting.sequence.frames import turn


def fit_poses(
    fitter: RegisteredFitter,
    x: np.ndarray,
    w: np.ndarray,
    G: np.ndarray,
    origin: np.ndarray,
    c: np.ndarray,
    q0: np.ndarray,
    r0: np.ndarray,
    stages: tuple[Stage, ...],
    workers: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Pose-only fit, in the canonical frames (G, origin), of world frames x (B, V, 3) with weights
    w (B, V), the shape c (1, n_shape) frozen, from q0 (B, n_dof) and r0 (B, 3): one problem per frame,
    the frames split into ``workers`` runs fitted at once, a thread each. Only the stages'
    vertices are turned. Returns coordinates (B, n_dof) and root (B, 3)."""
    dtype = fitter.config.dtype

    def fit(rows: slice) -> tuple[np.ndarray, np.ndarray]:
        w_r, G_r, o_r = w[rows], G[rows], origin[rows]
        w_mean = w_r.mean(axis=1, keepdims=True)
        z = fitter.start_state(q0[rows], r0[rows], np.repeat(c, len(w_r), axis=0))
        for stage in stages:
            idx = fitter.index[stage.vertices]
            xt = torch.as_tensor(turn(x[rows, idx], G_r, o_r) * 1000.0, dtype=dtype)
            wt = torch.as_tensor(w_r[:, idx] / w_mean, dtype=dtype)
            fitter.optimise(stage, z, vertex_term(xt, wt))
        _, q, root = fitter.parameters(z)
        return q.numpy(), root.numpy()

    runs = [slice(int(r[0]), int(r[-1]) + 1) for r in np.array_split(np.arange(len(x)), workers) if len(r)]
    with ThreadPoolExecutor(len(runs)) as pool:
        done = list(pool.map(fit, runs))
    return np.concatenate([q for q, _ in done]), np.concatenate([root for _, root in done])


class FramePoses:
    """The pose problems of a block of frames (the arguments of :func:`fit_poses`: world frames x (B, V, 3),
    weights w (B, V), canonical frames G (B, 3, 3) and origin (B, 3), frozen shape c (1, n_shape)), to be
    solved again for some of the frames from other starts, and each frame's data term at a pose: the
    :data:`.basins.Refit` and :data:`.basins.Losses` of :func:`.basins.settle`."""

    def __init__(
        self,
        fitter: RegisteredFitter,
        frames: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        c: np.ndarray,
        stages: tuple[Stage, ...],
        workers: int,
    ) -> None:
        self.fitter = fitter
        self.x, self.w, self.G, self.origin = frames
        self.c, self.stages, self.workers = c, stages, workers
        self._skin: PosedSkin | None = None

    def refit(self, rows: np.ndarray, q0: np.ndarray, r0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates (k, n_dof) and roots (k, 3) of frames ``rows`` (k,) fitted from q0 (k, n_dof) and
        r0 (k, 3) (k may repeat a frame: one fit per start)."""
        workers = max(1, min(self.workers, len(rows) // 4))  # a few frames: one thread is quicker
        every = len(rows) == len(self.x) and bool((rows == np.arange(len(rows))).all())
        take: np.ndarray | slice = slice(None) if every else rows  # the whole block: no copy
        x, w, G, o = self.x[take], self.w[take], self.G[take], self.origin[take]
        return fit_poses(self.fitter, x, w, G, o, self.c, q0, r0, self.stages, workers)

    def residuals(self, rows: np.ndarray, q: np.ndarray, root: np.ndarray) -> np.ndarray:
        """(k, N, 3) the last stage's vertices fitted minus input (mm) of frames ``rows`` (k,) at coordinates
        q (k, n_dof) and roots (k, 3) (canonical frames)."""
        dtype = self.fitter.config.dtype
        vertices = self.stages[-1].vertices
        if self._skin is None:
            self._skin = self.fitter.decoders[vertices].posed(torch.as_tensor(self.c, dtype=dtype))
        x = turn(self.x[rows][:, self.fitter.index[vertices]], self.G[rows], self.origin[rows])
        with torch.no_grad():
            v = self._skin(torch.as_tensor(q, dtype=dtype), torch.as_tensor(root, dtype=dtype))
        return np.asarray(v.double().numpy() * 1000.0 - x * 1000.0)

    def losses(self, rows: np.ndarray, q: np.ndarray, root: np.ndarray) -> np.ndarray:
        """(k,) the last stage's data term (weighted mean squared distance, mm^2, as :func:`vertex_term`) of
        frames ``rows`` (k,) at coordinates q (k, n_dof) and roots (k, 3) (canonical frames)."""
        w = self.w[rows]
        wt = w[:, self.fitter.index[self.stages[-1].vertices]] / w.mean(axis=1, keepdims=True)
        return np.asarray(((self.residuals(rows, q, root) ** 2).sum(-1) * wt).mean(1))
