"""Raw scans in a rig: closest points between the posed rig and each scan's points, both ways, as targets.

A raw scan's registration (its own fit, refined non-rigidly) lies on the scan's surface but slides along it
by a centimetre or more: the template's vertices sit where the nearest points happened to be. A rig built on
such registrations learns the sliding as offsets. So the rig built from raw scans is refined by iterated
closest points (P. J. Besl and N. D. McKay, "A Method for Registration of 3-D Shapes", IEEE Transactions on
Pattern Analysis and Machine Intelligence 14(2), 1992) over all scans at once: every round, the rig posed as
each scan is paired with that scan's points, every vertex with its nearest point and every point with its
nearest vertex, the pairs weighted by Geman-McClure (S. Geman and D. E. McClure, "Statistical methods for
tomographic image reconstruction", Bulletin of the International Statistical Institute 52(4), 1987), and each
vertex's target is moved along its normal only (point to plane: Y. Chen and G. Medioni, "Object Modelling by
Registration of Multiple Range Images", Image and Vision Computing 10(3), 1992). The rig's shared offsets,
weights and joints and every scan's pose are then solved against those targets (:mod:`.build`): the
correspondence along the surface comes from the rig, which all scans share, not from any one scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.nonrigid import geman_mcclure_weights
from bodyfit.models.fitting.common.surface import vertex_normals


@dataclass(frozen=True, kw_only=True)
class ClosestConfig:
    """max_distance: pairs further apart (m) are ignored; sigma: the Geman-McClure scale (m); rounds: the
    alternation's rounds when raw scans are given (each re-pairs the points); tangential: the share of each
    pull kept along the surface (0: across it only)."""

    max_distance: float = 0.04
    sigma: float = 0.01
    rounds: int = 8
    tangential: float = 0.0


def closest_targets(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, config: ClosestConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Targets (V, 3) for a posed mesh's vertices (V, 3) (triangles ``faces`` (F, 3)) on a scan's points
    (N, 3), in the same frame, metres, and their confidence (V,) in [0, 1] (0: no point near).

    Both directions count alike: the points' pulls are scaled by V / N, so a vertex paired with its share
    of points gets as much from them as from its own nearest point."""
    cfg = config or ClosestConfig()
    V, N = len(vertices), len(points)
    normals = vertex_normals(vertices, faces)
    d_m, near = PointTree(points).query(vertices, cfg.max_distance)
    seen = np.isfinite(d_m)
    w_m = np.where(seen, geman_mcclure_weights(np.where(seen, d_m, 0.0), cfg.sigma), 0.0)
    pull_m = np.zeros((V, 3))
    pull_m[seen] = points[near[seen]] - vertices[seen]
    d_s, owner = PointTree(vertices).query(points, cfg.max_distance)
    kept = np.isfinite(d_s)
    owner, pts = owner[kept], points[kept]
    w_s = geman_mcclure_weights(d_s[kept], cfg.sigma) * (V / max(N, 1))
    a = w_m + np.bincount(owner, w_s, minlength=V)
    pull = w_m[:, None] * pull_m
    for k in range(3):
        pull[:, k] += np.bincount(owner, w_s * (pts[:, k] - vertices[owner, k]), minlength=V)
    pull = np.divide(pull, a[:, None], out=np.zeros((V, 3)), where=a[:, None] > 0)
    across = np.einsum("vi,vi->v", normals, pull)[:, None] * normals
    return vertices + across + cfg.tangential * (pull - across), np.clip(a / 2.0, 0.0, 1.0)
