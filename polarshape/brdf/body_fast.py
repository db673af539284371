"""Fast, differentiable body (diffuse) reflection of the FMBRDF via per-material tables (spec §7).

The body term (paper eq. 13–22, 24) is

    s_b = (k_b/π) · G1(L) G1(V)/(N·V) · J(V, L),
    J   = ∫_Ω∫_Ω [n·V]₊ D(n) T-Stokes(θ_o, ψ(n)) · f(n, n_i) · [n_i·L]₊ D(n_i) T+(θ_i) dω_n dω_{n_i},
    f   = exp(κ n·n_i) / Z(n_i),   Z(n_i) = ∫_Ω exp(κ n·n_i) D(n) dω_n        (eq. 19–21)

With G1(ω) = cos θ_ω / P(ω) (spec §4) this is s_b = (k_b/π)(N·L)·W with the bounded, smooth

    W(θ_V, θ_L, Δφ) = J / (P(V) P(L)),

a function of three angles only (D is isotropic): the polar angles of V and L from N and their
azimuth difference. We tabulate W for the current (μ, α, β, κ) and interpolate it trilinearly.

Building the table (all torch, so W is differentiable in μ, α, β, κ):
- polar angles θ of the facets: a composite Gauss–Legendre rule graded to α
  (:mod:`polarshape.brdf.quadrature`); azimuths: Gauss–Legendre on the arc where n·ω > 0, whose
  ends are known in closed form, so the [·]₊ clipping of masking/shadowing is integrated exactly;
  at κ > 0 the facet side's azimuthal modes (:class:`ArcFourier`) are taken on the φ ≥ 0 half of
  each arc (:func:`fold_arc_rule`: its integrands are even or odd in φ);
- the correlation kernel exp(κ(n·n_i − 1)) = Σ_m k_m(θ, θ') cos m(φ − φ') (Fourier series in the
  azimuth difference; the coefficients are modified Bessel functions, computed as the cosine
  series of P samples in ψ, half of them by evenness and half the (θ, θ') pairs by symmetry:
  :func:`kernel_cosine_rule`), which turns the 4-D integral into, for each m, a product of small matrices
  A_m = H_m(θ_V) · k_m · G_m(θ_L)ᵀ — the route of spec §7 with a Fourier rather than a spherical-
  harmonic expansion. κ = 0 keeps only m = 0 (the separable case);
- J(θ_V, θ_L, Δφ) = Σ_m A_m cos mΔφ (intensity and s1), Σ_m A_m sin mΔφ (s2).

Polarisation is tabulated in a frame attached to the geometry, e'_x = normalise(N − (N·V)V) (the
projection of N), and rotated into the pixel frame at evaluation; the body AoLP is thus ∥ to the
plane of N and V where the exit transmission dominates (spec §5, §7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from polarshape.brdf.cache import BoundedCache
from polarshape.brdf.distribution import d_shape
from polarshape.brdf.fresnel import fresnel
from polarshape.brdf.geometry import (
    ShadingGeometry,
    Vec3,
    cross3,
    dot3,
    double_angle_of,
    rotate_linear_stokes,
    safe_atan2,
    safe_normalize3,
    shading_geometry,
    tiny,
)
from polarshape.brdf.quadrature import BLOCK_ELEMENTS, ThetaWarp, gauss_legendre, theta_cutoff, theta_rule
from polarshape.brdf.smith import interp_uniform


@dataclass(frozen=True)
class BodyTable:
    """W = J / (P(V) P(L)) of one material on a regular grid.

    Attributes:
        values: (G, G, F, 3) float64, channels last: (log W0, WQ/W0, WU/W0) over θ_V (G), θ_L (G),
            Δφ ∈ [0, π] (F).
            The polar angles are sampled uniformly in the warped coordinate of :class:`ThetaWarp`
            (dense near grazing). WQ, WU are in the frame e'_x = projection of N (see module doc);
            WU is odd in Δφ and stored for Δφ ≥ 0. The logarithm and the ratios are what vary
            slowly (W0 changes by orders of magnitude with Δφ at large κ), so they are what is
            interpolated.
        warp: the θ ↦ grid-coordinate map.
        n_modes: number of azimuthal Fourier modes used (1 = separable, κ = 0).
    """

    values: Tensor
    warp: ThetaWarp
    n_modes: int
    #: per-dtype lookup tables derived from ``values`` (:func:`body_parts`), kept while ``values``
    #: carries no autograd history (then they are constants of the material)
    cache: dict = field(default_factory=dict, compare=False, repr=False)


def arc_nodes(theta: np.ndarray, theta_w: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre azimuth nodes on the arc where a facet at polar angle θ sees direction ω.

    For ω at polar angle θ_ω and azimuth 0, n·ω = sin θ sin θ_ω cos φ + cos θ cos θ_ω > 0 exactly on
    |φ| < φ_c = arccos(−cot θ cot θ_ω) (the whole circle when that is ≤ −1).

    Args:
        theta: (Q,) facet polar angles; theta_w: (G,) polar angles of ω; n: nodes per arc.

    Returns:
        phi, weights: (G, Q, n) each.
    """
    x, w = gauss_legendre(n)
    phic = arc_half_width(theta, theta_w)
    return phic[..., None] * x, phic[..., None] * w


def arc_half_width(theta: np.ndarray, theta_w: np.ndarray) -> np.ndarray:
    """φ_c of :func:`arc_nodes`: (Q,) facet polar angles θ, (G,) polar angles θ_ω -> (G, Q) in (0, π]."""
    st, ct = np.sin(theta)[None, :], np.cos(theta)[None, :]
    sw, cw = np.sin(theta_w)[:, None], np.cos(theta_w)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (ct * cw) / (st * sw)
    full = ~(r < 1.0)  # includes r = inf / nan (θ or θ_ω = 0)
    return np.where(full, math.pi, np.arccos(-np.clip(np.nan_to_num(r, nan=1.0, posinf=1.0), -1.0, 1.0)))


