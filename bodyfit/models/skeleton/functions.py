"""Coordinate functions compiled into dense tables and evaluated in one vectorised pass.

Every :class:`~bodyfit.models.skeleton.spec.Function` is written in one form,

    f(x) = sum_k [lower_k <= x < upper_k] * cubic_k(x - anchor_k)
           + amp sin(omega x + phase) + a g1(x) + b g2(x),

so all transform axes of a skeleton are evaluated with the same tensor operations (no data-dependent
control flow; exports to ONNX). Splines keep their pieces in local coordinates, which keeps float32 exact to
~1e-7 (a global polynomial form loses digits to cancellation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.skeleton.spec import Function

_SMALL = 1e-3  # below this |x| the arc basis uses its Taylor series
_FAR = 1e4  # stands for infinity in piece bounds (coordinates are radians or metres)


def fmm_spline_second_derivatives(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Second derivatives at the knots of the Forsythe-Malcolm-Moler cubic spline (OpenSim SimmSpline).

    The spline of G. E. Forsythe, M. A. Malcolm and C. B. Moler, "Computer Methods for Mathematical
    Computations", Prentice-Hall, 1977 (routine SPLINE), which OpenSim's SimmSpline evaluates.

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


def spline_pieces(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Piecewise form of the SimmSpline through (x, y), as OpenSim evaluates it.

    Pieces: linear below x[0] (end slope), one cubic per knot interval, linear above x[-1].

    Returns:
        lower (P,), upper (P,) piece bounds (half-open [lower, upper)), coef (P, 4) local polynomial
        coefficients in t = x - lower (t = x - x[0] for the first, linear piece).
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    M = fmm_spline_second_derivatives(x, y)
    h = np.diff(x)
    a1 = (y[1:] - y[:-1]) / h - h * (2 * M[:-1] + M[1:]) / 6
    cubic = np.stack([y[:-1], a1, M[:-1] / 2, (M[1:] - M[:-1]) / (6 * h)], axis=1)
    end_slope = a1[-1] + 2 * cubic[-1, 2] * h[-1] + 3 * cubic[-1, 3] * h[-1] ** 2
    below = np.array([[y[0], a1[0], 0.0, 0.0]])
    above = np.array([[y[-1], end_slope, 0.0, 0.0]])
    lower = np.concatenate([[-_FAR], x])
    upper = np.concatenate([x, [_FAR]])
    return lower, upper, np.concatenate([below, cubic, above])


def evaluate_function(fn: Function, x: np.ndarray) -> np.ndarray:
    """Reference float64 evaluation of one function (numpy), used by exporters and tests."""
    table = FunctionTable.compile([fn])
    return table.evaluate_numpy(np.asarray(x, np.float64)[:, None])[:, 0]


@dataclass(frozen=True)
class FunctionTable:
    """Dense parameters of A functions (float64 numpy; turned into buffers by the kinematics).

    Piecewise cubic part: piece k of function a covers [lower[a, k], upper[a, k]) and evaluates
    coef[a, k] at t = x - anchor[a, k]; unused pieces are empty ([FAR, FAR)).
    """

    lower: np.ndarray  # (A, P)
    upper: np.ndarray  # (A, P)
    anchor: np.ndarray  # (A, P)
    coef: np.ndarray  # (A, P, 4)
    sine: np.ndarray  # (A, 3): amplitude, omega, phase
    arc: np.ndarray  # (A, 2): a, b
    multi: np.ndarray  # (S,) int64: the functions with more than one piece (splines)

    @staticmethod
    def compile(functions: list[Function]) -> FunctionTable:
        pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        for fn in functions:
            p = fn.params
            one = (np.array([-_FAR]), np.array([_FAR]))
            if fn.kind == "constant":
                pieces.append((*one, np.array([[p["value"], 0.0, 0.0, 0.0]])))
            elif fn.kind == "linear":
                pieces.append((*one, np.array([[p["intercept"], p["slope"], 0.0, 0.0]])))
            elif fn.kind == "sine":
                pieces.append((*one, np.array([[p["offset"], 0.0, 0.0, 0.0]])))
            elif fn.kind == "arc":
                pieces.append((*one, np.zeros((1, 4))))
            elif fn.kind == "spline":
                pieces.append(spline_pieces(np.array(p["x"]), np.array(p["y"])))
            else:
                raise ValueError(f"unknown function kind {fn.kind!r}")
        n, P = len(functions), max(len(lo) for lo, _, _ in pieces)
        lower = np.full((n, P), _FAR)
        upper = np.full((n, P), _FAR)
        coef = np.zeros((n, P, 4))
        sine = np.zeros((n, 3))
        arc = np.zeros((n, 2))
        for i, (fn, (lo, hi, c)) in enumerate(zip(functions, pieces)):
            lower[i, : len(lo)], upper[i, : len(hi)], coef[i, : len(c)] = lo, hi, c
            if fn.kind == "sine":
                sine[i] = [fn.params["amplitude"], fn.params["omega"], fn.params["phase"]]
            elif fn.kind == "arc":
                arc[i] = [fn.params["a"], fn.params["b"]]
        # Local polynomial origin: the piece start, except the unbounded first piece (its upper end, or 0).
        anchor = np.where(lower <= -_FAR, np.where(upper >= _FAR, 0.0, upper), lower)
        multi = np.flatnonzero((lower < _FAR).sum(axis=1) > 1).astype(np.int64)
        return FunctionTable(lower, upper, anchor, coef, sine, arc, multi)

    def evaluate_numpy(self, x: np.ndarray) -> np.ndarray:
        """(B, A) coordinate values -> (B, A) function values, float64."""
        t = {k: torch.as_tensor(v) for k, v in self.__dict__.items()}  # multi stays int64
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
    s = torch.sin(xs)
    half = torch.sin(xs / 2)
    versine = 2 * half * half  # 1 - cos x without cancellation (float32 stays accurate near 0)
    g1 = torch.where(small, x / 2 - x**3 / 8, s - versine / xs)
    g2 = torch.where(small, x**2 / 3 - x**4 / 30, (s / xs - 1) + versine)
    return g1, g2


def evaluate_table(
    x: torch.Tensor,
    lower: torch.Tensor,
    upper: torch.Tensor,
    anchor: torch.Tensor,
    coef: torch.Tensor,
    sine: torch.Tensor,
    arc: torch.Tensor,
    multi: torch.Tensor,
) -> torch.Tensor:
    """Evaluate A compiled functions at their coordinate values.

    Every function is first evaluated on its first piece (the only one of constants, lines, sines and
    arcs); the S splines among them are then evaluated piece by piece and written over that.

    Args:
        x: (B, A) the coordinate value feeding each function.
        lower, upper, anchor (A, P), coef (A, P, 4), sine (A, 3), arc (A, 2), multi (S,): see
            :class:`FunctionTable`.
    Returns:
        (B, A) function values.
    """
    c = coef[:, 0]
    t = x - anchor[:, 0]
    out = c[:, 0] + t * (c[:, 1] + t * (c[:, 2] + t * c[:, 3]))
    if len(multi):
        xe = x[:, multi].unsqueeze(-1)  # (B, S, 1)
        c = coef[multi]
        t = xe - anchor[multi]
        poly = c[..., 0] + t * (c[..., 1] + t * (c[..., 2] + t * c[..., 3]))
        inside = (xe >= lower[multi]) & (xe < upper[multi])
        out = out.index_copy(1, multi, torch.where(inside, poly, torch.zeros_like(poly)).sum(-1))
    out = out + sine[:, 0] * torch.sin(sine[:, 1] * x + sine[:, 2])
    g1, g2 = arc_basis(x)
    return out + arc[:, 0] * g1 + arc[:, 1] * g2
