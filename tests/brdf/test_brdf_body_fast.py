"""Tests of polarshape.brdf.body_fast: the body-term table build (chunking)."""

from __future__ import annotations

import pytest
import torch

from polarshape.brdf.body_fast import build_body_table
from polarshape.brdf.distribution import d_normalisation


def _material(kappa: float, requires_grad: bool = False) -> tuple[torch.Tensor, ...]:
    mu, a, b = (torch.tensor(v, dtype=torch.float64) for v in (1.5, 0.25, 2.0))
    k = torch.tensor(kappa, dtype=torch.float64, requires_grad=requires_grad)
    return mu, a, b, k, d_normalisation(a, b)


@pytest.mark.parametrize("kappa", [0.0, 50.0])
def test_body_table_does_not_depend_on_the_chunk_size(kappa: float) -> None:
    """One θ row at a time (and one kernel row) gives the table of one chunk for everything."""
    whole = build_body_table(*_material(kappa), n_grid=9, n_theta=3, max_width=0.3, chunk_elements=1 << 40)
    rows = build_body_table(*_material(kappa), n_grid=9, n_theta=3, max_width=0.3, chunk_elements=1)
    assert rows.n_modes == whole.n_modes and rows.values.shape == whole.values.shape
    torch.testing.assert_close(rows.values, whole.values, rtol=1e-13, atol=1e-13)


def test_body_table_gradient_does_not_depend_on_the_chunk_size() -> None:
    grads = []
    for chunk in (1 << 40, 1):
        mu, a, b, k, c = _material(20.0, requires_grad=True)
        build_body_table(mu, a, b, k, c, n_grid=5, n_dphi=9, n_theta=3, max_width=0.3,
                         chunk_elements=chunk).values.sum().backward()
        grads.append(k.grad)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-12, atol=0.0)
