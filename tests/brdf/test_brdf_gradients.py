"""torch.autograd.gradcheck in float64 for the normal and every parameter, fast and exact paths."""

import numpy as np
import pytest
import torch
from brdf_helpers import random_geometry

from polarshape.brdf import build_tables, fmbrdf_stokes

F64 = torch.float64
LAYOUT = (0.35, 1.8, 8.0)  # fixed discretisation: the function is then smooth in α, β, κ


def _geometry(n=3, seed=0):
    n_, l_, v_ = random_geometry(np.random.default_rng(seed), n, max_deg=80)
    return n_, l_, v_


def test_gradcheck_normal_light_view_with_fixed_tables():
    n, l, v = _geometry(6)
    t = build_tables(ior=1.5, alpha=0.35, beta=1.8, kappa=8.0)
    p = dict(ior=1.5, k_s=0.8, k_b=0.6, alpha=0.35, beta=1.8, kappa=8.0, tables=t)
    inputs = tuple(x.clone().requires_grad_(True) for x in (n, l, v))
    assert torch.autograd.gradcheck(lambda n, l, v: fmbrdf_stokes(n, l, v, **p), inputs, atol=1e-7, rtol=1e-4)


@pytest.mark.slow
def test_gradcheck_all_parameters_fast_path():
    n, l, v = _geometry(4, seed=1)
    n = n.clone().requires_grad_(True)
    params = tuple(torch.tensor(x, dtype=F64, requires_grad=True) for x in (1.5, 0.8, 0.6, 0.35, 1.8, 8.0))

    def f(normal, ior, k_s, k_b, alpha, beta, kappa):
        t = build_tables(ior=ior, alpha=alpha, beta=beta, kappa=kappa, n_grid=17, layout=LAYOUT)
        return fmbrdf_stokes(normal, l, v, ior=ior, k_s=k_s, k_b=k_b, alpha=alpha, beta=beta, kappa=kappa, tables=t)

    assert torch.autograd.gradcheck(f, (n, *params), atol=1e-7, rtol=1e-4, fast_mode=True)


def test_per_pixel_body_albedo_gradient():
    n, l, v = _geometry(5, seed=2)
    t = build_tables(ior=1.5, alpha=0.35, beta=1.8, kappa=8.0)
    kb = torch.rand(5, dtype=F64, requires_grad=True)
    f = lambda kb: fmbrdf_stokes(n, l, v, ior=1.5, k_s=0.5, k_b=kb, alpha=0.35, beta=1.8, kappa=8.0, tables=t)  # noqa: E731
    assert torch.autograd.gradcheck(f, (kb,))


def test_kappa_gradient_at_zero_is_nonzero_and_matches_one_sided_difference():
    """Fitting κ from 0 needs ∂/∂κ at κ = 0: no separable shortcut when κ requires grad."""
    n, l, v = _geometry(8, seed=3)
    k = torch.tensor(0.0, dtype=F64, requires_grad=True)
    t = build_tables(ior=1.5, alpha=0.5, beta=2.0, kappa=k)
    s = fmbrdf_stokes(n, l, v, ior=1.5, k_s=0.0, k_b=1.0, alpha=0.5, beta=2.0, kappa=k, tables=t)[:, 0].sum()
    (g,) = torch.autograd.grad(s, k)
    h = 1e-4
    with torch.no_grad():
        th = build_tables(ior=1.5, alpha=0.5, beta=2.0, kappa=h)  # κ > 0: Fourier-kernel path
        s_h = fmbrdf_stokes(n, l, v, ior=1.5, k_s=0.0, k_b=1.0, alpha=0.5, beta=2.0, kappa=h, tables=th)[:, 0].sum()
    fd = float((s_h - s.detach()) / h)
    assert abs(float(g)) > 1e-6
    assert float(g) == pytest.approx(fd, rel=2e-2)


@pytest.mark.slow
def test_gradcheck_exact_path():
    """The reference evaluator is differentiable too (κ = 0: its separable branch; κ > 0 in the
    directional check below)."""
    n, l, v = _geometry(1, seed=4)
    n = n.clone().requires_grad_(True)
    params = tuple(torch.tensor(x, dtype=F64, requires_grad=True) for x in (1.5, 0.8, 0.6, 0.35, 1.8))

    def f(normal, ior, k_s, k_b, alpha, beta):
        return fmbrdf_stokes(normal, l, v, ior=ior, k_s=k_s, k_b=k_b, alpha=alpha, beta=beta, kappa=0.0, exact=True)

    assert torch.autograd.gradcheck(f, (n, *params), atol=1e-6, rtol=1e-3, fast_mode=True)


@pytest.mark.slow
def test_exact_path_kappa_gradient_directional():
    n, l, v = _geometry(1, seed=5)
    k = torch.tensor(20.0, dtype=F64, requires_grad=True)
    f = lambda k: fmbrdf_stokes(n, l, v, ior=1.5, k_s=0.0, k_b=1.0, alpha=0.35, beta=1.8, kappa=k, exact=True)[..., 0].sum()  # noqa: E731
    (g,) = torch.autograd.grad(f(k), k)
    h = 0.05
    fd = float((f(torch.tensor(20.0 + h, dtype=F64)) - f(torch.tensor(20.0 - h, dtype=F64))) / (2 * h))
    assert float(g) == pytest.approx(fd, rel=2e-2, abs=1e-9)
