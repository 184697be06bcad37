"""Bounded parameterisation of coordinates: the tanh-bounded joint angles of BLSM (eq. 6 of H. Wang, R. A.
Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned Model of the Human Mesh",
European Conference on Computer Vision (ECCV), 2020).

``q = (lo + hi) / 2 + (hi - lo) / 2 * tanh(u)`` maps any real ``u`` into the open range (lo, hi), so
fitting can optimise ``u`` freely and every pose it returns respects the joint limits.
"""

from __future__ import annotations

import torch


def to_coordinates(u: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Unconstrained values -> coordinates inside their ranges.

    Args:
        u: (B, n) any real values.
        lo, hi: (n,) range bounds.
    Returns:
        (B, n) coordinates with lo < q < hi.
    """
    return (lo + hi) / 2 + (hi - lo) / 2 * torch.tanh(u)


def from_coordinates(
    q: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, margin: float = 1e-6
) -> torch.Tensor:
    """Inverse of :func:`to_coordinates` for coordinates inside their ranges.

    Values exactly on a bound map to the value of the bound moved inwards by ``margin`` of the range (a
    finite ``u``). Callers check the range first (:meth:`Skeleton.check_range`).

    Args:
        q: (B, n) coordinates with lo <= q <= hi.
        lo, hi: (n,) range bounds.
    Returns:
        (B, n) unconstrained values.
    """
    x = (2 * q - (lo + hi)) / (hi - lo)
    return torch.atanh(x.clamp(-1 + margin, 1 - margin))
