"""Tests of polarshape.brdf.body_fast: the body-term table build (chunking) and its lookups."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.brdf import build_tables
from polarshape.brdf.body_fast import (
    ArcFourier,
    BodyTable,
    arc_nodes,
    body_stokes_fast,
    build_body_table,
    clear_facet_cache,
    fold_arc_rule,
    kernel_cosine_rule,
)
from polarshape.brdf.distribution import d_normalisation
from polarshape.brdf.smith import clear_smith_cache


def _material(kappa: float, requires_grad: bool = False) -> tuple[torch.Tensor, ...]:
    mu, a, b = (torch.tensor(v, dtype=torch.float64) for v in (1.5, 0.25, 2.0))
    k = torch.tensor(kappa, dtype=torch.float64, requires_grad=requires_grad)
    return mu, a, b, k, d_normalisation(a, b)


@pytest.mark.parametrize("kappa", [0.0, 50.0])
def test_body_table_does_not_depend_on_the_chunk_size(kappa: float) -> None:
    """One θ row at a time (and one kernel row) gives the table of one chunk for everything."""
    whole = build_body_table(*_material(kappa), n_grid=9, n_theta=3, max_width=0.3, chunk_elements=1 << 40)
    rows = build_body_table(*_material(kappa), n_grid=9, n_theta=3, max_width=0.3, chunk_elements=1)
    assert rows.n_modes == whole.n_modes and rows.values.shape == whole.values.shape
    torch.testing.assert_close(rows.values, whole.values, rtol=1e-13, atol=1e-13)


def test_body_table_gradient_does_not_depend_on_the_chunk_size() -> None:
    grads = []
    for chunk in (1 << 40, 1):
        mu, a, b, k, c = _material(20.0, requires_grad=True)
        build_body_table(mu, a, b, k, c, n_grid=5, n_dphi=9, n_theta=3, max_width=0.3,
                         chunk_elements=chunk).values.sum().backward()
        grads.append(k.grad)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-12, atol=0.0)


def test_cached_kernel_leaves_the_kappa_gradient() -> None:
    """A build at κ fills the kernel cache; a build whose κ requires grad is not served from it: its
    ∂/∂κ is that of a build from empty caches."""
    grads = []
    for warm in (False, True):
        clear_facet_cache()
        if warm:
            build_body_table(*_material(20.0), n_grid=5, n_dphi=9, n_theta=3, max_width=0.3)
        mu, a, b, k, c = _material(20.0, requires_grad=True)
        build_body_table(mu, a, b, k, c, n_grid=5, n_dphi=9, n_theta=3, max_width=0.3).values.sum().backward()
        grads.append(k.grad)
    assert grads[0] is not None and float(grads[0].abs()) > 0.0
    torch.testing.assert_close(grads[1], grads[0], rtol=0.0, atol=0.0)


def _arc_inputs(shape: tuple[int, ...], n: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Random h_even (2, *shape, n), h_odd (*shape, n) and angles φ (*shape, n) in (−π, π)."""
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    phi = (torch.rand(*shape, n, generator=gen, dtype=f64) * 2.0 - 1.0) * math.pi
    return torch.randn(2, *shape, n, generator=gen, dtype=f64), torch.randn(*shape, n, generator=gen, dtype=f64), phi


def _direct_modes(
    h_even: torch.Tensor, h_odd: torch.Tensor, phi: torch.Tensor, n_modes: int
) -> tuple[torch.Tensor, ...]:
    """The sums of ArcFourier written out with one (..., n, M) tensor of cos mφ, sin mφ."""
    angle = phi.unsqueeze(-1) * torch.arange(n_modes, dtype=phi.dtype)  # (..., n, M)
    even = (h_even.unsqueeze(-1) * torch.cos(angle)).sum(-2).movedim(-1, 1)  # (2, M, ...)
    odd = (h_odd.unsqueeze(-1) * torch.sin(angle)).sum(-2).movedim(-1, 0)  # (M, ...)
    return even, odd


@pytest.mark.parametrize("n_modes", [2, 3, 7, 41, 160])
def test_arc_fourier_gives_the_direct_sums(n_modes: int) -> None:
    """The recurrence's sums equal the written-out ones for every mode, pair and channel, up to the
    mode cap of :func:`n_fourier_modes` (160: the recurrence's rounding grows as m²·eps)."""
    h_even, h_odd, phi = _arc_inputs((3, 5), 11)
    even, odd = ArcFourier.apply(h_even, h_odd, phi, n_modes)
    ref_even, ref_odd = _direct_modes(h_even, h_odd, phi, n_modes)
    assert even.shape == (2, n_modes, 3, 5) and odd.shape == (n_modes, 3, 5)
    torch.testing.assert_close(even, ref_even, rtol=1e-12, atol=1e-11)
    torch.testing.assert_close(odd, ref_odd, rtol=1e-12, atol=1e-11)


