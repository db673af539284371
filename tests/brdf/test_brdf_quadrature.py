"""Tests of polarshape.brdf.quadrature: the θ warp of the tables."""

from __future__ import annotations

import torch

from polarshape.brdf.quadrature import ThetaWarp, asinh_nonneg


def test_asinh_identity_matches_torch_asinh() -> None:
    x = torch.cat([torch.zeros(1), torch.logspace(-12, 4, 2001)]).double()
    torch.testing.assert_close(asinh_nonneg(x), torch.asinh(x), rtol=4e-16, atol=0.0)
    x32 = x.float()
    torch.testing.assert_close(asinh_nonneg(x32), torch.asinh(x32), rtol=3e-7, atol=0.0)
    xg = x[1::50].clone().requires_grad_(True)
    (g,) = torch.autograd.grad(asinh_nonneg(xg).sum(), xg)
    torch.testing.assert_close(g, 1.0 / torch.sqrt(1.0 + xg.detach() ** 2), rtol=1e-14, atol=0.0)


def test_warp_maps_the_quarter_circle_onto_the_grid() -> None:
    warp = ThetaWarp.for_alpha(0.3)
    nodes = torch.as_tensor(warp.nodes(65))
    t = warp.to_grid(nodes)
    torch.testing.assert_close(t, torch.linspace(-1.0, 1.0, 65, dtype=torch.float64), rtol=0.0, atol=1e-13)
