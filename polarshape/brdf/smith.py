"""Smith masking–shadowing for the FMBRDF microfacet distribution (spec §4, paper eq. 1, 17).

No closed form exists for D ∝ exp(−(θ/α)^β). We use the exact height-field identity

    1 + Λ(ω) = P(ω) / cos θ_ω,   P(ω) = ∫_Ω [ω·m]₊ D(m) dω_m,   G1(ω) = cos θ_ω / P(ω),

where P is the projected area of the microfacets visible from ω. Its azimuthal integral is closed
form (:func:`clipped_cos_azimuthal`), leaving a 1-D integral over θ_m:

    P(θ_ω) = ∫₀^{π/2} D(θ_m) sin θ_m Φ(cos θ_ω cos θ_m, sin θ_ω sin θ_m) dθ_m.

Two evaluators: :func:`projected_area_exact` (adaptive: the kink θ_m = π/2 − θ_ω is a panel
breakpoint and the rule is refined until converged) and :class:`SmithTable` (P tabulated for the
current α, β on a grid dense near grazing, linearly interpolated; error measured in the tests).
The azimuthal factor Φ of a table depends on its layout alone (grid and θ_m rule), not on α, β:
it is kept for the last few layouts (:func:`clear_smith_cache`), so a fit's finite differences on a
frozen layout rebuild a table as one weighted sum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from polarshape.brdf.cache import BoundedCache
from polarshape.brdf.distribution import d_shape
from polarshape.brdf.geometry import tiny
from polarshape.brdf.quadrature import BLOCK_ELEMENTS, HALF_PI, ThetaWarp, composite_rule, theta_breaks


def clipped_cos_azimuthal(a: Tensor, b: Tensor) -> Tensor:
    """∫₀^{2π} [a + b cos φ]₊ dφ for a ≥ 0, b ≥ 0 (closed form, finite gradients).

    Equals 2πa when b ≤ a, else 2(a φ_c + √(b² − a²)) with φ_c = atan2(√(b² − a²), −a).
    """
    eps = tiny(a.dtype)
    s = torch.sqrt((b * b - a * a).clamp_min(eps))
    phic = torch.atan2(s, -a)
    return torch.where(b > a, 2.0 * (a * phic + s), 2.0 * math.pi * a)


def _azimuthal_on_nodes(theta_w: Tensor, th: Tensor) -> Tensor:
    """Φ(cos θ_ω cos θ_m, sin θ_ω sin θ_m) for (...) θ_ω and the θ_m nodes th (Q,): returns (..., Q)."""
    tw = theta_w.unsqueeze(-1)
    return clipped_cos_azimuthal(torch.cos(tw) * torch.cos(th), torch.sin(tw) * torch.sin(th))


def _projected_area_of(phi: tuple[Tensor, ...], th: Tensor, w: Tensor, alpha: Tensor, beta: Tensor, c: Tensor) -> Tensor:
    """P(θ_ω) from the azimuthal factors of :func:`_azimuthal_on_nodes` in blocks of θ_ω, phi
    ((g, Q), ...) or ((..., Q),), and the θ_m rule (th, w) (Q,): returns (G,) or (...)."""
    wd = w * torch.sin(th) * d_shape(th, alpha, beta)  # (Q,)
    sums = [(p * wd).sum(-1) for p in phi]
    return c * (sums[0] if len(sums) == 1 else torch.cat(sums))


def _projected_area_on_nodes(theta_w: Tensor, th: Tensor, w: Tensor, alpha: Tensor, beta: Tensor, c: Tensor) -> Tensor:
    """P(θ_ω) for (...) θ_ω with the θ_m rule (th, w) of shape (Q,): returns (...)."""
    return _projected_area_of((_azimuthal_on_nodes(theta_w, th),), th, w, alpha, beta, c)


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


@dataclass(frozen=True)
class _SmithLayout:
    """What a Smith table takes from its layout alone: the grid (G,) and its cos, the θ_m rule (Q,), and
    the azimuthal factors Φ (G, Q) (:func:`_azimuthal_on_nodes`) in blocks of grid rows of at most
    :data:`~polarshape.brdf.quadrature.BLOCK_ELEMENTS` elements."""

    warp: ThetaWarp
    cos_grid: Tensor
    th: Tensor
    w: Tensor
    phi: tuple[Tensor, ...]


SMITH_CACHE_ENTRIES = 4

#: The layouts of the last few Smith tables (:func:`build_smith_table`), by everything they depend on:
#: the layout (α, β), the grid size, the nodes per panel, dtype and device — not α, β themselves, not
#: μ. A fit's finite differences in μ, α and β on a frozen layout then cost one weighted sum each.
#: Constants only (no autograd history): Φ depends on no parameter. ≤ 2·513·330 float64 per entry.
_SMITH_CACHE: BoundedCache[_SmithLayout] = BoundedCache(SMITH_CACHE_ENTRIES)


def clear_smith_cache() -> int:
    """Empty the layout cache of :func:`build_smith_table` (its memory back; the tables do not change);
    returns how many entries it held."""
    return _SMITH_CACHE.clear()


def _smith_layout(la: float, lb: float, n_grid: int, n: int, dtype: torch.dtype, device: torch.device) -> _SmithLayout:
    """The :class:`_SmithLayout` of a table placed at (α, β) = (la, lb), from :data:`_SMITH_CACHE` when it has it."""
    key = (la, lb, n_grid, n, dtype, str(device))
    cached = _SMITH_CACHE.get(key)
    if cached is not None:
        return cached
    warp = smith_warp(la)
    grid = torch.as_tensor(warp.nodes(n_grid), dtype=dtype, device=device)
    nodes, weights = composite_rule(theta_breaks(la, lb, max_width=0.05), n)
    th = torch.as_tensor(nodes, dtype=dtype, device=device)
    w = torch.as_tensor(weights, dtype=dtype, device=device)
    rows = max(1, BLOCK_ELEMENTS // th.numel())
    phi = tuple(_azimuthal_on_nodes(grid[g0 : g0 + rows], th) for g0 in range(0, grid.numel(), rows))
    return _SMITH_CACHE.put(key, _SmithLayout(warp=warp, cos_grid=torch.cos(grid), th=th, w=w, phi=phi))


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
    lay = _smith_layout(la, lb, n_grid, n, alpha.dtype, alpha.device)
    area = _projected_area_of(lay.phi, lay.th, lay.w, alpha, beta, c)
    return SmithTable(warp=lay.warp, excess=area - lay.cos_grid)
