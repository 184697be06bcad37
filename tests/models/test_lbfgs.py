"""Batched L-BFGS: every row is its own problem."""

from __future__ import annotations

import pytest
import torch

from bodyfit.models.fitting.common.lbfgs import batched_lbfgs


def rosenbrock(z: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """(N, 2) -> (N,) Rosenbrock functions, row n scaled by scale[n]."""
    x, y = z[:, 0], z[:, 1]
    return scale * ((1 - x) ** 2 + 100 * (y - x**2) ** 2)


def test_rows_converge_independently_of_their_scale() -> None:
    scale = torch.tensor([1e-3, 1.0, 1e3], dtype=torch.float64)
    z0 = torch.tensor([[-1.2, 1.0], [0.0, 0.0], [2.0, -1.0]], dtype=torch.float64)
    result = batched_lbfgs(lambda z: rosenbrock(z, scale), z0, iterations=300)
    torch.testing.assert_close(result.z, torch.ones(3, 2, dtype=torch.float64), atol=1e-5, rtol=0)
    assert (result.loss < 1e-8 * scale.clamp_min(1)).all()
    assert result.evaluations == 301


def test_a_row_does_not_depend_on_its_neighbours() -> None:
    scale = torch.tensor([1.0, 50.0], dtype=torch.float64)
    z0 = torch.tensor([[-1.2, 1.0], [3.0, 3.0]], dtype=torch.float64)
    both = batched_lbfgs(lambda z: rosenbrock(z, scale), z0, iterations=40)
    alone = batched_lbfgs(lambda z: rosenbrock(z, scale[:1]), z0[:1], iterations=40)
    torch.testing.assert_close(both.z[:1], alone.z, atol=1e-12, rtol=0)


def test_quadratic_is_solved_exactly() -> None:
    A = torch.diag(torch.tensor([1.0, 10.0, 100.0, 1000.0], dtype=torch.float64))
    b = torch.tensor([1.0, -2.0, 3.0, -4.0], dtype=torch.float64)
    result = batched_lbfgs(
        lambda z: 0.5 * ((z @ A) * z).sum(1) - z @ b, torch.zeros(1, 4, dtype=torch.float64), 60
    )
    torch.testing.assert_close(result.z[0], torch.linalg.solve(A, b), atol=1e-8, rtol=0)


def test_a_newton_start_solves_a_whitened_quadratic_in_one_step() -> None:
    """Variables scaled so that the Hessian is the identity: the first step is the Newton step."""
    b = torch.tensor([[30.0, -20.0, 5.0]], dtype=torch.float64)

    def f(z: torch.Tensor) -> torch.Tensor:
        return 0.5 * ((z - b) ** 2).sum(1)

    newton = batched_lbfgs(f, torch.zeros_like(b), 1, newton_start=True)
    torch.testing.assert_close(newton.z, b, atol=1e-12, rtol=0)
    unit = batched_lbfgs(f, torch.zeros_like(b), 1)
    assert unit.z.norm() == pytest.approx(1.0)  # the default first step has unit length
