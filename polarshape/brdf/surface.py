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
from polarshape.brdf.geometry import ShadingGeometry, Vec3, angle_from, dot3, double_angle_of, safe_norm3, shading_geometry


def surface_parts(
    geo: ShadingGeometry,
    *,
    ior: Tensor | float,
    scale: Tensor | float,
    alpha: Tensor,
    beta: Tensor,
    c: Tensor,
    projected_area: Callable[[Tensor], Tensor],
) -> Vec3:
    """Surface-reflection Stokes (s0, s1, s2) (spec §6) of a :class:`ShadingGeometry`, each (...).

    Args:
        geo: :func:`~polarshape.brdf.geometry.shading_geometry` of unit N, L, V.
        ior: μ; scale: k_s times the irradiance (broadcastable to (...)).
        alpha, beta: D's parameters (0-dim); c: D's normalisation (eq. 5).
        projected_area: θ ↦ P(θ) of spec §4 (tabulated or exact).

    Returns:
        (s0, s1, s2) in the pixel frame, zero unless N·L > 0 and N·V > 0 (then [N·L]₊ and the
        N·V mask make the factor 0; every other factor is finite).
    """
    dt = geo.n_dot_l.dtype
    h = (geo.light[0] + geo.view[0], geo.light[1] + geo.view[1], geo.light[2] + geo.view[2])  # L + V ∝ H (spec §6)
    # θ_H = ∠(N, H) = ∠(N, L + V): N × (L + V) = N × L + N × V, N·(L + V) = N·L + N·V
    n_cross_h = (geo.n_cross_l[0] + geo.n_cross_v[0], geo.n_cross_l[1] + geo.n_cross_v[1], geo.n_cross_l[2] + geo.n_cross_v[2])
    theta_h = angle_from(n_cross_h, geo.n_dot_l + geo.n_dot_v)
    d = c.to(dt) * d_shape(theta_h, alpha.to(dt), beta.to(dt))  # eq. 2, 5
    # D G1(L) G1(V) / (4 N·V) = D (N·L) / (4 P(L) P(V))  (spec §4, §6); P(V) per pixel
    area_v4 = 4.0 * projected_area(geo.theta_v)
    k = torch.as_tensor(scale, dtype=dt, device=geo.n_dot_l.device) * geo.view_mask
    factor = k * (d * geo.n_dot_l.clamp_min(0.0) / (projected_area(geo.theta_l) * area_v4))
    # θ_d = ∠(V, H): cos θ_d = V·(L + V)/|L + V| = |L + V|/2 for unit L, V (|L + V|² = 2 + 2 L·V)
    fr = fresnel(0.5 * safe_norm3(h), ior)
    cos2, sin2 = double_angle_of(dot3(h, geo.e_x), dot3(h, geo.e_y))  # ψ(H); |L + V| cancels
    s1_factor = factor * fr.t_minus  # −R− (spec §5 reflected: (R+, −R− cos 2ψ, −R− sin 2ψ))
    return factor * fr.r_plus, s1_factor * cos2, s1_factor * sin2


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
        (..., 3) Stokes (s0, s1, s2) in the pixel frame (:func:`surface_parts` stacked; (...) is
        the broadcast shape of the inputs); zero unless N·L > 0 and N·V > 0.
    """
    geo = shading_geometry(normal, light, view) if geometry is None else geometry
    parts = surface_parts(geo, ior=ior, scale=k_s, alpha=alpha, beta=beta, c=c, projected_area=projected_area)
    return torch.stack(torch.broadcast_tensors(*parts), dim=-1)
