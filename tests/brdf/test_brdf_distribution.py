import math

import numpy as np
import pytest
import scipy.integrate as si
import torch

from polarshape.brdf.distribution import d_normalisation, d_shape, microfacet_d

BOX = [(0.01, 0.5), (0.01, 4.0), (2.0, 0.5), (2.0, 4.0), (0.3, 2.0), (0.05, 1.0), (0.8, 3.0)]
RNG = np.random.default_rng(7)
BOX += [(float(np.exp(RNG.uniform(np.log(0.01), np.log(2.0)))), float(RNG.uniform(0.5, 4.0))) for _ in range(12)]


@pytest.mark.parametrize("alpha,beta", BOX)
def test_projected_area_normalisation_eq5(alpha, beta):
    """∫_Ω D(θ) cos θ dω = 1 (eq. 5), checked with scipy's adaptive quadrature to 1e-6."""
    c = float(d_normalisation(alpha, beta))

    def f(t):
        return c * math.exp(-((t / alpha) ** beta)) * math.cos(t) * math.sin(t) * 2 * math.pi

    pts = [alpha * x for x in (0.1, 0.5, 1, 2, 4, 8, 16) if alpha * x < math.pi / 2]
    val, _ = si.quad(f, 0, math.pi / 2, points=pts, limit=500, epsabs=1e-14, epsrel=1e-12)
    assert abs(val - 1.0) < 1e-6


def test_d_peak_and_monotone():
    th = torch.linspace(0, math.pi / 2, 200, dtype=torch.float64)
    d = microfacet_d(th, 0.2, 2.0)
    assert torch.all(d[1:] <= d[:-1])
    # Gaussian-like limit: c ≈ 1/(π α²) for small α, β = 2
    assert float(d[0]) == pytest.approx(1.0 / (math.pi * 0.2**2), rel=0.05)


@pytest.mark.parametrize("beta", [0.5, 1.0, 2.0, 4.0])
def test_d_finite_gradients_at_zero_and_far_tail(beta):
    th = torch.tensor([0.0, 1e-12, 1e-3, math.pi / 2], dtype=torch.float64, requires_grad=True)
    a = torch.tensor(0.01, dtype=torch.float64, requires_grad=True)
    b = torch.tensor(beta, dtype=torch.float64, requires_grad=True)
    d_shape(th, a, b).sum().backward()
    for g in (th.grad, a.grad, b.grad):
        assert torch.isfinite(g).all()


def test_normalisation_gradcheck():
    a = torch.tensor(0.4, dtype=torch.float64, requires_grad=True)
    b = torch.tensor(1.7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: d_normalisation(a, b, layout=(0.4, 1.7)), (a, b))
