"""The pose-only fits of a sequence's frames with the person's shape frozen: each frame its own problem, in
the frame's canonical frame (:mod:`.frames`), the frames split over threads."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

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
