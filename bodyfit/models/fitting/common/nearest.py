"""Nearest-neighbour queries for the fitting loops: kd-trees (J. L. Bentley, "Multidimensional binary search
trees used for associative searching", Communications of the ACM 18(9), 1975), through pykdtree, which builds
and queries faster than scipy's cKDTree at our sizes (10^3-10^5 points)."""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree


class PointTree:
    """A kd-tree of points (N, 3) (float64)."""

    def __init__(self, points: np.ndarray) -> None:
        self._tree = KDTree(np.ascontiguousarray(points, np.float64))

    def query(
        self, queries: np.ndarray, upper: float | None = None, k: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each query point's (M, 3) nearest tree point: distances (M,) and indices (M,) int64, or the ``k``
        nearest (M, k) when k > 1. Beyond ``upper`` the distance is inf and the index the number of tree
        points."""
        queries = np.ascontiguousarray(queries, np.float64)
        d, i = self._tree.query(queries, k=k, distance_upper_bound=upper)
        return d, i.astype(np.int64)
