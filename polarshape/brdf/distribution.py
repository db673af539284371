"""Microfacet distribution D(θ) = c(α, β)·exp(−(θ/α)^β) (spec §3, paper eq. 2 and 5).

c is fixed by the projected-area normalisation ∫_Ω D(θ_m) cos θ_m dω_m = 1 (eq. 5):
c = 1 / (2π ∫₀^{π/2} exp(−(θ/α)^β) cos θ sin θ dθ), evaluated by a graded composite
Gauss–Legendre rule in torch, so that c is differentiable in α and β.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from polarshape.brdf.geometry import tiny
from polarshape.brdf.quadrature import composite_rule, theta_breaks


def d_shape(theta: Tensor, alpha: Tensor, beta: Tensor) -> Tensor:
    """Un-normalised distribution exp(−(θ/α)^β) (spec §3).

    Written as exp(−exp(β·log(θ/α))) with θ floored at a tiny value, so that values and gradients
    stay finite at θ = 0 for β < 1 (where the true derivative is infinite) and for θ ≫ α.

    Args:
        theta: (...) microfacet polar angle, rad, in [0, π/2].
        alpha: roughness α > 0 (rad), broadcastable.
        beta: shape β > 0, broadcastable.

    Returns:
        (...) values in [0, 1].
    """
    x = theta.clamp_min(tiny(theta.dtype) ** 0.5) / alpha
    log_pow = (beta * torch.log(x)).clamp(max=60.0)
    return torch.exp(-torch.exp(log_pow))


def d_normalisation(
    alpha: Tensor | float, beta: Tensor | float, *, n: int = 12, dtype: torch.dtype = torch.float64, layout: tuple[float, float] | None = None
) -> Tensor:
    """Normalisation constant c(α, β) of eq. 5 (0-dim tensor, differentiable in α and β).

    A composite 12-point Gauss–Legendre rule on panels graded to α (widest 0.05 rad) gives c to
    ~1e-12 relative over α ∈ [0.01, 2], β ∈ [0.5, 4] (checked against scipy in the tests).
    ``layout`` = (α, β) at which to place the nodes (default: the values themselves); fixing it
    makes c a smooth function of α, β with a fixed discretisation.
    """
    alpha_t = torch.as_tensor(alpha, dtype=dtype)
    beta_t = torch.as_tensor(beta, dtype=dtype, device=alpha_t.device)
    la, lb = layout if layout is not None else (float(alpha_t.detach()), float(beta_t.detach()))
    nodes, weights = composite_rule(theta_breaks(la, lb, max_width=0.05), n)
    th = torch.as_tensor(nodes, dtype=alpha_t.dtype, device=alpha_t.device)
    w = torch.as_tensor(weights, dtype=alpha_t.dtype, device=alpha_t.device)
    integral = 2.0 * math.pi * (w * d_shape(th, alpha_t, beta_t) * torch.cos(th) * torch.sin(th)).sum()
    return 1.0 / integral


def microfacet_d(theta: Tensor, alpha: Tensor | float, beta: Tensor | float, c: Tensor | None = None) -> Tensor:
    """Normalised microfacet distribution D(θ) (spec §3, eq. 2 with eq. 5's c).

    Args:
        theta: (...) angle between microfacet normal and macro normal, rad.
        alpha, beta: parameters (floats or broadcastable tensors; scalars for ``c=None``).
        c: precomputed :func:`d_normalisation` (computed when omitted).

    Returns:
        (...) D(θ) in sr⁻¹ (per unit projected area).
    """
    alpha_t = torch.as_tensor(alpha, dtype=theta.dtype, device=theta.device)
    beta_t = torch.as_tensor(beta, dtype=theta.dtype, device=theta.device)
    if c is None:
        c = d_normalisation(alpha_t.to(torch.float64), beta_t.to(torch.float64))
    return c.to(theta.dtype) * d_shape(theta, alpha_t, beta_t)
