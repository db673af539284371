"""Surface (specular) reflection of the FMBRDF (spec §6, paper eq. 1 and 23).

    s_s = k_s · D(θ_H) · G1(L) G1(V) / (4 N·V) · R-Stokes(θ_d, ψ(H)) · E

With the Smith identity of spec §4, G1(ω) = cos θ_ω / P(ω), this is evaluated as
k_s · D(θ_H) · (N·L) / (4 P(L) P(V)) · R-Stokes, which has no 1/(N·V) singularity at grazing view.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from polarshape.brdf.distribution import d_shape
from polarshape.brdf.fresnel import fresnel
from polarshape.brdf.geometry import ShadingGeometry, angle_between, dot, double_angle, safe_normalize, shading_geometry


def surface_stokes(
    normal: Tensor,
    light: Tensor,
    view: Tensor,
    *,
    ior: Tensor | float,
    k_s: Tensor | float,
    alpha: Tensor,
    beta: Tensor,
    c: Tensor,
    projected_area: Callable[[Tensor], Tensor],
    geometry: ShadingGeometry | None = None,
) -> Tensor:
    """Surface-reflection Stokes vector (spec §6) for unit irradiance at normal incidence.

    Args:
        normal, light, view: (..., 3) unit vectors N, L, V in the camera frame (broadcastable).
        ior: μ; k_s: surface albedo (broadcastable to (...)).
        alpha, beta: D's parameters (0-dim); c: D's normalisation (eq. 5).
        projected_area: θ ↦ P(θ) of spec §4 (tabulated or exact).
        geometry: :func:`~polarshape.brdf.geometry.shading_geometry` of (N, L, V) if already computed.

    Returns:
        (..., 3) Stokes (s0, s1, s2) in the pixel frame; zero unless N·L > 0 and N·V > 0.
    """
    normal, light, view = torch.broadcast_tensors(normal, light, view)
    geo = shading_geometry(normal, light, view) if geometry is None else geometry
    e_x, e_y, n_dot_l, front, theta_l, theta_v = geo.e_x, geo.e_y, geo.n_dot_l, geo.front, geo.theta_l, geo.theta_v
    half = safe_normalize(light + view)  # H (spec §6)
    theta_h = angle_between(normal, half)
    d = c.to(normal.dtype) * d_shape(theta_h, alpha.to(normal.dtype), beta.to(normal.dtype))  # eq. 2, 5
    # D G1(L) G1(V) / (4 N·V) = D (N·L) / (4 P(L) P(V))  (spec §4, §6)
    radiance = d * n_dot_l.clamp_min(0.0) / (4.0 * projected_area(theta_l) * projected_area(theta_v))
    fr = fresnel(dot(view, half), ior)  # θ_d = ∠(V, H)
    cos2, sin2 = double_angle(half, e_x, e_y)  # ψ(H)
    k = torch.as_tensor(k_s, dtype=normal.dtype, device=normal.device)
    s = torch.stack([fr.r_plus, -fr.r_minus * cos2, -fr.r_minus * sin2], dim=-1)  # spec §5 reflected
    out = (k * radiance).unsqueeze(-1) * s
    return torch.where(front.unsqueeze(-1), out, torch.zeros_like(out))
