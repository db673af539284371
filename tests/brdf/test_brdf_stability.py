"""No NaN/Inf in values or gradients for any valid input (hypothesis): back-facing normals, L = V,
L = −V, grazing angles, zero vectors, and α, β, κ, μ at the ends of their ranges."""

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from polarshape.brdf import build_tables, fmbrdf_stokes

F64 = torch.float64
MATERIALS = [(1.2, 0.01, 0.5, 0.0), (2.0, 0.01, 4.0, 100.0), (1.2, 2.0, 0.5, 100.0), (2.0, 2.0, 4.0, 0.0), (1.0001, 0.3, 2.0, 30.0)]


@pytest.fixture(scope="module")
def tables():
    out = []
    for mu, a, b, k in MATERIALS:
        p = dict(zip(("ior", "alpha", "beta", "kappa"), (mu, a, b, k)))
        out.append((p, build_tables(**p)))
    return out


def _unit(theta, phi):
    return [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), -math.cos(theta)]


angles = st.tuples(
    st.one_of(st.floats(0, math.pi), st.sampled_from([0.0, math.pi / 2, math.pi / 2 - 1e-7, math.pi / 2 + 1e-7, math.pi])),
    st.floats(0, 2 * math.pi),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    idx=st.integers(0, len(MATERIALS) - 1),
    n_ang=angles,
    l_ang=angles,
    special=st.sampled_from(["none", "l_eq_v", "l_eq_minus_v", "n_eq_v", "zero_normal", "n_eq_l"]),
    dtype=st.sampled_from([torch.float32, F64]),
)
def test_finite_values_and_gradients(tables, idx, n_ang, l_ang, special, dtype):
    p, t = tables[idx]
    v = torch.tensor([0.0, 0.0, -1.0], dtype=dtype)
    n = torch.tensor(_unit(*n_ang), dtype=dtype)
    l = torch.tensor(_unit(*l_ang), dtype=dtype)
    if special == "l_eq_v":
        l = v.clone()
    elif special == "l_eq_minus_v":
        l = -v
    elif special == "n_eq_v":
        n = v.clone()
    elif special == "zero_normal":
        n = torch.zeros(3, dtype=dtype)
    elif special == "n_eq_l":
        n = l.clone()
    n.requires_grad_(True)
    l.requires_grad_(True)
    kb = torch.tensor(0.7, dtype=dtype, requires_grad=True)
    s = fmbrdf_stokes(n, l, v, ior=p["ior"], k_s=1.0, k_b=kb, alpha=p["alpha"], beta=p["beta"], kappa=p["kappa"], tables=t)
    assert torch.isfinite(s).all(), s
    assert float(s[0].detach()) >= 0.0
    grads = torch.autograd.grad(s.sum() + s[1] * 0.3 - s[2] * 0.7, [n, l, kb], allow_unused=True)
    for g in grads:
        assert g is None or torch.isfinite(g).all(), grads


@pytest.mark.parametrize("material", MATERIALS)
def test_parameter_gradients_finite_at_bounds_on_degenerate_batch(material):
    """Values and gradients w.r.t. μ, α, β, κ (through the table build), k_s, k_b and N stay finite
    for a batch mixing every degenerate configuration, at the ends of the parameter ranges."""
    p = {k: torch.tensor(x, dtype=F64, requires_grad=True) for k, x in zip(("ior", "alpha", "beta", "kappa"), material)}
    ks = torch.tensor(1.0, dtype=F64, requires_grad=True)
    v = torch.tensor([0.0, 0.0, -1.0], dtype=F64)
    n = torch.tensor(
        [[0, 0, -1.0], [0, 0, 1.0], [1, 0, 0.0], [0, 0, 0.0], [0.6, 0, -0.8], [0.999999, 0, -0.0014142], [0, 0.6, -0.8]], dtype=F64, requires_grad=True
    )
    l = torch.tensor(
        [[0, 0, -1.0], [0, 0, -1.0], [1, 0, 0.0], [0, 1, 0.0], [0, 0, 1.0], [0.999999, 0, -0.0014142], [0, -0.6, -0.8]], dtype=F64
    )
    s = fmbrdf_stokes(n, l, v, k_s=ks, k_b=0.5, **p)
    assert torch.isfinite(s).all()
    grads = torch.autograd.grad((s * torch.tensor([1.0, 0.3, -0.7], dtype=F64)).sum(), [n, ks, *p.values()])
    for g in grads:
        assert torch.isfinite(g).all(), grads
