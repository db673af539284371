"""Dielectric Fresnel reflection and transmission for light arriving from air (spec §5).

With amplitude coefficients r_s, r_p at incidence cos θ_i and relative index μ:
R± = (R_s ± R_p)/2, T± = (T_s ± T_p)/2 with T = 1 − R, so that R+ + T+ = 1 and T− = −R− ≤ 0.
Reflected Stokes ∝ (R+, −R− cos 2ψ, −R− sin 2ψ); transmitted ∝ (T+, −T− cos 2ψ, −T− sin 2ψ),
ψ the angle of the facet normal in the Stokes frame (spec §5).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from polarshape.brdf.geometry import tiny


class FresnelTerms(NamedTuple):
    """R+, R−, T+, T− of spec §5, each (...)."""

    r_plus: Tensor
    r_minus: Tensor
    t_plus: Tensor
    t_minus: Tensor


def fresnel(cos_i: Tensor, ior: Tensor | float) -> FresnelTerms:
    """Fresnel terms at incidence cos θ_i for a dielectric of index μ ≥ 1 (spec §5).

    Args:
        cos_i: (...) cosine of the incidence angle (clamped to [0, 1]).
        ior: μ, float or broadcastable tensor (μ → 1 gives R = 0, T = 1).

    Returns:
        :class:`FresnelTerms` (R+, R−, T+, T−), finite with finite gradients everywhere.
    """
    eps = tiny(cos_i.dtype)
    mu = torch.as_tensor(ior, dtype=cos_i.dtype, device=cos_i.device)
    ci = cos_i.clamp(0.0, 1.0)
    sin2_t = (1.0 - ci * ci) / (mu * mu)
    ct = torch.sqrt((1.0 - sin2_t).clamp_min(eps))
    r_s = (ci - mu * ct) / (ci + mu * ct).clamp_min(eps)
    r_p = (mu * ci - ct) / (mu * ci + ct).clamp_min(eps)
    rs2 = r_s * r_s
    rp2 = r_p * r_p
    r_plus = 0.5 * (rs2 + rp2)
    r_minus = 0.5 * (rs2 - rp2)
    return FresnelTerms(r_plus, r_minus, 1.0 - r_plus, -r_minus)