def test_arc_fourier_backward_is_the_transposed_product() -> None:
    """gradcheck of the custom backward (non-square pairs, nodes and modes: a wrong transpose or
    channel fails) and its agreement with autograd through the written-out sums."""
    h_even, h_odd, phi = _arc_inputs((2, 3), 5, seed=1)
    h_even.requires_grad_(True)
    h_odd.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda e, o: ArcFourier.apply(e, o, phi, 7), (h_even, h_odd))
    gen = torch.Generator().manual_seed(2)
    w_even = torch.randn(2, 7, 2, 3, generator=gen, dtype=torch.float64)
    w_odd = torch.randn(7, 2, 3, generator=gen, dtype=torch.float64)
    grads = []
    for fn in (ArcFourier.apply, _direct_modes):
        even, odd = fn(h_even, h_odd, phi, 7)
        grads.append(torch.autograd.grad((even * w_even).sum() + (odd * w_odd).sum(), (h_even, h_odd)))
    for got, ref in zip(*grads):
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n", [8, 9])
def test_folded_arc_rule_gives_the_full_rule_sums(n: int) -> None:
    """On the φ ≥ 0 half of the arc rules (doubled weights, the node φ = 0 once) an integrand even in φ
    (cosine modes) and one odd in φ (sine modes) have the modes of the full rules."""
    theta = torch.linspace(0.1, 1.5, 4, dtype=torch.float64).numpy()
    phi_full, w_full = arc_nodes(theta, theta[:3], n)  # (3, 4, n)
    phi_half, w_half = fold_arc_rule(phi_full, w_full)
    assert phi_half.shape == (3, 4, (n + 1) // 2) and bool((phi_half >= 0).all())
    sums = []
    for phi_np, w_np in ((phi_full, w_full), (phi_half, w_half)):
        phi, w = torch.as_tensor(phi_np), torch.as_tensor(w_np)
        even = torch.stack([w * torch.exp(torch.cos(phi)), w * torch.cos(phi) ** 2])
        odd = w * torch.sin(phi) * (1.0 + torch.cos(phi))
        sums.append(ArcFourier.apply(even, odd, phi, 9))
    for half, full in zip(sums[1], sums[0]):
        torch.testing.assert_close(half, full, rtol=1e-12, atol=1e-13)


def test_kernel_cosine_rule_gives_the_fft_cosine_series() -> None:
    """For an even function of ψ the half-period matrix product is the cosine series read off the FFT."""
    n_modes, n_psi = 12, 2 * 12 + 64
    cos_psi, basis = kernel_cosine_rule(n_modes, n_psi, torch.float64, "cpu")
    assert cos_psi.shape == (n_psi // 2 + 1,) and basis.shape == (n_psi // 2 + 1, n_modes)
    z = torch.tensor([[0.5], [7.0], [30.0]], dtype=torch.float64)
    full = torch.exp(z * torch.cos(torch.arange(n_psi, dtype=torch.float64) * (2.0 * math.pi / n_psi)))  # (3, P)
    ref = torch.fft.rfft(full, dim=-1).real[:, :n_modes] / n_psi
    ref[:, 1:] *= 2.0
    torch.testing.assert_close(torch.exp(z * cos_psi) @ basis, ref, rtol=1e-12, atol=1e-13 * float(ref[:, 0].max()))


def _geometry(p: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unit N, L, V (p, 3) within 80° of each other's hemisphere, perspective views."""
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    v = torch.cat([(torch.rand(p, 2, generator=gen, dtype=f64) - 0.5) * 0.6, -torch.ones(p, 1, dtype=f64)], 1)
    n = v + 0.9 * torch.randn(p, 3, generator=gen, dtype=f64)
    l = v + 0.9 * torch.randn(p, 3, generator=gen, dtype=f64)
    return tuple(x / x.norm(dim=-1, keepdim=True) for x in (n, l, v))  # type: ignore[return-value]


def test_separable_lookup_matches_the_trilinear_one() -> None:
    """κ = 0: the two 1-D interpolations of the separable table give the trilinear interpolation's values."""
    table = build_tables(ior=1.5, alpha=0.25, beta=2.0, kappa=0.0).body
    assert table.n_modes == 1
    general = BodyTable(table.values, table.warp, n_modes=2)  # same values, the general lookup
    n, l, v = _geometry(500)
    sep = body_stokes_fast(table, n, l, v, k_b=1.0)
    tri = body_stokes_fast(general, n, l, v, k_b=1.0)
    assert bool((sep[:, 0] > 0).any())
    torch.testing.assert_close(sep, tri, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("kappa", [0.0, 20.0])
def test_view_along_the_normal_takes_the_azimuth_of_the_light(kappa: float) -> None:
    """V ∥ N: the tabulated frame follows L's azimuth, so turning L about N turns the body's AoLP
    with it and keeps s0 and the DoLP (orthographic: the pixel frame is x̂, ŷ)."""
    tables = build_tables(ior=1.5, alpha=0.3, beta=2.0, kappa=kappa)
    n = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    phi = torch.linspace(0.0, 2.5, 6, dtype=torch.float64)
    zen = 0.7
    l = torch.stack([math.sin(zen) * phi.cos(), math.sin(zen) * phi.sin(), -math.cos(zen) * torch.ones_like(phi)], -1)
    s = body_stokes_fast(tables.body, n, l, n, k_b=1.0)  # (6, 3)
    lin = torch.sqrt(s[:, 1] ** 2 + s[:, 2] ** 2)
    torch.testing.assert_close(s[:, 0], s[:1, 0].expand(6), rtol=1e-12, atol=0.0)
    torch.testing.assert_close(lin, lin[:1].expand(6), rtol=1e-9, atol=1e-15)
    if kappa > 0:  # polarised: the angle turns with L (2ψ by 2φ)
        assert float(lin[0] / s[0, 0]) > 1e-6  # weakly (the exit facets see V at nearly equal angles)
        c2 = torch.cos(2 * phi) * s[0, 1] - torch.sin(2 * phi) * s[0, 2]
        s2 = torch.sin(2 * phi) * s[0, 1] + torch.cos(2 * phi) * s[0, 2]
        torch.testing.assert_close(s[:, 1:], torch.stack([c2, s2], -1), rtol=1e-9, atol=1e-12 * float(s[0, 0]))


@pytest.mark.parametrize("kappa", [0.0, 20.0])
def test_a_pixel_with_view_along_the_normal_leaves_the_others_unchanged(kappa: float) -> None:
    """The batch without such a pixel skips that case on CPU: the values of the other pixels are the same."""
    tables = build_tables(ior=1.5, alpha=0.3, beta=2.0, kappa=kappa)
    n, l, v = _geometry(200, seed=3)
    plain = body_stokes_fast(tables.body, n, l, v, k_b=1.0)
    n2, v2 = torch.cat([n, v[:1]]), torch.cat([v, v[:1]])  # one more pixel with N = V
    mixed = body_stokes_fast(tables.body, n2, torch.cat([l, l[:1]]), v2, k_b=1.0)
    torch.testing.assert_close(mixed[:-1], plain, rtol=1e-15, atol=0.0)
    assert bool(torch.isfinite(mixed).all())


@pytest.mark.parametrize("kappa", [0.0, 20.0])
def test_cached_facet_side_gives_the_table_built_afresh(kappa: float) -> None:
    """Builds on one frozen layout share their facet side (a fit's finite differences): every table then
    equals the one built with an empty cache — a changed μ is a new side, a changed α, β or κ is not."""
    layout = (0.25, 2.0, kappa)
    variants = [dict(ior=1.5, alpha=0.25, beta=2.0, kappa=kappa), dict(ior=1.5, alpha=0.2503, beta=2.0, kappa=kappa),
                dict(ior=1.5, alpha=0.25, beta=2.004, kappa=kappa * 1.01), dict(ior=1.52, alpha=0.25, beta=2.0, kappa=kappa)]
    clear_facet_cache()
    shared = [build_tables(**v, layout=layout, n_grid=17).body.values for v in variants]
    for v, values in zip(variants, shared):
        clear_facet_cache()
        fresh = build_tables(**v, layout=layout, n_grid=17).body.values
        assert torch.equal(values, fresh), v
    assert not torch.equal(shared[0], shared[3])  # μ moved the table: the cache did not hand back μ 1.5's side
    assert clear_facet_cache() >= 1



def test_cached_kappa_zero_geometry_is_not_reused_for_another_layout() -> None:
    """κ = 0 keeps the facet geometry by layout, not μ: builds on other layouts (α, β placing the nodes)
    and other μ after one another each give the table built with empty caches — a geometry reused for
    another layout, or a Smith Φ for another grid, would change them."""
    builds = [dict(ior=1.5, alpha=0.25, beta=2.0, layout=(0.25, 2.0, 0.0)),
              dict(ior=1.5, alpha=0.26, beta=2.0, layout=(0.26, 2.0, 0.0)),  # another layout, same μ
              dict(ior=1.5, alpha=0.25, beta=2.4, layout=(0.25, 2.4, 0.0)),
              dict(ior=1.55, alpha=0.26, beta=2.0, layout=(0.26, 2.0, 0.0)),  # a cached layout, a new μ
              dict(ior=1.5, alpha=0.25, beta=2.0, layout=(0.25, 2.0, 0.0), n_grid=33)]  # another grid
    clear_facet_cache()
    clear_smith_cache()
    shared = [build_tables(kappa=0.0, **b) for b in builds]
    for b, tables in zip(builds, shared):
        clear_facet_cache()
        clear_smith_cache()
        fresh = build_tables(kappa=0.0, **b)
        assert torch.equal(tables.body.values, fresh.body.values), b
        assert torch.equal(tables.smith.excess, fresh.smith.excess), b
    assert not torch.equal(shared[0].body.values, shared[1].body.values)


def test_kappa_zero_gradient_with_a_cached_geometry() -> None:
    """μ with autograd history skips the facet-side cache but uses the κ = 0 geometry (constants): the
    gradient is the one of a build with empty caches."""
    grads = []
    for clear in (True, False):
        if clear:
            clear_facet_cache()
        mu = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
        tables = build_tables(ior=mu, alpha=0.25, beta=2.0, kappa=0.0, n_grid=17)
        tables.body.values.sum().backward()
        grads.append(mu.grad)
    assert float(grads[0].abs()) > 0
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-13, atol=0.0)
