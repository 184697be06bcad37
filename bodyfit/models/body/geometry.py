"""Mesh geometry helpers (numpy, pure)."""

from __future__ import annotations

import numpy as np


def winding_number(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, chunk: int = 256
) -> np.ndarray:
    """Generalised winding number of points with respect to a closed triangle mesh.

    A. Jacobson, L. Kavan and O. Sorkine-Hornung, "Robust Inside-Outside Segmentation using Generalized
    Winding Numbers", ACM Transactions on Graphics 32(4) (SIGGRAPH), 2013. About 1 inside, 0 outside, for a
    consistently oriented closed surface (either orientation: the sign is dropped). Solid angles by A. Van
    Oosterom and J. Strackee, "The Solid Angle of a Plane Triangle", IEEE Transactions on Biomedical
    Engineering BME-30(2), 1983.

    Args:
        vertices: (V, 3); faces: (F, 3); points: (P, 3).
    Returns:
        (P,) winding numbers.
    """
    tri = vertices[faces]  # (F, 3, 3)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        d = tri[None] - points[s : s + chunk, None, None]  # (p, F, 3, 3)
        a, b, c = d[:, :, 0], d[:, :, 1], d[:, :, 2]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("pfi,pfi->pf", a, b) * lc
            + np.einsum("pfi,pfi->pf", b, c) * la
            + np.einsum("pfi,pfi->pf", c, a) * lb
        )
        out[s : s + chunk] = np.abs(2.0 * np.arctan2(num, den).sum(axis=1) / (4.0 * np.pi))
    return out
