"""Smith masking–shadowing for the FMBRDF microfacet distribution (spec §4, paper eq. 1, 17).

No closed form exists for D ∝ exp(−(θ/α)^β). We use the exact height-field identity

    1 + Λ(ω) = P(ω) / cos θ_ω,   P(ω) = ∫_Ω [ω·m]₊ D(m) dω_m,   G1(ω) = cos θ_ω / P(ω),

where P is the projected area of the microfacets visible from ω. Its azimuthal integral is closed
form (:func:`clipped_cos_azimuthal`), leaving a 1-D integral over θ_m:

    P(θ_ω) = ∫₀^{π/2} D(θ_m) sin θ_m Φ(cos θ_ω cos θ_m, sin θ_ω sin θ_m) dθ_m.

Two evaluators: :func:`projected_area_exact` (adaptive: the kink θ_m = π/2 − θ_ω is a panel
breakpoint and the rule is refined until converged) and :class:`SmithTable` (P tabulated for the
current α, β on a grid dense near grazing, linearly interpolated; error measured in the tests).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from polarshape.brdf.distribution import d_shape
from polarshape.brdf.geometry import tiny
from polarshape.brdf.quadrature import HALF_PI, ThetaWarp, composite_rule, theta_breaks


def clipped_cos_azimuthal(a: Tensor, b: Tensor) -> Tensor:
    """∫₀^{2π} [a + b cos φ]₊ dφ for a ≥ 0, b ≥ 0 (closed form, finite gradients).

    Equals 2πa when b ≤ a, else 2(a φ_c + √(b² − a²)) with φ_c = atan2(√(b² − a²), −a).
    """
    eps = tiny(a.dtype)
    s = torch.sqrt((b * b - a * a).clamp_min(eps))
    phic = torch.atan2(s, -a)
    return torch.where(b > a, 2.0 * (a * phic + s), 2.0 * math.pi * a)


def _projected_area_on_nodes(theta_w: Tensor, th: Tensor, w: Tensor, alpha: Tensor, beta: Tensor, c: Tensor) -> Tensor:
    """P(θ_ω) for (...) θ_ω with the θ_m rule (th, w) of shape (Q,): returns (...)."""
    tw = theta_w.unsqueeze(-1)
    phi = clipped_cos_azimuthal(torch.cos(tw) * torch.cos(th), torch.sin(tw) * torch.sin(th))
    return c * (phi * (w * torch.sin(th) * d_shape(th, alpha, beta))).sum(-1)


def projected_area_exact(
    theta_w: Tensor, alpha: Tensor, beta: Tensor, c: Tensor, *, rtol: float = 1e-10, max_level: int = 6
) -> Tensor:
    """Reference P(θ_ω) (spec §4) by refined quadrature, differentiable in θ_ω, α, β, c.

    Args:
        theta_w: (...) polar angle of ω from the macro normal, rad, in [0, π/2].
        alpha, beta, c: 0-dim tensors (c from :func:`~polarshape.brdf.distribution.d_normalisation`).
        rtol: relative convergence tolerance between successive refinements.

    Returns:
        (...) projected area P(θ_ω) > 0.
    """
    flat = theta_w.reshape(-1)
    out = []
    for t in flat:
        kink = HALF_PI - float(t.detach())
        breaks = theta_breaks(float(alpha.detach()), float(beta.detach()), max_width=0.05, extra=(kink,))
        prev = None
        for level in range(max_level):
            nodes, weights = composite_rule(breaks, 8 * 2**level)
            th = torch.as_tensor(nodes, dtype=t.dtype, device=t.device)
            w = torch.as_tensor(weights, dtype=t.dtype, device=t.device)
            val = _projected_area_on_nodes(t, th, w, alpha, beta, c)
            if prev is not None and abs(float((val - prev).detach())) <= rtol * abs(float(val.detach())):
                break
            prev = val
        out.append(val)
    return torch.stack(out).reshape(theta_w.shape)


def smith_warp(alpha: float) -> ThetaWarp:
    """θ ↦ grid coordinate for the Smith table: uniform away from grazing, refined within ~α/4 of it."""
    return ThetaWarp.for_alpha(alpha, eps_factor=0.25, layer=0.5 * math.pi)


def interp_uniform(t: Tensor, fp: Tensor) -> Tensor:
    """Linear interpolation of samples fp (G,) at fractional indices t (...) (clamped)."""
    g = fp.numel()
    tc = t.clamp(0.0, g - 1.0)
    i0 = tc.detach().floor().clamp(max=g - 2)
    idx = i0.long().reshape(-1)
    lo = fp.index_select(0, idx).reshape(t.shape)
    hi = fp.index_select(0, idx + 1).reshape(t.shape)
    return torch.lerp(lo, hi, tc - i0)


@dataclass(frozen=True)
class SmithTable:
    """P(θ) tabulated for one (α, β) at the G nodes of ``warp``: ``excess`` (G,) = P(θ) − cos θ ≥ 0.

    The excess (the facets a clipped view still sees beyond the macro-surface's cos θ) is what is
    interpolated; cos θ is added back exactly, so the table is exact wherever no facet is hidden.
    The grid is uniform in the warped coordinate (dense near grazing), so a lookup is an index
    computation, not a search.
    """

    warp: ThetaWarp
    excess: Tensor

    def projected_area(self, theta: Tensor) -> Tensor:
        """Interpolated P(θ) for (...) θ in [0, π/2] (in θ's dtype)."""
        t = theta.clamp(0.0, HALF_PI)
        idx = (self.warp.to_grid(t) + 1.0) * (0.5 * (self.excess.numel() - 1))
        return torch.cos(t) + interp_uniform(idx, self.excess.to(theta.dtype))

    def g1(self, theta: Tensor) -> Tensor:
        """Smith G1(θ) = cos θ / P(θ) for (...) θ (0 beyond π/2)."""
        return torch.cos(theta).clamp_min(0.0) / self.projected_area(theta)


def build_smith_table(
    alpha: Tensor, beta: Tensor, c: Tensor, *, n_grid: int = 513, n: int = 8, layout: tuple[float, float] | None = None
) -> SmithTable:
    """Tabulate P(θ) for the current α, β (differentiable in α, β, c through the values).

    Args:
        alpha, beta, c: 0-dim float64 tensors.
        n_grid: grid points on [0, π/2] (uniform in the warped coordinate of :func:`smith_warp`).
        n: Gauss–Legendre points per θ_m panel.
        layout: (α, β) at which to place grid and nodes (default: the values themselves).
    """
    la, lb = layout if layout is not None else (float(alpha.detach()), float(beta.detach()))
    warp = smith_warp(la)
    grid = torch.as_tensor(warp.nodes(n_grid), dtype=alpha.dtype, device=alpha.device)
    nodes, weights = composite_rule(theta_breaks(la, lb, max_width=0.05), n)
    th = torch.as_tensor(nodes, dtype=alpha.dtype, device=alpha.device)
    w = torch.as_tensor(weights, dtype=alpha.dtype, device=alpha.device)
    area = _projected_area_on_nodes(grid, th, w, alpha, beta, c)
    return SmithTable(warp=warp, excess=area - torch.cos(grid))
