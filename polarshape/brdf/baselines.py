"""Baseline reflectance models of spec §10, behind the FMBRDF's interface.

Each ``*_stokes(normal, light, view, **params)`` takes (..., 3) unit vectors in the camera frame
(N, L to the light, V to the camera) and returns (..., 3) Stokes (s0, s1, s2) in the pixel frame of
spec §1 for unit irradiance at normal incidence (N·L foreshortening included), zero unless N·L > 0
and N·V > 0 — exactly like :func:`polarshape.brdf.fmbrdf_stokes`, so later stages can swap models.
:data:`MODELS` lists them with their parameters and bounds for model selection.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from polarshape.brdf.fresnel import fresnel
from polarshape.brdf.geometry import angle_between, dot, double_angle, safe_normalize, stokes_frame, tiny


def _prep(normal: Tensor, light: Tensor, view: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    n, l, v = torch.broadcast_tensors(safe_normalize(normal), safe_normalize(light), safe_normalize(view))
    n_dot_l, n_dot_v = dot(n, l), dot(n, v)
    return n, l, v, n_dot_l, n_dot_v, (n_dot_l > 0) & (n_dot_v > 0)


def _masked(front: Tensor, s: Tensor) -> Tensor:
    return torch.where(front.unsqueeze(-1), s, torch.zeros_like(s))


def _unpolarised(value: Tensor) -> Tensor:
    z = torch.zeros_like(value)
    return torch.stack([value, z, z], dim=-1)


def lambertian_stokes(normal: Tensor, light: Tensor, view: Tensor, *, k_d: Tensor | float) -> Tensor:
    """Lambertian: I = (k_d/π)(N·L)₊, unpolarised (spec §10)."""
    n, l, v, n_dot_l, _, front = _prep(normal, light, view)
    kd = torch.as_tensor(k_d, dtype=n.dtype, device=n.device)
    return _masked(front, _unpolarised(kd / math.pi * n_dot_l.clamp_min(0.0)))


def oren_nayar_stokes(normal: Tensor, light: Tensor, view: Tensor, *, k_d: Tensor | float, sigma: Tensor | float) -> Tensor:
    """Qualitative Oren–Nayar body reflection (roughness σ, rad), unpolarised (spec §10).

    I = (k_d/π)(N·L)(A + B max(0, cos(φ_V − φ_L)) sin a tan b), a = max(θ_L, θ_V), b = min(θ_L, θ_V),
    A = 1 − 0.5σ²/(σ² + 0.33), B = 0.45σ²/(σ² + 0.09).
    """
    n, l, v, n_dot_l, n_dot_v, front = _prep(normal, light, view)
    s2 = torch.as_tensor(sigma, dtype=n.dtype, device=n.device) ** 2
    a_coef = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b_coef = 0.45 * s2 / (s2 + 0.09)
    th_l = angle_between(n, l).clamp(max=math.pi / 2)
    th_v = angle_between(n, v).clamp(max=math.pi / 2)
    l_t = l - n_dot_l.unsqueeze(-1) * n
    v_t = v - n_dot_v.unsqueeze(-1) * n
    cos_dphi = dot(safe_normalize(l_t), safe_normalize(v_t))
    big, small = torch.maximum(th_l, th_v), torch.minimum(th_l, th_v).clamp(max=math.pi / 2 - 1e-4)
    value = n_dot_l.clamp_min(0.0) * (a_coef + b_coef * cos_dphi.clamp_min(0.0) * torch.sin(big) * torch.tan(small))
    kd = torch.as_tensor(k_d, dtype=n.dtype, device=n.device)
    return _masked(front, _unpolarised(kd / math.pi * value))


def _reflected_stokes(half: Tensor, view: Tensor, ior: Tensor | float, e_x: Tensor, e_y: Tensor) -> Tensor:
    fr = fresnel(dot(view, half), ior)
    cos2, sin2 = double_angle(half, e_x, e_y)
    return torch.stack([fr.r_plus, -fr.r_minus * cos2, -fr.r_minus * sin2], dim=-1)


def beckmann_d(cos_h: Tensor, m: Tensor) -> Tensor:
    """Beckmann distribution exp(−tan²θ/m²)/(π m² cos⁴θ), m = RMS slope."""
    c2 = (cos_h * cos_h).clamp_min(tiny(cos_h.dtype) ** 0.25)
    tan2 = (1.0 - c2) / c2
    return torch.exp(-tan2 / (m * m)) / (math.pi * m * m * c2 * c2)


def ggx_d(cos_h: Tensor, a: Tensor) -> Tensor:
    """GGX / Trowbridge–Reitz distribution a²/(π((N·H)²(a² − 1) + 1)²)."""
    a2 = a * a
    den = (cos_h * cos_h * (a2 - 1.0) + 1.0).clamp_min(tiny(cos_h.dtype) ** 0.25)
    return a2 / (math.pi * den * den)


def ggx_g1(cos_w: Tensor, a: Tensor) -> Tensor:
    """Smith G1 for GGX: 2 cos / (cos + √(a² + (1 − a²) cos²))."""
    c = cos_w.clamp_min(0.0)
    return 2.0 * c / (c + torch.sqrt(a * a + (1.0 - a * a) * c * c)).clamp_min(tiny(c.dtype))


def beckmann_g1(cos_w: Tensor, m: Tensor) -> Tensor:
    """Smith G1 for Beckmann, Walter et al. 2007 rational approximation (rel. error < 0.35 %)."""
    c = cos_w.clamp(0.0, 1.0)
    s = torch.sqrt((1.0 - c * c).clamp_min(tiny(c.dtype)))
    x = c / (m * s)  # a = cot θ / m
    g = (3.535 * x + 2.181 * x * x) / (1.0 + 2.276 * x + 2.577 * x * x)
    return torch.where(x < 1.6, g, torch.ones_like(g))


def torrance_sparrow_stokes(
    normal: Tensor, light: Tensor, view: Tensor, *, ior: Tensor | float, k_s: Tensor | float, roughness: Tensor | float
) -> Tensor:
    """Torrance–Sparrow specular lobe (spec §10): k_s · F · D_Beckmann · G_V-cavity / (4 N·V), with
    the polarised Fresnel reflection of spec §5 (⟂ to the plane of incidence)."""
    n, l, v, n_dot_l, n_dot_v, front = _prep(normal, light, view)
    e_x, e_y = stokes_frame(v)
    h = safe_normalize(l + v)
    n_dot_h = dot(n, h).clamp_min(0.0)
    v_dot_h = dot(v, h).clamp_min(tiny(n.dtype) ** 0.5)
    m = torch.as_tensor(roughness, dtype=n.dtype, device=n.device)
    g = torch.minimum(torch.ones_like(n_dot_h), 2.0 * n_dot_h * torch.minimum(n_dot_v, n_dot_l).clamp_min(0.0) / v_dot_h)
    value = beckmann_d(n_dot_h, m) * g / (4.0 * n_dot_v.clamp_min(tiny(n.dtype) ** 0.5))
    ks = torch.as_tensor(k_s, dtype=n.dtype, device=n.device)
    return _masked(front, (ks * value).unsqueeze(-1) * _reflected_stokes(h, v, ior, e_x, e_y))


def baek_pbrdf_stokes(
    normal: Tensor,
    light: Tensor,
    view: Tensor,
    *,
    ior: Tensor | float,
    k_s: Tensor | float,
    k_d: Tensor | float,
    alpha: Tensor | float,
    distribution: str = "ggx",
) -> Tensor:
    """Baek et al. 2018 polarimetric BRDF (spec §10).

    Specular: k_s · D(θ_H) G1(L) G1(V) / (4 N·V) · R-Stokes(θ_d, ψ(H)) with GGX (or Beckmann,
    ``distribution="beckmann"``, α = RMS slope, as Mitsuba's ``pplastic``) D and Smith G.
    Diffuse: (k_d/π)(N·L) T+(θ_L) · T-Stokes(θ_V, ψ(N)) — Lambertian body with Fresnel transmission
    into (θ_L) and out of (θ_V) the macro-surface, polarised ∥ to the plane of N and V.
    """
    if distribution not in ("ggx", "beckmann"):
        raise ValueError(f"distribution must be 'ggx' or 'beckmann'; got {distribution!r}")
    n, l, v, n_dot_l, n_dot_v, front = _prep(normal, light, view)
    e_x, e_y = stokes_frame(v)
    h = safe_normalize(l + v)
    a = torch.as_tensor(alpha, dtype=n.dtype, device=n.device)
    n_dot_h = dot(n, h).clamp_min(0.0)
    if distribution == "ggx":
        d, g = ggx_d(n_dot_h, a), ggx_g1(n_dot_l, a) * ggx_g1(n_dot_v, a)
    else:
        d, g = beckmann_d(n_dot_h, a), beckmann_g1(n_dot_l, a) * beckmann_g1(n_dot_v, a)
    ks = torch.as_tensor(k_s, dtype=n.dtype, device=n.device)
    spec = (ks * d * g / (4.0 * n_dot_v.clamp_min(tiny(n.dtype) ** 0.5))).unsqueeze(-1) * _reflected_stokes(h, v, ior, e_x, e_y)
    t_in = fresnel(n_dot_l.clamp_min(0.0), ior)
    t_out = fresnel(n_dot_v.clamp_min(0.0), ior)
    cos2, sin2 = double_angle(n, e_x, e_y)  # ψ(N)
    kd = torch.as_tensor(k_d, dtype=n.dtype, device=n.device)
    scale = kd / math.pi * n_dot_l.clamp_min(0.0) * t_in.t_plus
    diff = scale.unsqueeze(-1) * torch.stack([t_out.t_plus, -t_out.t_minus * cos2, -t_out.t_minus * sin2], dim=-1)
    return _masked(front, spec + diff)


@dataclass(frozen=True)
class ModelSpec:
    """A reflectance model: its Stokes function, parameters with (lower, upper) bounds, and whether
    it predicts polarisation."""

    stokes: Callable[..., Tensor]
    params: dict[str, tuple[float, float]]
    polarised: bool


def _fmbrdf(*args: Tensor, **kw: object) -> Tensor:
    from polarshape.brdf.fmbrdf import fmbrdf_stokes

    return fmbrdf_stokes(*args, **kw)  # type: ignore[arg-type]


#: Every model by name, simplest first.
MODELS: dict[str, ModelSpec] = {
    "lambertian": ModelSpec(lambertian_stokes, {"k_d": (0.0, math.inf)}, polarised=False),
    "oren_nayar": ModelSpec(oren_nayar_stokes, {"k_d": (0.0, math.inf), "sigma": (0.0, 1.5)}, polarised=False),
    "torrance_sparrow": ModelSpec(torrance_sparrow_stokes, {"ior": (1.0, 3.0), "k_s": (0.0, math.inf), "roughness": (0.01, 1.5)}, polarised=True),
    "baek": ModelSpec(baek_pbrdf_stokes, {"ior": (1.0, 3.0), "k_s": (0.0, math.inf), "k_d": (0.0, math.inf), "alpha": (0.01, 1.5)}, polarised=True),
    "fmbrdf": ModelSpec(
        _fmbrdf,
        {"ior": (1.0, 4.0), "k_s": (0.0, math.inf), "k_b": (0.0, math.inf), "alpha": (0.01, 2.0), "beta": (0.5, 4.0), "kappa": (0.0, 100.0)},
        polarised=True,
    ),
}
