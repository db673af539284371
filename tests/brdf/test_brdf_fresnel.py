import math

import pytest
import torch

from polarshape.brdf.fresnel import fresnel


@pytest.mark.parametrize("mu", [1.0, 1.2, 1.5, 2.0])
def test_energy_r_plus_t_is_one(mu):
    ci = torch.linspace(0, 1, 101, dtype=torch.float64)
    f = fresnel(ci, mu)
    assert torch.allclose(f.r_plus + f.t_plus, torch.ones_like(ci), atol=1e-15)
    assert torch.allclose(f.t_minus, -f.r_minus)
    assert torch.all(f.r_minus >= -1e-15)  # R_s ≥ R_p: reflection polarised ⟂, transmission ∥
    assert torch.all((f.r_plus >= 0) & (f.r_plus <= 1))


def test_normal_incidence_and_grazing_and_brewster():
    mu = 1.5
    f = fresnel(torch.tensor([1.0, 0.0], dtype=torch.float64), mu)
    assert float(f.r_plus[0]) == pytest.approx(((mu - 1) / (mu + 1)) ** 2, rel=1e-12)
    assert float(f.r_minus[0]) == pytest.approx(0.0, abs=1e-15)
    assert float(f.r_plus[1]) == pytest.approx(1.0, abs=1e-6)
    brewster = math.atan(mu)
    fb = fresnel(torch.tensor([math.cos(brewster)], dtype=torch.float64), mu)
    # R_p = 0 at Brewster: R+ = R− = R_s/2
    assert float(fb.r_plus[0] - fb.r_minus[0]) == pytest.approx(0.0, abs=1e-12)


def test_mu_to_one_is_transparent():
    """μ → 1: R → 0 at every incidence short of exactly grazing (where R = 1 for any μ > 1)."""
    f = fresnel(torch.linspace(0.01, 1, 100, dtype=torch.float64), 1.0 + 1e-9)
    assert float(f.r_plus.max()) < 1e-6
    assert float(fresnel(torch.tensor([0.0], dtype=torch.float64), 1.0 + 1e-9).r_plus[0]) == pytest.approx(1.0)


def test_gradients_finite_everywhere():
    ci = torch.tensor([0.0, 1e-9, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    mu = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    f = fresnel(ci, mu)
    (f.r_plus + f.r_minus).sum().backward()
    assert torch.isfinite(ci.grad).all() and torch.isfinite(mu.grad).all()
