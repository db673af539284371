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
- the correlation kernel exp(κ(n·n_i − 1)) = Σ_m k_m(θ, θ') cos m(φ − φ') (Fourier series in the
  azimuth difference; the coefficients are modified Bessel functions, computed by FFT), which
  turns the 4-D integral into, for each m, a product of small matrices
  A_m = H_m(θ_V) · k_m · G_m(θ_L)ᵀ — the route of spec §7 with a Fourier rather than a spherical-
  harmonic expansion. κ = 0 keeps only m = 0 (the separable case);
- J(θ_V, θ_L, Δφ) = Σ_m A_m cos mΔφ (intensity and s1), Σ_m A_m sin mΔφ (s2).

Polarisation is tabulated in a frame attached to the geometry, e'_x = normalise(N − (N·V)V) (the
projection of N), and rotated into the pixel frame at evaluation; the body AoLP is thus ∥ to the
plane of N and V where the exit transmission dominates (spec §5, §7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from polarshape.brdf.distribution import d_shape
from polarshape.brdf.fresnel import fresnel
from polarshape.brdf.geometry import (
    ShadingGeometry,
    dot,
    double_angle,
    rotate_linear_stokes,
    safe_atan2,
    safe_normalize,
    shading_geometry,
    tiny,
)
from polarshape.brdf.quadrature import ThetaWarp, gauss_legendre, theta_cutoff, theta_rule


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
    st, ct = np.sin(theta)[None, :], np.cos(theta)[None, :]
    sw, cw = np.sin(theta_w)[:, None], np.cos(theta_w)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (ct * cw) / (st * sw)
    full = ~(r < 1.0)  # includes r = inf / nan (θ or θ_ω = 0)
    phic = np.where(full, math.pi, np.arccos(-np.clip(np.nan_to_num(r, nan=1.0, posinf=1.0), -1.0, 1.0)))
    return phic[..., None] * x, phic[..., None] * w


class ArcFourier(torch.autograd.Function):
    """Azimuthal Fourier coefficients on the arc rules: for m = 0..M−1,
    even[c, m] = Σ_n h_even[c, ..., n] cos(m φ_n) and odd[m] = Σ_n h_odd[..., n] sin(m φ_n).

    cos mφ and sin mφ come from the rotation recurrence (angle addition) in both passes, so no
    (…, n, M) tensor is ever stored: memory O(G·Q·n) instead of O(G·Q·n·M), and the backward pass
    (the same sums transposed) costs as much as the forward one.
    """

    @staticmethod
    def _modes(phi: Tensor, n_modes: int):  # noqa: ANN205
        c1, s1 = torch.cos(phi), torch.sin(phi)
        c, s = torch.ones_like(phi), torch.zeros_like(phi)
        for _ in range(n_modes):
            yield c, s
            c, s = c * c1 - s * s1, s * c1 + c * s1

    @staticmethod
    def forward(ctx, h_even: Tensor, h_odd: Tensor, phi: Tensor, n_modes: int) -> tuple[Tensor, Tensor]:  # noqa: ANN001
        ctx.save_for_backward(phi)
        ctx.n_modes = n_modes
        if n_modes == 1:  # κ = 0: only m = 0 (cos 0 = 1, sin 0 = 0), no trigonometry needed
            return h_even.sum(-1).unsqueeze(1), torch.zeros_like(h_odd[..., 0]).unsqueeze(0)
        even = torch.stack([(h_even * c).sum(-1) for c, _ in ArcFourier._modes(phi, n_modes)], dim=1)
        odd = torch.stack([(h_odd * s).sum(-1) for _, s in ArcFourier._modes(phi, n_modes)], dim=0)
        return even, odd

    @staticmethod
    def backward(ctx, g_even: Tensor, g_odd: Tensor):  # noqa: ANN001, ANN205
        (phi,) = ctx.saved_tensors
        if ctx.n_modes == 1:
            d_even = g_even[:, 0].unsqueeze(-1).expand(g_even.shape[0], *phi.shape).contiguous()
            return d_even, torch.zeros_like(phi), None, None
        d_even = torch.zeros((g_even.shape[0], *phi.shape), dtype=phi.dtype, device=phi.device)
        d_odd = torch.zeros_like(phi)
        for i, (c, s) in enumerate(ArcFourier._modes(phi, ctx.n_modes)):
            d_even += g_even[:, i].unsqueeze(-1) * c
            d_odd += g_odd[i].unsqueeze(-1) * s
        return d_even, d_odd, None, None


def n_fourier_modes(kappa: float, alpha: float, beta: float, *, log_tol: float = 14.0, cap: int = 160) -> int:
    """Azimuthal modes needed for exp(κ(n·n_i − 1)): the m-th coefficient is e^{−κ(1−cc')} I_m(κ s s'),
    which decays like exp(−m²/(2κ s s')), with s, s' ≤ sin θ_cut. Returns M + 1 (m = 0..M)."""
    if kappa <= 0.0:
        return 1
    z = kappa * math.sin(theta_cutoff(alpha, beta)) ** 2
    return min(cap, int(math.ceil(math.sqrt(2.0 * z * log_tol))) + 3)


def _facet_modes(
    sq: Tensor, cq: Tensor, bq: Tensor, tg: Tensor, phi: Tensor, wphi: Tensor, ior: Tensor, n_modes: int
) -> tuple[Tensor, Tensor]:
    """The facet side of J for some rows of the θ grid: azimuthal Fourier modes of the exit (and,
    with the same integrand, entry) weights, and the projected areas.

    Args:
        sq, cq, bq: (Q,) sin θ, cos θ and θ weight × sin θ × D(θ) of the facet nodes.
        tg: (g,) polar angles of ω (rows of the grid); phi, wphi: (g, Q, n) their arc rules.
        ior: μ. n_modes: M.

    Returns:
        h_modes (3, M, g, Q) (intensity, s1 cosine modes; s2 sine modes; × bq), area (g,) = P(θ_g).
    """
    sg, cg = torch.sin(tg)[:, None, None], torch.cos(tg)[:, None, None]
    n_x, n_y, n_z = sq[None, :, None] * torch.cos(phi), sq[None, :, None] * torch.sin(phi), cq[None, :, None]
    cos_o = (n_x * sg + n_z * cg).clamp_min(0.0)  # n·ω with ω = (sin θ_g, 0, cos θ_g)
    fr = fresnel(cos_o, ior)  # spec §5 transmission at θ_o
    # facet normal in the frame e'_x = (−cos θ_g, 0, sin θ_g), e'_y = (0, 1, 0) (projection of N)
    ax = -n_x * cg + n_z * sg
    r2 = (ax * ax + n_y * n_y).clamp_min(tiny(phi.dtype))
    cos2, sin2 = (ax * ax - n_y * n_y) / r2, 2.0 * ax * n_y / r2
    base = wphi * cos_o  # arc weight × [n·ω]₊
    h = torch.stack([base * fr.t_plus, base * (-fr.t_minus) * cos2, base * (-fr.t_minus) * sin2])  # (3,g,Q,n)
    area = (base.sum(-1) * bq).sum(-1)  # (g,)
    # intensity and s1 are even in φ (cosine modes), s2 odd (sine modes)
    h_even, h_odd = ArcFourier.apply(h[:2], h[2], phi, n_modes)  # (2, M, g, Q), (M, g, Q)
    return torch.cat([h_even, h_odd.unsqueeze(0)]) * bq, area


def _kernel_modes(cq_rows: Tensor, sq_rows: Tensor, cq: Tensor, sq: Tensor, cos_psi: Tensor, kappa: Tensor,
                  n_modes: int) -> Tensor:
    """(q, Q, M) cosine-series coefficients (before the factor 2 of m ≥ 1) of exp(κ(n·n_i − 1)) in
    φ − φ' for the facet rows (q,) against all nodes (Q,), by FFT over the (P,) azimuths cos ψ."""
    arg = (cq_rows[:, None] * cq[None, :] - 1.0).unsqueeze(-1) + (sq_rows[:, None] * sq[None, :]).unsqueeze(-1) * cos_psi
    return torch.fft.rfft(torch.exp(kappa * arg), dim=-1).real[..., :n_modes] / cos_psi.numel()


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
    phi_np, wphi_np = arc_nodes(tq_np, tg_np, n_phi)  # (G, Q, n)

    def T(x: np.ndarray) -> Tensor:
        return torch.as_tensor(x, dtype=dt, device=dev)

    tq, wq, tg = T(tq_np), T(wq_np), T(tg_np)
    sq, cq = torch.sin(tq), torch.cos(tq)
    bq = wq * sq * c * d_shape(tq, alpha, beta)  # θ weight × sin θ × D(θ)   (Q,)
    n_q = tq.numel()
    # the rows of the θ grid are independent: a few at a time keep the (rows, Q, n) temporaries small
    rows = max(1, chunk_elements // (n_q * n_phi))
    parts = [
        _facet_modes(sq, cq, bq, tg[g0 : g0 + rows], T(phi_np[g0 : g0 + rows]), T(wphi_np[g0 : g0 + rows]), ior, n_modes)
        for g0 in range(0, n_grid, rows)
    ]
    h_modes = torch.cat([hm for hm, _ in parts], dim=2)  # (3, M, G, Q)
    area = torch.cat([ar for _, ar in parts])  # P(θ_g) (spec §4)   (G,)
    del parts

    m = torch.arange(n_modes, dtype=dt, device=dev)
    if n_modes == 1:
        k_m = torch.ones(1, n_q, n_q, dtype=dt, device=dev)
    else:
        n_psi = 2 * n_modes + 64
        psi = torch.arange(n_psi, dtype=dt, device=dev) * (2.0 * math.pi / n_psi)
        cos_psi = torch.cos(psi)
        q_rows = max(1, chunk_elements // (n_q * n_psi))
        spec = torch.cat([  # (Q, Q, M), θ rows a few at a time
            _kernel_modes(cq[q0 : q0 + q_rows], sq[q0 : q0 + q_rows], cq, sq, cos_psi, kappa, n_modes)
            for q0 in range(0, n_q, q_rows)
        ])
        spec = spec * torch.where(m == 0, 1.0, 2.0)
        k_m = spec.permute(2, 0, 1)  # (M,Q,Q): exp(κ(n·n_i−1)) = Σ k_m cos m(φ−φ')
    z = 2.0 * math.pi * (bq[:, None] * k_m[0]).sum(0)  # Z(θ') of eq. 20   (Q,)
    g_modes = h_modes[0] / z  # entry side: [n_i·L]₊ D T+(θ_i) / Z   (M, G, Q)
    inner = torch.matmul(k_m, g_modes.transpose(1, 2))  # (M, Q, G)
    amp = torch.matmul(h_modes, inner)  # (3, M, G_V, G_L)

    dphi = torch.linspace(0.0, math.pi, n_dphi, dtype=dt, device=dev)
    md = m[:, None] * dphi  # (M, F)
    j = torch.stack(
        [
            torch.einsum("mgh,mf->ghf", amp[0], torch.cos(md)),
            torch.einsum("mgh,mf->ghf", amp[1], torch.cos(md)),
            torch.einsum("mgh,mf->ghf", amp[2], torch.sin(md)),
        ]
    )
    w0 = (j[0] / (area[:, None, None] * area[None, :, None])).clamp_min(1e-300)
    values = torch.stack([torch.log(w0), j[1] / j[0].clamp_min(1e-300), j[2] / j[0].clamp_min(1e-300)], dim=-1)
    return BodyTable(values=values.contiguous(), warp=warp, n_modes=n_modes)


def trilinear(table: Tensor, i: Tensor, j: Tensor, k: Tensor) -> Tensor:
    """Trilinear interpolation of a channels-last table at fractional indices.

    Args:
        table: (A, B, C, K) values.
        i, j, k: (...) fractional indices along A, B, C (clamped to the table).

    Returns:
        (..., K), differentiable in the indices and the table. (Eight row gathers of K values:
        about twice as fast on CPU as ``grid_sample`` on the channels-first layout.)
    """
    a, b, c, n_ch = table.shape
    flat = table.reshape(-1, n_ch)
    shape = i.shape
    i, j, k = (x.reshape(-1) for x in (i, j, k))
    idx, frac = [], []
    for x, size in ((i, a), (j, b), (k, c)):
        xc = x.clamp(0.0, size - 1.0)
        x0 = xc.detach().floor().clamp(max=max(size - 2, 0))
        idx.append(x0.long())
        frac.append((xc - x0).unsqueeze(-1))
    base = (idx[0] * b + idx[1]) * c + idx[2]
    si, sj, sk = (b * c if a > 1 else 0), (c if b > 1 else 0), (1 if c > 1 else 0)

    def at(offset: int) -> Tensor:
        return flat.index_select(0, base + offset)

    fi, fj, fk = frac
    c00 = torch.lerp(at(0), at(sk), fk)
    c01 = torch.lerp(at(sj), at(sj + sk), fk)
    c10 = torch.lerp(at(si), at(si + sk), fk)
    c11 = torch.lerp(at(si + sj), at(si + sj + sk), fk)
    out = torch.lerp(torch.lerp(c00, c01, fj), torch.lerp(c10, c11, fj), fi)
    return out.reshape(*shape, n_ch)


def azimuth_frame(normal: Tensor, view: Tensor, light: Tensor, e_x: Tensor) -> tuple[Tensor, Tensor]:
    """Tangent frame (x_ref, y_ref = N × x_ref) with x_ref toward V's azimuth about N.

    When V ∥ N the azimuth of L is used instead, and when both are ∥ N any tangent (from e_x):
    the tabulated quantities do not depend on the choice there. Shapes (..., 3).
    """
    eps2 = 1e-12 if normal.dtype == torch.float64 else 1e-8
    v_t = view - dot(normal, view).unsqueeze(-1) * normal
    l_t = light - dot(normal, light).unsqueeze(-1) * normal
    f_t = e_x - dot(normal, e_x).unsqueeze(-1) * normal
    use_v = (dot(v_t, v_t) > eps2).unsqueeze(-1)
    use_l = (dot(l_t, l_t) > eps2).unsqueeze(-1)
    x_ref = safe_normalize(torch.where(use_v, v_t, torch.where(use_l, l_t, f_t)))
    return x_ref, torch.linalg.cross(normal, x_ref, dim=-1)


def body_stokes_fast(
    table: BodyTable,
    normal: Tensor,
    light: Tensor,
    view: Tensor,
    *,
    k_b: Tensor | float,
    geometry: ShadingGeometry | None = None,
) -> Tensor:
    """Body-reflection Stokes vector (spec §7) from a :class:`BodyTable`.

    Args:
        table: built by :func:`build_body_table` for the material.
        normal, light, view: (..., 3) unit vectors in the camera frame (broadcastable).
        k_b: body albedo, float or tensor broadcastable to (...) (e.g. per pixel).
        geometry: :func:`~polarshape.brdf.geometry.shading_geometry` of (N, L, V) if already computed.

    Returns:
        (..., 3) Stokes (s0, s1, s2) for unit irradiance; zero unless N·L > 0 and N·V > 0.
    """
    normal, light, view = torch.broadcast_tensors(normal, light, view)
    dt = normal.dtype
    geo = shading_geometry(normal, light, view) if geometry is None else geometry
    e_x, e_y, cos_l, front, theta_l, theta_v = geo.e_x, geo.e_y, geo.n_dot_l, geo.front, geo.theta_l, geo.theta_v
    x_ref, y_ref = azimuth_frame(normal, view, light, e_x)
    dphi = safe_atan2(dot(light, y_ref), dot(light, x_ref))

    g, f = table.values.shape[0], table.values.shape[2]
    w = trilinear(
        table.values.to(dt),  # (G_V, G_L, F, 3)
        (table.warp.to_grid(theta_v) + 1.0) * (0.5 * (g - 1)),
        (table.warp.to_grid(theta_l) + 1.0) * (0.5 * (g - 1)),
        dphi.abs() * ((f - 1) / math.pi),
    )  # (..., 3)
    w0 = torch.exp(w[..., 0])
    wq, wu = w0 * w[..., 1], w0 * w[..., 2] * torch.where(dphi < 0, -1.0, 1.0).to(dt)

    # local polarisation frame e'_x = sin θ_V N − cos θ_V x_ref (= normalise(N − (N·V)V))
    e_xl = torch.sin(theta_v).unsqueeze(-1) * normal - torch.cos(theta_v).unsqueeze(-1) * x_ref
    cos2chi, sin2chi = double_angle(e_xl, e_x, e_y)
    s1, s2 = rotate_linear_stokes(wq, wu, cos2chi, sin2chi)
    kb = torch.as_tensor(k_b, dtype=dt, device=normal.device)
    out = ((kb / math.pi) * cos_l.clamp_min(0.0)).unsqueeze(-1) * torch.stack([w0, s1, s2], dim=-1)
    return torch.where(front.unsqueeze(-1), out, torch.zeros_like(out))