def fold_arc_rule(phi: np.ndarray, wphi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The half (φ ≥ 0) of symmetric arc rules, for integrands even or odd in φ.

    The Gauss–Legendre nodes of :func:`arc_nodes` are exactly symmetric (x_{n−1−i} = −x_i, equal
    weights, x = 0 for odd n), so Σ_n f(φ_n) w_n = Σ_{φ_n ≥ 0} f(φ_n) w'_n with w' = 2w for φ > 0
    (w for the node φ = 0) when f is even, and Σ_n f(φ_n) cos(mφ_n) w_n, Σ_n f(φ_n) sin(mφ_n) w_n
    likewise for f even, resp. odd: the same sums on half the nodes (spec §7's facet side is even in φ
    for intensity and s1, odd for s2).

    Args:
        phi, wphi: (..., n) rules of :func:`arc_nodes`.

    Returns:
        phi, weights: (..., ⌈n/2⌉) each, φ ≥ 0.
    """
    n = phi.shape[-1]
    half = np.full(n - n // 2, 2.0)
    if n % 2:
        half[0] = 1.0  # the node φ = 0 is its own mirror
    return phi[..., n // 2 :], wphi[..., n // 2 :] * half


class ArcFourier(torch.autograd.Function):
    """Azimuthal Fourier coefficients on the arc rules: for m = 0..M−1,
    even[c, m] = Σ_n h_even[c, ..., n] cos(m φ_n) and odd[m] = Σ_n h_odd[..., n] sin(m φ_n).

    cos mφ and sin mφ come from the Chebyshev recurrence x_{m+1} = 2 cos φ · x_m − x_{m−1} (both obey
    it), one mode at a time on the flattened (arc pairs, nodes) arrays, each mode's sums taken as it is
    made: two trigonometric evaluations per node instead of 2M, and no (pairs, nodes, M) block. At the
    κ 50, α 0.8 layout (M 41; 40 rows × 100 facet nodes × 33 arc nodes) 2.6× faster than the
    direct cos, sin of a (pairs, nodes, M) block with batched products, to 7e-15 of the largest
    coefficient (the recurrence's rounding grows as m²·eps: ≤ 3e-12 at the cap M = 160). The backward
    pass is the same sums transposed (the modes are recomputed, not stored).
    """

    @staticmethod
    def _modes(phi: Tensor, n_modes: int):  # noqa: ANN205
        """(m, cos mφ, sin mφ) for m = 0..M−1, each (P, n) over the flattened arc pairs of ``phi``."""
        flat = phi.reshape(-1, phi.shape[-1])  # (P, n)
        c_prev, s_prev = torch.ones_like(flat), torch.zeros_like(flat)
        yield 0, c_prev, s_prev
        if n_modes < 2:
            return
        c, s = torch.cos(flat), torch.sin(flat)
        yield 1, c, s
        two_cos = 2.0 * c
        for m in range(2, n_modes):
            c_prev, c = c, torch.addcmul(-c_prev, two_cos, c)  # cos mφ = 2 cos φ cos (m−1)φ − cos (m−2)φ
            s_prev, s = s, torch.addcmul(-s_prev, two_cos, s)  # sin likewise
            yield m, c, s

    @staticmethod
    def forward(ctx, h_even: Tensor, h_odd: Tensor, phi: Tensor, n_modes: int) -> tuple[Tensor, Tensor]:  # noqa: ANN001
        ctx.save_for_backward(phi)
        ctx.n_modes = n_modes
        if n_modes == 1:  # κ = 0: only m = 0 (cos 0 = 1, sin 0 = 0), no trigonometry needed
            return h_even.sum(-1).unsqueeze(1), torch.zeros_like(h_odd[..., 0]).unsqueeze(0)
        n_c, pairs = h_even.shape[0], phi.shape[:-1]
        he, ho = h_even.reshape(n_c, -1, phi.shape[-1]), h_odd.reshape(-1, phi.shape[-1])  # (C, P, n), (P, n)
        even = phi.new_empty((n_c, n_modes, he.shape[1]))
        odd = phi.new_empty((n_modes, he.shape[1]))
        for m, cos_m, sin_m in ArcFourier._modes(phi, n_modes):
            even[:, m] = (he * cos_m).sum(-1)
            odd[m] = (ho * sin_m).sum(-1)
        return even.reshape(n_c, n_modes, *pairs), odd.reshape(n_modes, *pairs)

    @staticmethod
    def backward(ctx, g_even: Tensor, g_odd: Tensor):  # noqa: ANN001, ANN205
        (phi,) = ctx.saved_tensors
        if ctx.n_modes == 1:
            d_even = g_even[:, 0].unsqueeze(-1).expand(g_even.shape[0], *phi.shape).contiguous()
            return d_even, torch.zeros_like(phi), None, None
        n_c, n = g_even.shape[0], phi.shape[-1]
        ge, go = g_even.reshape(n_c, ctx.n_modes, -1, 1), g_odd.reshape(ctx.n_modes, -1, 1)  # (C, M, P, 1), (M, P, 1)
        d_even = phi.new_zeros((n_c, ge.shape[2], n))
        d_odd = phi.new_zeros((ge.shape[2], n))
        for m, cos_m, sin_m in ArcFourier._modes(phi, ctx.n_modes):
            d_even.addcmul_(ge[:, m], cos_m)
            d_odd.addcmul_(go[m], sin_m)
        return d_even.reshape(n_c, *phi.shape), d_odd.reshape(phi.shape), None, None


def n_fourier_modes(kappa: float, alpha: float, beta: float, *, log_tol: float = 14.0, cap: int = 160) -> int:
    """Azimuthal modes needed for exp(κ(n·n_i − 1)): the m-th coefficient is e^{−κ(1−cc')} I_m(κ s s'),
    which decays like exp(−m²/(2κ s s')), with s, s' ≤ sin θ_cut. Returns M + 1 (m = 0..M)."""
    if kappa <= 0.0:
        return 1
    z = kappa * math.sin(theta_cutoff(alpha, beta)) ** 2
    return min(cap, int(math.ceil(math.sqrt(2.0 * z * log_tol))) + 3)


def _facet_frame(sq: Tensor, cq: Tensor, tg: Tensor, phi: Tensor, wphi: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The exit geometry of the facets at the arc nodes of some rows of the θ grid, with
    ω = (sin θ_g, 0, cos θ_g): [n·ω]₊, the arc weight × [n·ω]₊, and the facet normal's components
    (ax, n_y) in the frame e'_x = (−cos θ_g, 0, sin θ_g), e'_y = (0, 1, 0) (the projection of N).
    It depends on the layout alone (not on μ, α, β, κ).

    Args:
        sq, cq: (Q,) sin θ, cos θ of the facet nodes.
        tg: (g,) polar angles of ω (rows of the grid); phi, wphi: (g, Q, n) their arc rules.

    Returns:
        cos_o, base, ax, n_y: each (g, Q, n).
    """
    sg, cg = torch.sin(tg)[:, None, None], torch.cos(tg)[:, None, None]
    n_x, n_y, n_z = sq[None, :, None] * torch.cos(phi), sq[None, :, None] * torch.sin(phi), cq[None, :, None]
    cos_o = (n_x * sg + n_z * cg).clamp_min(0.0)  # n·ω
    ax = -n_x * cg + n_z * sg
    return cos_o, wphi * cos_o, ax, n_y  # base = arc weight × [n·ω]₊


def _facet_modes(
    sq: Tensor, cq: Tensor, tg: Tensor, phi: Tensor, wphi: Tensor, ior: Tensor, n_modes: int
) -> tuple[Tensor, Tensor]:
    """The facet side of J for some rows of the θ grid, before the factor bq = θ weight × sin θ ×
    D(θ) of each facet node (so that it depends on μ and the layout only, not on α, β, κ): azimuthal
    Fourier modes of the exit (and, with the same integrand, entry) weights, and the arc sums of
    the projected areas. (κ = 0, one mode, takes :func:`_separable_modes`.)

    Args:
        sq, cq: (Q,) sin θ, cos θ of the facet nodes.
        tg: (g,) polar angles of ω (rows of the grid); phi, wphi: (g, Q, n) their arc rules.
        ior: μ. n_modes: M.

    Returns:
        h_modes (3, M, g, Q) (intensity, s1 cosine modes; s2 sine modes), area_q (g, Q) with
        P(θ_g) = Σ_Q area_q · bq.
    """
    cos_o, base, ax, n_y = _facet_frame(sq, cq, tg, phi, wphi)
    fr = fresnel(cos_o, ior)  # spec §5 transmission at θ_o
    r2 = (ax * ax + n_y * n_y).clamp_min(tiny(phi.dtype))
    area_q = base.sum(-1)  # (g, Q)
    cos2, sin2 = (ax * ax - n_y * n_y) / r2, 2.0 * ax * n_y / r2
    h = torch.stack([base * fr.t_plus, base * (-fr.t_minus) * cos2, base * (-fr.t_minus) * sin2])  # (3,g,Q,n)
    # intensity and s1 are even in φ (cosine modes), s2 odd (sine modes)
    h_even, h_odd = ArcFourier.apply(h[:2], h[2], phi, n_modes)  # (2, M, g, Q), (M, g, Q)
    return torch.cat([h_even, h_odd.unsqueeze(0)]), area_q


@dataclass(frozen=True)
class _SeparableGeometry:
    """What the κ = 0 facet side takes from the layout alone (not μ): :func:`_facet_frame` on every
    row of the θ grid, in blocks of rows of at most :data:`~polarshape.brdf.quadrature.BLOCK_ELEMENTS`
    elements at the arc nodes of φ ≥ 0 (temporaries that stay in cache).

    Attributes:
        blocks: per block of rows (r,): cos_o_half (r, Q, n − n//2) = [n·ω]₊ at the arc nodes of
            φ ≥ 0, base (r, Q, n) = arc weight × [n·ω]₊, cos2 (r, Q, n) = cos 2ψ of the facet
            normal in the frame of the projection of N. The arc rules are symmetric (φ_i =
            −φ_{n−1−i}, equal weights; :func:`arc_nodes`) and n·ω is even in φ, so cos_o_half holds
            every distinct exit angle: Fresnel is evaluated there and mirrored (:func:`_mirrored`; so
            are base and cos2, which are even in φ too, when they are made).
        odd: n mod 2 (an odd rule's middle node, φ = 0, is its own mirror image).
        area_q: (G, Q) arc sums of base: P(θ_g) = Σ_Q area_q · bq.
    """

    blocks: tuple[tuple[Tensor, Tensor, Tensor], ...]
    odd: int
    area_q: Tensor

    def numel(self) -> int:
        return sum(t.numel() for block in self.blocks for t in block)


def _mirrored(half: Tensor, odd: int) -> Tensor:
    """(..., n − n//2) values at the arc nodes of φ ≥ 0 -> (..., n) at all n nodes of the symmetric arc
    rule (φ_i = −φ_{n−1−i}) of a function even in φ; ``odd`` = n mod 2."""
    return torch.cat([half[..., odd:].flip(-1), half], dim=-1)


#: The largest entry of the facet, geometry and kernel caches below (elements).
FACET_CACHE_MAX_ELEMENTS = 1 << 21
#: Entries of each cache below.
GEOMETRY_CACHE_ENTRIES, FACET_CACHE_ENTRIES, KERNEL_CACHE_ENTRIES = 4, 4, 2

#: The κ = 0 facet geometry (:class:`_SeparableGeometry`) of the last few layouts, by everything it
#: depends on: the layout (α, β, κ that place the nodes), the rules, dtype and device — not μ, not
#: α, β themselves. A μ change on a frozen layout (a fit's μ difference; the next iteration's
#: differences at an accepted trial point) then costs Fresnel on the distinct exit angles and two
#: weighted sums. Constants only (no autograd history), so kept whether or not μ requires grad;
#: ≈ 2.5·G·Q·n elements (κ = 0: 4–7 MB in float64) and at most
#: :data:`FACET_CACHE_MAX_ELEMENTS` each. Emptied by :func:`clear_facet_cache`.
_GEOMETRY_CACHE: BoundedCache[_SeparableGeometry] = BoundedCache(GEOMETRY_CACHE_ENTRIES, FACET_CACHE_MAX_ELEMENTS)


def _separable_geometry(key: tuple, sq: Tensor, cq: Tensor, tg: Tensor, tq_np: np.ndarray, tg_np: np.ndarray,
                        n: int, rows: int) -> _SeparableGeometry:
    """The :class:`_SeparableGeometry` of a layout (``key``; facet nodes tq_np (Q,), grid tg_np (G,), n arc
    nodes), from :data:`_GEOMETRY_CACHE` when it has it; blocks of at most ``rows`` rows."""
    cached = _GEOMETRY_CACHE.get(key)
    if cached is not None:
        return cached
    half = n // 2
    x, w = (torch.tensor(v[half:], dtype=sq.dtype, device=sq.device) for v in gauss_legendre(n))  # φ ≥ 0 (a copy: read-only)
    phic = torch.as_tensor(arc_half_width(tq_np, tg_np), dtype=sq.dtype, device=sq.device)[..., None]  # (G, Q, 1)
    rows = max(1, min(rows, BLOCK_ELEMENTS // (sq.numel() * (n - half))))
    blocks, areas = [], []
    for g0 in range(0, tg.numel(), rows):
        pc = phic[g0 : g0 + rows]
        cos_o, base, ax, n_y = _facet_frame(sq, cq, tg[g0 : g0 + rows], pc * x, pc * w)  # :func:`arc_nodes`' φ ≥ 0
        base = _mirrored(base, n % 2)
        blocks.append((cos_o, base, _mirrored(double_angle_of(ax, n_y)[0], n % 2)))
        areas.append(base.sum(-1))
    geo = _SeparableGeometry(tuple(blocks), n % 2, torch.cat(areas))
    return _GEOMETRY_CACHE.put(key, geo, geo.numel())


def _separable_modes(geo: _SeparableGeometry, ior: Tensor) -> Tensor:
    """:func:`_facet_modes` of κ = 0 on every row: only m = 0, the arc sums of intensity and s1 (the s2
    sine mode is 0) — ArcFourier's separable case without its (3, G, Q, n) stack. Returns h_modes
    (3, 1, G, Q)."""
    parts = []
    for cos_o_half, base, cos2 in geo.blocks:
        fr = fresnel(cos_o_half, ior)  # spec §5 transmission at θ_o, on the distinct exit angles
        t_plus, r_minus = _mirrored(fr.t_plus, geo.odd), _mirrored(fr.r_minus, geo.odd)  # T+, −T−
        parts.append(torch.stack([(base * t_plus).sum(-1), (base * r_minus * cos2).sum(-1)]))
    even = torch.cat(parts, dim=1)  # (2, G, Q)
    return torch.cat([even.unsqueeze(1), torch.zeros_like(even[:1]).unsqueeze(1)])


#: The facet sides of the last few table builds (:func:`_facet_side`), by what they depend on: μ, the
#: layout (α, β, κ that place the nodes and set the mode count), the rules, dtype and device — not
#: α, β, κ themselves. A fit's finite differences in α, β (and κ) on a frozen layout then rebuild
#: only the cheap rest of the table (bq, the kernel, the products): 60–80 % of a κ = 0 build is
#: the facet side. Only μ without autograd history is cached, and only sides of at most
#: :data:`FACET_CACHE_MAX_ELEMENTS` elements (3·M·G·Q: κ = 0 3·65·Q; at G = 65, Q ≤ 156 up to
#: M = 68 modes, κ ≈ 150 at α ≥ 0.3: the κ 50 layouts, 1.2 M elements = 10 MB, are kept).
_FACET_CACHE: BoundedCache[tuple[Tensor, Tensor]] = BoundedCache(FACET_CACHE_ENTRIES, FACET_CACHE_MAX_ELEMENTS)


#: The correlation kernels k_m (M, Q, Q) of the last few κ > 0 builds (:func:`_kernel_side`), by κ's
#: value and what places the θ nodes: a fit's finite differences in μ, α, β leave κ, and so the kernel,
#: unchanged (at κ 100 it is half of such a build). Only κ without autograd history is cached, and
#: only kernels of at most :data:`FACET_CACHE_MAX_ELEMENTS` elements (κ 100, α 0.3: 56·156² = 1.4 M).
_KERNEL_CACHE: BoundedCache[Tensor] = BoundedCache(KERNEL_CACHE_ENTRIES, FACET_CACHE_MAX_ELEMENTS)


def clear_facet_cache() -> int:
    """Empty the facet-side caches of :func:`build_body_table` (:data:`_FACET_CACHE` and the κ = 0
    geometry, :data:`_GEOMETRY_CACHE`) and the κ > 0 kernels (:data:`_KERNEL_CACHE`): their memory
    back; the tables do not change. Returns how many entries they held."""
    return _FACET_CACHE.clear() + _GEOMETRY_CACHE.clear() + _KERNEL_CACHE.clear()


def _facet_side(key: tuple, sq: Tensor, cq: Tensor, tg: Tensor, tq_np: np.ndarray, tg_np: np.ndarray, n_phi: int,
                ior: Tensor, n_modes: int, rows: int) -> tuple[Tensor, Tensor]:
    """:func:`_facet_modes` of every row of the θ grid, ``rows`` at a time: h_modes (3, M, G, Q),
    area_q (G, Q); from :data:`_FACET_CACHE` when it has ``key`` and μ carries no autograd history.
    tq_np (Q,), tg_np (G,): the facet nodes and the grid; n_phi: nodes per arc (:func:`arc_nodes`)."""
    cacheable = not ior.requires_grad
    cached = _FACET_CACHE.get(key) if cacheable else None
    if cached is not None:
        return cached

    if n_modes == 1:  # κ = 0: the geometry (by layout: the key without μ) and Fresnel
        geo = _separable_geometry(key[1:], sq, cq, tg, tq_np, tg_np, n_phi, rows)
        side = _separable_modes(geo, ior), geo.area_q
    else:
        # κ > 0: the modes on the φ ≥ 0 half of the arcs (the integrands are even or odd in φ)
        phi_np, wphi_np = fold_arc_rule(*arc_nodes(tq_np, tg_np, n_phi))  # (G, Q, ⌈n/2⌉)

        def T(x: np.ndarray) -> Tensor:
            return torch.as_tensor(x, dtype=sq.dtype, device=sq.device)

        parts = [
            _facet_modes(sq, cq, tg[g0 : g0 + rows], T(phi_np[g0 : g0 + rows]), T(wphi_np[g0 : g0 + rows]), ior, n_modes)
            for g0 in range(0, tg.numel(), rows)
        ]
        side = torch.cat([hm for hm, _ in parts], dim=2), torch.cat([ar for _, ar in parts])
    return _FACET_CACHE.put(key, side, side[0].numel()) if cacheable else side


def kernel_cosine_rule(
    n_modes: int, n_psi: int, dtype: torch.dtype, device: torch.device | str
) -> tuple[Tensor, Tensor]:
    """The half-period samples and cosine-series matrix of :func:`_kernel_modes`.

    A function f(ψ) even in ψ, sampled at ψ_k = 2πk/P (k = 0..P−1, P even), has the cosine series
    f = Σ_m a_m cos mψ with a_0 = Re F_0/P, a_m = 2 Re F_m/P (F = DFT of the samples), and by
    evenness Re F_m = Σ_{k=0}^{P/2} w_k f(ψ_k) cos(mψ_k) with w = (1, 2, …, 2, 1): half the samples and
    one real matrix product (forward and backward) instead of a complex FFT.

    Args:
        n_modes: M; n_psi: P (even).

    Returns:
        cos_psi: (P/2 + 1,) cos ψ_k; basis: (P/2 + 1, M) with a = f(ψ_k) @ basis.
    """
    k = torch.arange(n_psi // 2 + 1, dtype=dtype, device=device)
    cos_psi = torch.cos(k * (2.0 * math.pi / n_psi))
    m = torch.arange(n_modes, dtype=dtype, device=device)
    w = torch.where((k == 0) | (k == n_psi // 2), 1.0, 2.0)[:, None] * torch.where(m == 0, 1.0, 2.0)  # (P/2+1, M)
    # cos(2π (m k mod P)/P): the angle reduced exactly, so every entry is as accurate as cos ψ_k itself
    basis = w * torch.cos(torch.remainder(k[:, None] * m, n_psi) * (2.0 * math.pi / n_psi)) / n_psi
    return cos_psi, basis


def _kernel_modes(cq_rows: Tensor, sq_rows: Tensor, cq: Tensor, sq: Tensor, cos_psi: Tensor, basis: Tensor,
                  kappa: Tensor) -> Tensor:
    """(M, q, Q) cosine-series coefficients of exp(κ(n·n_i − 1)) in φ − φ' for the facet rows (q,)
    against the nodes (Q,), from the half-period azimuths cos ψ (P/2 + 1,) and the matrix ``basis``
    (P/2 + 1, M) of :func:`kernel_cosine_rule` (the kernel is even in ψ); modes first, the layout of
    the products that use them."""
    arg = (cq_rows[:, None] * cq[None, :] - 1.0).unsqueeze(-1) + (sq_rows[:, None] * sq[None, :]).unsqueeze(-1) * cos_psi
    samples = torch.exp(kappa * arg).reshape(-1, cos_psi.numel())  # (q·Q, P/2 + 1)
    return torch.matmul(basis.t(), samples.t()).reshape(basis.shape[1], cq_rows.numel(), cq.numel())


def _symmetric_rows(parts: list[Tensor]) -> Tensor:
    """A symmetric (..., Q, Q) array from its upper blocks: ``parts[k]`` (..., q_k, Q − r_k) holds rows
    r_k .. r_k + q_k − 1 from column r_k on (r_k = q_0 + … + q_{k−1}); the columns left of r_k are the
    transposes of the earlier parts' rows. The kernel's exp(κ(cos θ cos θ' + sin θ sin θ' cos ψ − 1))
    is symmetric in θ, θ' to the last bit (products commute), so half of it is computed."""
    starts = [0]
    for part in parts:
        starts.append(starts[-1] + part.shape[-2])
    rows = []
    for k, part in enumerate(parts):
        r0, r1 = starts[k], starts[k + 1]
        left = [parts[j][..., r0 - starts[j] : r1 - starts[j]].transpose(-1, -2) for j in range(k)]
        rows.append(torch.cat([*left, part], dim=-1))
    return torch.cat(rows, dim=-2)


def _kernel_side(key: tuple, cq: Tensor, sq: Tensor, kappa: Tensor, n_modes: int, chunk_elements: int) -> Tensor:
    """(M, Q, Q) modes of the correlation kernel, exp(κ(n·n_i−1)) = Σ k_m cos m(φ−φ'), θ rows a few at a
    time (each from its diagonal on: :func:`_symmetric_rows`); from :data:`_KERNEL_CACHE` when it has
    ``key`` and κ carries no autograd history."""
    cacheable = not kappa.requires_grad
    cached = _KERNEL_CACHE.get(key) if cacheable else None
    if cached is not None:
        return cached
    cos_psi, basis = kernel_cosine_rule(n_modes, 2 * n_modes + 64, cq.dtype, cq.device)  # (P/2+1,), (P/2+1, M)
    n_q = cq.numel()
    q_rows = max(1, chunk_elements // (n_q * cos_psi.numel()))
    k_m = _symmetric_rows([
        _kernel_modes(cq[q0 : q0 + q_rows], sq[q0 : q0 + q_rows], cq[q0:], sq[q0:], cos_psi, basis, kappa)
        for q0 in range(0, n_q, q_rows)
    ])
    return _KERNEL_CACHE.put(key, k_m, k_m.numel()) if cacheable else k_m


def build_body_table(
    ior: Tensor,
    alpha: Tensor,
    beta: Tensor,
    kappa: Tensor,
    c: Tensor,
    *,
    n_grid: int = 65,
    n_dphi: int | None = None,
    n_theta: int = 6,
    max_width: float = 0.1,
    log_tol: float = 14.0,
    layout: tuple[float, float, float] | None = None,
    chunk_elements: int = 1 << 18,
) -> BodyTable:
    """Tabulate W(θ_V, θ_L, Δφ) for one material (differentiable in μ, α, β, κ, c).

    Args:
        ior, alpha, beta, kappa, c: 0-dim float64 tensors (c = D's normalisation, eq. 5).
        n_grid: grid points in θ_V and θ_L over [0, π/2].
        n_dphi: grid points in Δφ over [0, π]; default: 2 when κ = 0 (W does not depend on Δφ:
            the separable case), 129 for weak and 257 for strong correlation (W0 then varies by
            orders of magnitude with Δφ).
        n_theta: Gauss–Legendre points per θ panel; max_width: widest θ panel (rad).
        log_tol: Fourier modes of the correlation kernel are kept down to e^−log_tol of the first.
        layout: (α, β, κ) at which to place nodes, grid warp and mode count (default: the values
            themselves). A fixed layout makes the table a smooth function of the parameters with a
            fixed discretisation (for gradient checks and consistent line searches).
        chunk_elements: the facet integrals are computed for as many θ_V rows (and the kernel for as
            many θ rows) at a time as keep each temporary under this many elements (2¹⁸: 2 MB in
            float64), so memory stays small at any κ; the table does not depend on it.

    Returns:
        :class:`BodyTable`.
    """
    dev, dt = alpha.device, alpha.dtype
    a, b, kap = layout if layout is not None else (float(alpha.detach()), float(beta.detach()), float(kappa.detach()))
    tq_np, wq_np = theta_rule(a, b, n_theta, max_width=max_width)
    n_modes = n_fourier_modes(kap, a, b, log_tol=log_tol)
    if kappa.requires_grad:
        n_modes = max(n_modes, 3)  # ∂/∂κ at κ = 0 needs the m = 0, 1 modes: no separable shortcut
    n_phi = max(32, n_modes + 24)
    if n_dphi is None:
        n_dphi = 2 if n_modes == 1 else (129 if n_modes <= 20 else 257)
    warp = ThetaWarp.for_alpha(a)
    tg_np = warp.nodes(n_grid)

    def T(x: np.ndarray) -> Tensor:
        return torch.as_tensor(x, dtype=dt, device=dev)

    tq, wq, tg = T(tq_np), T(wq_np), T(tg_np)
    sq, cq = torch.sin(tq), torch.cos(tq)
    bq = wq * sq * c * d_shape(tq, alpha, beta)  # θ weight × sin θ × D(θ)   (Q,)
    n_q = tq.numel()
    # the rows of the θ grid are independent: a few at a time keep the (rows, Q, n) temporaries small
    rows = max(1, chunk_elements // (n_q * n_phi))
    key = (float(ior.detach()), a, b, kap, n_grid, n_theta, max_width, n_modes, n_phi, rows, dt, str(dev))
    h_raw, area_q = _facet_side(key, sq, cq, tg, tq_np, tg_np, n_phi, ior, n_modes, rows)
    h_modes = h_raw * bq  # (3, M, G, Q)
    area = (area_q * bq).sum(-1)  # P(θ_g) (spec §4)   (G,)

    m = torch.arange(n_modes, dtype=dt, device=dev)
    if n_modes == 1:
        k_m = torch.ones(1, n_q, n_q, dtype=dt, device=dev)
    else:
        kernel_key = (float(kappa.detach()), a, b, n_theta, max_width, n_modes, chunk_elements, dt, str(dev))
        k_m = _kernel_side(kernel_key, cq, sq, kappa, n_modes, chunk_elements)  # (M, Q, Q)
    z = 2.0 * math.pi * (bq[:, None] * k_m[0]).sum(0)  # Z(θ') of eq. 20   (Q,)
    g_modes = h_modes[0] / z  # entry side: [n_i·L]₊ D T+(θ_i) / Z   (M, G, Q)
    inner = torch.matmul(k_m, g_modes.transpose(1, 2))  # (M, Q, G)
    amp = torch.matmul(h_modes, inner)  # (3, M, G_V, G_L)

    dphi = torch.linspace(0.0, math.pi, n_dphi, dtype=dt, device=dev)
    md = m[:, None] * dphi  # (M, F)
    # three (G, G, F) tensors, not one stacked: indexing a stack would cost a full-size zero fill per
    # channel in the backward pass
    j0 = torch.einsum("mgh,mf->ghf", amp[0], torch.cos(md))
    j1 = torch.einsum("mgh,mf->ghf", amp[1], torch.cos(md))
    j2 = torch.einsum("mgh,mf->ghf", amp[2], torch.sin(md))
    w0 = (j0 / (area[:, None, None] * area[None, :, None])).clamp_min(1e-300)
    j0c = j0.clamp_min(1e-300)
    values = torch.stack([torch.log(w0), j1 / j0c, j2 / j0c], dim=-1)
    return BodyTable(values=values.contiguous(), warp=warp, n_modes=n_modes)


def _corner(x: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Lower grid index (long) and fraction of fractional indices x (...) along an axis of ``size``
    (clamped to the axis; the last cell takes x = size − 1)."""
    xc = x.clamp(0.0, size - 1.0)
    x0 = xc.detach().floor().clamp(max=max(size - 2, 0))
    return x0.long(), xc - x0


def _trilinear_flat(channels: tuple[Tensor, ...], sizes: tuple[int, int, int], i: Tensor, j: Tensor, k: Tensor) -> list[Tensor]:
    """Trilinear interpolation of a table stored as one flat (A·B·C,) tensor per channel.

    The eight corners of every sample are gathered with one ``index_select`` per channel and
    combined by three ``lerp`` calls over (2, 2, 2, ...) blocks (contiguous along the samples).

    Args:
        channels: K tensors (A·B·C,), row-major over (A, B, C).
        sizes: (A, B, C).
        i, j, k: broadcastable (...) fractional indices along A, B, C (clamped to the table).

    Returns:
        K tensors (...) (the broadcast shape), differentiable in the indices and the table.
    """
    a, b, c = sizes
    (i0, fi), (j0, fj), (k0, fk) = _corner(i, a), _corner(j, b), _corner(k, c)
    base = (i0 * b + j0) * c + k0
    shape = base.shape
    si, sj, sk = (b * c if a > 1 else 0), (c if b > 1 else 0), (1 if c > 1 else 0)
    corner = torch.arange(8, device=base.device)  # (di, dj, dk) = its binary digits; made on the device (no copy)
    offsets = ((corner // 4) * si + (corner // 2 % 2) * sj + (corner % 2) * sk).reshape(8, *([1] * base.dim()))
    idx = (base.unsqueeze(0) + offsets).reshape(-1)  # (8·N,)
    out = []
    for ch in channels:
        g = ch.index_select(0, idx).reshape(2, 2, 2, *shape)  # (di, dj, dk, ...)
        g = torch.lerp(g[:, :, 0], g[:, :, 1], fk)  # along Δφ
        g = torch.lerp(g[:, 0], g[:, 1], fj)  # along θ_L
        out.append(torch.lerp(g[0], g[1], fi))  # along θ_V
    return out


def _lookup(table: BodyTable, dtype: torch.dtype) -> tuple[Tensor, ...]:
    """The tables :func:`body_parts` interpolates, in ``dtype`` (cached on ``table`` when its values
    carry no autograd history).

    Separable (``n_modes`` = 1, κ = 0): W does not depend on Δφ, WU = 0 and W = J/(P(V) P(L)) is a
    product of a function of θ_V and one of θ_L (module docstring: k_m = 1, so A_0 = H_0(θ_V) G_0(θ_L)ᵀ;
    WQ/W0 = H_1/H_0 depends on θ_V alone), so log W0[i, j] = log W0[i, 0] + (log W0[0, j] − log W0[0, 0])
    and bilinear interpolation of that sum is the sum of two linear ones: returns (G,) tables
    (log W0[·, 0], log W0[0, ·] − log W0[0, 0], WQ/W0[·, 0]).
    Otherwise: the three channels (log W0, WQ/W0, WU/W0), each flat (G·G·F,).
    """
    cacheable = not table.values.requires_grad
    if cacheable and dtype in table.cache:
        return table.cache[dtype]
    v = table.values
    if table.n_modes == 1:
        out = (v[:, 0, 0, 0], v[0, :, 0, 0] - v[0, 0, 0, 0], v[:, 0, 0, 1])
    else:
        out = tuple(v.reshape(-1, v.shape[-1]).t())
    out = tuple(t.to(dtype).contiguous() for t in out)
    if cacheable:
        table.cache[dtype] = out
    return out


def _any_on_host(mask: Tensor) -> bool:
    """Whether any element of ``mask`` is nonzero, answered on CPU only: True on other devices (no
    host synchronisation; callers then take the general path, which gives the same values)."""
    return mask.device.type != "cpu" or bool(mask.any())


def body_parts(table: BodyTable, geo: ShadingGeometry, *, scale: Tensor | float) -> Vec3:
    """Body-reflection Stokes (s0, s1, s2) (spec §7) of a :class:`ShadingGeometry` from a :class:`BodyTable`.

    W(θ_V, θ_L, Δφ) is interpolated with Δφ the azimuth of L about N from x_ref, the tangent
    direction toward V (toward L where V ∥ N, and any tangent, from e_x, when both are: the
    tabulated quantities do not depend on the choice there). The table's polarisation frame
    e'_x = sin θ_V N − cos θ_V x_ref (= normalise(N − (N·V)V)) is rotated into the pixel frame.
    Where V is not ∥ N, x_ref and the rotation depend on N and V alone and are computed at their
    (per-pixel) shape; with κ = 0 the lookup is two 1-D interpolations (:func:`_lookup`).

    Args:
        table: built by :func:`build_body_table` for the material.
        geo: :func:`~polarshape.brdf.geometry.shading_geometry` of unit N, L, V.
        scale: k_b times the irradiance (broadcastable to (...)).

    Returns:
        (s0, s1, s2), each (...), for unit irradiance times ``scale``; zero unless N·L > 0 and N·V > 0.
    """
    n, l, v, e_x, e_y = geo.normal, geo.light, geo.view, geo.e_x, geo.e_y
    dt = geo.n_dot_l.dtype
    eps2 = 1e-12 if dt == torch.float64 else 1e-8
    # per pixel: x_p toward V's azimuth (from e_x where V ∥ N), y_p = N × x_p
    v_t = tuple(torch.addcmul(v[c], geo.n_dot_v, n[c], value=-1.0) for c in range(3))
    n_dot_ex = dot3(n, e_x)
    f_t = tuple(torch.addcmul(e_x[c], n_dot_ex, n[c], value=-1.0) for c in range(3))
    use_v = (dot3(v_t, v_t) > eps2).to(dt)
    x_p = safe_normalize3(tuple(v_t[c] * use_v + f_t[c] * (1.0 - use_v) for c in range(3)))
    y_p = cross3(n, x_p)
    lx, ly = dot3(l, x_p), dot3(l, y_p)  # L in the tangent frame
    # where V ∥ N and L is not, x_ref = normalise(L − (N·L)N) = (lx x_p + ly y_p)/r: (cos γ, sin γ) = (lx, ly)/r
    fallback = _any_on_host(1.0 - use_v)
    if fallback:
        r2 = lx * lx + ly * ly
        fb = (1.0 - use_v) * (r2 > eps2).to(dt)  # 1 where x_ref is L's azimuth
        rinv = fb / torch.sqrt(r2.clamp_min(tiny(dt) ** 2))
        cos_g, sin_g = (1.0 - fb) + lx * rinv, ly * rinv
    # e'_x = sin θ_V N − cos θ_V x_ref projected on e_x, e_y; x_ref = cos γ x_p + sin γ y_p
    sin_v, cos_v = torch.sin(geo.theta_v), torch.cos(geo.theta_v)
    a0, b0 = sin_v * n_dot_ex, sin_v * dot3(n, e_y)
    ax, bx = cos_v * dot3(x_p, e_x), cos_v * dot3(x_p, e_y)
    if fallback:
        ay, by = cos_v * dot3(y_p, e_x), cos_v * dot3(y_p, e_y)
        cos2chi, sin2chi = double_angle_of(a0 - torch.addcmul(cos_g * ax, sin_g, ay), b0 - torch.addcmul(cos_g * bx, sin_g, by))
    else:
        cos2chi, sin2chi = double_angle_of(a0 - ax, b0 - bx)

    g = table.values.shape[0]
    i = (table.warp.to_grid(geo.theta_v) + 1.0) * (0.5 * (g - 1))
    j = (table.warp.to_grid(geo.theta_l) + 1.0) * (0.5 * (g - 1))
    k = torch.as_tensor(scale, dtype=dt, device=geo.n_dot_l.device) * geo.view_mask
    factor = (k / math.pi) * geo.n_dot_l.clamp_min(0.0)  # (k_b/π) [N·L]₊ (spec §7 with G1 = cos θ/P)
    if table.n_modes == 1:  # separable (κ = 0): log W0 = A(θ_V) + B(θ_L), WQ/W0 = Q(θ_V), WU = 0
        a_tab, b_tab, q_tab = _lookup(table, dt)
        s0 = factor * torch.exp(interp_uniform(i, a_tab) + interp_uniform(j, b_tab))
        q = interp_uniform(i, q_tab)
        return s0, s0 * (q * cos2chi), s0 * (q * sin2chi)
    dphi = safe_atan2(ly, lx)
    if fallback:
        dphi = dphi * (1.0 - fb)  # Δφ = 0 where x_ref is L's azimuth
    f = table.values.shape[2]
    w_log, w_q, w_u = _trilinear_flat(_lookup(table, dt), tuple(table.values.shape[:3]), i, j, dphi.abs() * ((f - 1) / math.pi))
    s0 = factor * torch.exp(w_log)
    wu = w_u * (1.0 - 2.0 * (dphi < 0).to(dt))  # WU is odd in Δφ
    s1, s2 = rotate_linear_stokes(s0 * w_q, s0 * wu, cos2chi, sin2chi)
    return s0, s1, s2


def body_stokes_fast(
    table: BodyTable,
    normal: Tensor,
    light: Tensor,
    view: Tensor,
    *,
    k_b: Tensor | float,
    geometry: ShadingGeometry | None = None,
) -> Tensor:
    """Body-reflection Stokes vector (spec §7) from a :class:`BodyTable` (:func:`body_parts` stacked).

    Args:
        table: built by :func:`build_body_table` for the material.
        normal, light, view: (..., 3) unit vectors in the camera frame (broadcastable).
        k_b: body albedo, float or tensor broadcastable to (...) (e.g. per pixel).
        geometry: :func:`~polarshape.brdf.geometry.shading_geometry` of (N, L, V) if already computed.

    Returns:
        (..., 3) Stokes (s0, s1, s2) for unit irradiance; zero unless N·L > 0 and N·V > 0.
    """
    geo = shading_geometry(normal, light, view) if geometry is None else geometry
    return torch.stack(torch.broadcast_tensors(*body_parts(table, geo, scale=k_b)), dim=-1)
