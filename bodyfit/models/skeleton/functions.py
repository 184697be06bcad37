"""Coordinate functions compiled into dense tables and evaluated in one vectorised pass.

Every :class:`~bodyfit.models.skeleton.spec.Function` is written as a linear combination of a fixed basis,

    f(x) = c0 + c1 x + c2 x^2 + c3 x^3 + sum_k w_k relu(x - k_k)^3
           + amp sin(omega x + phase) + a g1(x) + b g2(x),

so all transform axes of a skeleton are evaluated with the same tensor operations (no data-dependent
control flow; exports to ONNX). Splines use the truncated-power form of a cubic spline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.skeleton.spec import Function

_SMALL = 1e-3  # below this |x| the arc basis uses its Taylor series


def fmm_spline_second_derivatives(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Second derivatives at the knots of the Forsythe-Malcolm-Moler cubic spline (OpenSim SimmSpline).

    End conditions: the third derivative at each end equals that of the cubic through the four end
    knots (plain not-natural ends). With fewer than four knots the spline is natural.

    Args:
        x: (n,) strictly increasing knots; y: (n,) values.
    Returns:
        (n,) second derivatives M.
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    n = len(x)
    if n < 3:
        return np.zeros(n)
    h = np.diff(x)
    A = np.zeros((n, n))
    r = np.zeros(n)
    for i in range(1, n - 1):
        A[i, i - 1] = h[i - 1]
        A[i, i] = 2 * (h[i - 1] + h[i])
        A[i, i + 1] = h[i]
        r[i] = 6 * ((y[i + 1] - y[i]) / h[i] - (y[i] - y[i - 1]) / h[i - 1])
    if n > 3:

        def third_divided(xs: np.ndarray, ys: np.ndarray) -> float:
            d = ys.copy()
            for level in range(1, 4):
                d = (d[1:] - d[:-1]) / (xs[level:] - xs[:-level])
            return float(d[0])

        # S''' on the end segments = 6 * third divided difference of the four end knots.
        A[0, 0], A[0, 1], r[0] = -1.0 / h[0], 1.0 / h[0], 6 * third_divided(x[:4], y[:4])
        A[-1, -2], A[-1, -1], r[-1] = -1.0 / h[-1], 1.0 / h[-1], 6 * third_divided(x[-4:], y[-4:])
    else:
        A[0, 0] = A[-1, -1] = 1.0
    return np.linalg.solve(A, r)


def spline_to_truncated_power(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cubic spline through (x, y) -> monomial coefficients of its first piece and truncated-power jumps.

    Returns:
        poly (4,) with f(x) = poly[0] + poly[1] x + poly[2] x^2 + poly[3] x^3 on the first piece,
        knots (n-2,) interior knots, weights (n-2,) so that f(x) = poly(x) + sum w relu(x - knot)^3.
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    M = fmm_spline_second_derivatives(x, y)
    h = np.diff(x)
    cubic = (M[1:] - M[:-1]) / (6 * h)  # cubic coefficient of each piece
    # First piece around x0: y0 + s1 (t) + M0/2 t^2 + cubic0 t^3 with t = x - x0.
    s1 = (y[1] - y[0]) / h[0] - h[0] * (2 * M[0] + M[1]) / 6
    x0 = x[0]
    p = np.array([y[0], s1, M[0] / 2, cubic[0]])
    # Expand sum_k p_k (x - x0)^k into monomials of x.
    poly = np.array(
        [
            p[0] - p[1] * x0 + p[2] * x0**2 - p[3] * x0**3,
            p[1] - 2 * p[2] * x0 + 3 * p[3] * x0**2,
            p[2] - 3 * p[3] * x0,
            p[3],
        ]
    )
    return poly, x[1:-1].copy(), np.diff(cubic)


def evaluate_function(fn: Function, x: np.ndarray) -> np.ndarray:
    """Reference float64 evaluation of one function (numpy), used by exporters and tests."""
    table = FunctionTable.compile([fn])
    return table.evaluate_numpy(np.asarray(x, np.float64)[:, None])[:, 0]


@dataclass(frozen=True)
class FunctionTable:
    """Dense parameters of A functions (float64 numpy; turned into buffers by the kinematics)."""

    poly: np.ndarray  # (A, 4)
    knots: np.ndarray  # (A, K)
    weights: np.ndarray  # (A, K)
    sine: np.ndarray  # (A, 3): amplitude, omega, phase
    arc: np.ndarray  # (A, 2): a, b

    @staticmethod
    def compile(functions: list[Function]) -> FunctionTable:
        n = len(functions)
        pieces = []
        for fn in functions:
            if fn.kind == "spline":
                pieces.append(spline_to_truncated_power(np.array(fn.params["x"]), np.array(fn.params["y"])))
        K = max([len(k) for _, k, _ in pieces], default=0)
        K = max(K, 1)
        poly = np.zeros((n, 4))
        knots = np.full((n, K), 1e3)  # padding knots lie far beyond every coordinate range
        weights = np.zeros((n, K))
        sine = np.zeros((n, 3))
        arc = np.zeros((n, 2))
        it = iter(pieces)
        for i, fn in enumerate(functions):
            p = fn.params
            if fn.kind == "constant":
                poly[i, 0] = p["value"]
            elif fn.kind == "linear":
                poly[i, :2] = [p["intercept"], p["slope"]]
            elif fn.kind == "spline":
                pl, kn, w = next(it)
                poly[i] = pl
                knots[i, : len(kn)] = kn
                weights[i, : len(w)] = w
            elif fn.kind == "sine":
                poly[i, 0] = p["offset"]
                sine[i] = [p["amplitude"], p["omega"], p["phase"]]
            elif fn.kind == "arc":
                arc[i] = [p["a"], p["b"]]
            else:
                raise ValueError(f"unknown function kind {fn.kind!r}")
        return FunctionTable(poly, knots, weights, sine, arc)

    def evaluate_numpy(self, x: np.ndarray) -> np.ndarray:
        """(B, A) coordinate values -> (B, A) function values, float64."""
        t = {k: torch.as_tensor(v) for k, v in self.__dict__.items()}
        return evaluate_table(torch.as_tensor(x), **t).numpy()


def arc_basis(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """g1(x) = sin x - (1 - cos x)/x and g2(x) = sin x / x - cos x, smooth through x = 0.

    Args:
        x: (...) radians.
    Returns:
        g1, g2 with the shape of ``x``.
    """
    small = torch.abs(x) < _SMALL
    xs = torch.where(small, torch.ones_like(x), x)  # keeps the unused branch finite for autograd
    s, c = torch.sin(xs), torch.cos(xs)
    g1 = torch.where(small, x / 2 - x**3 / 8, s - (1 - c) / xs)
    g2 = torch.where(small, x**2 / 3 - x**4 / 30, s / xs - c)
    return g1, g2


def evaluate_table(
    x: torch.Tensor,
    poly: torch.Tensor,
    knots: torch.Tensor,
    weights: torch.Tensor,
    sine: torch.Tensor,
    arc: torch.Tensor,
) -> torch.Tensor:
    """Evaluate A compiled functions at their coordinate values.

    Args:
        x: (B, A) the coordinate value feeding each function.
        poly (A, 4), knots (A, K), weights (A, K), sine (A, 3), arc (A, 2): see :class:`FunctionTable`.
    Returns:
        (B, A) function values.
    """
    out = poly[:, 0] + x * (poly[:, 1] + x * (poly[:, 2] + x * poly[:, 3]))
    out = out + (torch.relu(x.unsqueeze(-1) - knots) ** 3 * weights).sum(-1)
    out = out + sine[:, 0] * torch.sin(sine[:, 1] * x + sine[:, 2])
    g1, g2 = arc_basis(x)
    return out + arc[:, 0] * g1 + arc[:, 1] * g2
