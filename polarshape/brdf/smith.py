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

import numpy as np
import torch
from torch import Tensor

from polarshape.brdf.distribution import d_shape
from polarshape.brdf.geometry import tiny
from polarshape.brdf.quadrature import HALF_PI, composite_rule, theta_breaks


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


def smith_grid(alpha: float, n_uniform: int = 129) -> np.ndarray:
    """θ grid on [0, π/2]: uniform plus geometric refinement within a few α of grazing."""
    geo = HALF_PI - alpha * 2.0 ** (np.arange(-80, 49) / 8.0)
    pts = np.concatenate([np.linspace(0.0, HALF_PI, n_uniform), geo[(geo > 0) & (geo < HALF_PI)]])
    return np.unique(pts)


def interp1d(x: Tensor, xp: Tensor, fp: Tensor) -> Tensor:
    """Piecewise-linear interpolation of (xp, fp) at x (clamped to the grid), differentiable in x and fp.

    Args:
        x: (...) query points.
        xp: (G,) increasing grid.
        fp: (G,) values.
    """
    xc = x.clamp(xp[0], xp[-1])
    idx = torch.searchsorted(xp, xc.detach().contiguous(), right=True).clamp(1, xp.numel() - 1)
    x0 = xp[idx - 1]
    x1 = xp[idx]
    t = (xc - x0) / (x1 - x0)
    return fp[idx - 1] * (1.0 - t) + fp[idx] * t


@dataclass(frozen=True)
class SmithTable:
    """P(θ) tabulated for one (α, β): ``grid`` (G,) rad and ``excess`` (G,) = P(θ) − cos θ ≥ 0.

    The excess (the facets a clipped view still sees beyond the macro-surface's cos θ) is what is
    interpolated; cos θ is added back exactly, so the table is exact wherever no facet is hidden.
    """

    grid: Tensor
    excess: Tensor

    def projected_area(self, theta: Tensor) -> Tensor:
        """Interpolated P(θ) for (...) θ in [0, π/2] (in θ's dtype)."""
        t = theta.clamp(0.0, HALF_PI)
        return torch.cos(t) + interp1d(t, self.grid.to(theta.dtype), self.excess.to(theta.dtype))

    def g1(self, theta: Tensor) -> Tensor:
        """Smith G1(θ) = cos θ / P(θ) for (...) θ (0 beyond π/2)."""
        return torch.cos(theta).clamp_min(0.0) / self.projected_area(theta)


def build_smith_table(
    alpha: Tensor, beta: Tensor, c: Tensor, *, n_uniform: int = 257, n: int = 8, layout: tuple[float, float] | None = None
) -> SmithTable:
    """Tabulate P(θ) for the current α, β (differentiable in α, β, c through the values).

    Args:
        alpha, beta, c: 0-dim float64 tensors.
        n_uniform: uniform grid points on [0, π/2] (plus refinement near grazing).
        n: Gauss–Legendre points per θ_m panel.
        layout: (α, β) at which to place grid and nodes (default: the values themselves).
    """
    la, lb = layout if layout is not None else (float(alpha.detach()), float(beta.detach()))
    grid = torch.as_tensor(smith_grid(la, n_uniform), dtype=alpha.dtype, device=alpha.device)
    nodes, weights = composite_rule(theta_breaks(la, lb, max_width=0.05), n)
    th = torch.as_tensor(nodes, dtype=alpha.dtype, device=alpha.device)
    w = torch.as_tensor(weights, dtype=alpha.dtype, device=alpha.device)
    area = _projected_area_on_nodes(grid, th, w, alpha, beta, c)
    return SmithTable(grid=grid, excess=area - torch.cos(grid))
