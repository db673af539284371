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
    """R+, R− of spec §5, each (...); T+ = 1 − R+ and T− = −R− are computed when read (a caller that
    needs only the reflection, or only T+ and R−, makes neither)."""

    r_plus: Tensor
    r_minus: Tensor

    @property
    def t_plus(self) -> Tensor:
        """T+ = (T_s + T_p)/2 = 1 − R+ (...)."""
        return 1.0 - self.r_plus

    @property
    def t_minus(self) -> Tensor:
        """T− = (T_s − T_p)/2 = −R− ≤ 0 (...)."""
        return -self.r_minus


def fresnel(cos_i: Tensor, ior: Tensor | float) -> FresnelTerms:
    """Fresnel terms at incidence cos θ_i for a dielectric of index μ ≥ 1 (spec §5).

    Args:
        cos_i: (...) cosine of the incidence angle (clamped to [0, 1]).
        ior: μ, float or broadcastable tensor (μ → 1 gives R = 0, T = 1).

    Returns:
        :class:`FresnelTerms` (R+, R−; T+, T− on reading), finite with finite gradients everywhere.
    """
    eps = tiny(cos_i.dtype)
    mu = torch.as_tensor(ior, dtype=cos_i.dtype, device=cos_i.device)
    ci = cos_i.clamp(0.0, 1.0)
    sin2_t = (1.0 - ci * ci) / (mu * mu)
    ct = torch.sqrt((1.0 - sin2_t).clamp_min(eps))
    # the denominators are ≥ μ·√eps > eps for any μ > √eps (ct ≥ √eps): no clamp needed, none taken
    r_s = (ci - mu * ct) / (ci + mu * ct)
    r_p = (mu * ci - ct) / (mu * ci + ct)
    rs2 = r_s * r_s
    rp2 = r_p * r_p
    return FresnelTerms(0.5 * (rs2 + rp2), 0.5 * (rs2 - rp2))
