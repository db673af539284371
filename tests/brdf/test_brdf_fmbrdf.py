"""Physics of the fast FMBRDF evaluator: limits, reciprocity, polarisation, energy (spec §5–§7)."""

import math

import numpy as np
import pytest
import torch
from brdf_helpers import angle_diff_mod_pi, around, random_geometry

from polarshape.brdf import build_tables, fmbrdf_stokes
from polarshape.brdf.distribution import d_normalisation, d_shape
from polarshape.brdf.fresnel import fresnel
from polarshape.brdf.quadrature import theta_rule
from polarshape.brdf.smith import projected_area_exact
from polarshape.errors import ShapeError
from polarshape.imaging.stokes import aolp, dolp

F64 = torch.float64
Z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


def dirs(theta_deg, phi_deg=0.0):
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return torch.tensor([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)], dtype=F64)


def body(n, l, v, tables, **kw):
    return fmbrdf_stokes(n, l, v, ior=1.5, k_s=0.0, k_b=1.0, alpha=0.3, beta=2.0, kappa=0.0, tables=tables, **kw)


def surface(n, l, v, tables):
    return fmbrdf_stokes(n, l, v, ior=1.5, k_s=1.0, k_b=0.0, alpha=0.3, beta=2.0, kappa=0.0, tables=tables)


def test_shapes_dtypes_and_zero_when_back_facing():
    n = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])  # facing / back-facing an orthographic camera
    v = torch.tensor([0.0, 0.0, -1.0])
    l = torch.tensor([0.3, 0.0, -0.954]).expand(2, 3)
    s = fmbrdf_stokes(n, l, v, ior=1.5, k_s=1.0, k_b=0.4, alpha=0.2, beta=2.0, kappa=10.0)
    assert s.shape == (2, 3) and s.dtype == torch.float32
    assert float(s[0, 0]) > 0 and torch.all(s[1] == 0)
    s64 = fmbrdf_stokes(n.double(), l.double(), v.double(), ior=1.5, k_s=1.0, k_b=0.4, alpha=0.2, beta=2.0, kappa=10.0)
    assert torch.allclose(s.double(), s64, rtol=1e-4, atol=1e-7)


def test_per_pixel_body_albedo_broadcasts():
    rng = np.random.default_rng(0)
    n, l, v = random_geometry(rng, 64)
    t = build_tables(ior=1.4, alpha=0.3, beta=2.0, kappa=5.0)
    kb = torch.linspace(0.0, 1.0, 64, dtype=F64)
    s = fmbrdf_stokes(n, l, v, ior=1.4, k_s=0.0, k_b=kb, alpha=0.3, beta=2.0, kappa=5.0, tables=t)
    s1 = fmbrdf_stokes(n, l, v, ior=1.4, k_s=0.0, k_b=1.0, alpha=0.3, beta=2.0, kappa=5.0, tables=t)
    assert torch.allclose(s, kb[:, None] * s1)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(ior=0.9), "ior"),
        (dict(alpha=0.0), "alpha"),
        (dict(kappa=-1.0), "kappa"),
        (dict(k_b=float("nan")), "k_b"),
        (dict(alpha=torch.tensor([0.1, 0.2])), "one value of 'alpha'"),
    ],
)
def test_invalid_parameters_are_named(kwargs, match):
    p = dict(ior=1.5, k_s=1.0, k_b=0.5, alpha=0.3, beta=2.0, kappa=0.0)
    p.update(kwargs)
    n = torch.tensor([0.0, 0.0, -1.0])
    with pytest.raises(ValueError, match=match):
        fmbrdf_stokes(n, n, n, **p)


def test_invalid_vectors_are_named():
    n = torch.tensor([0.0, 0.0, -1.0])
    with pytest.raises(ShapeError, match=r"normal must have shape \(\*, 3\); got \(4, 2\)"):
        fmbrdf_stokes(torch.zeros(4, 2), n, n, ior=1.5, k_s=1, k_b=1, alpha=0.3, beta=2, kappa=0)
    with pytest.raises(ShapeError, match="do not broadcast"):
        fmbrdf_stokes(torch.zeros(4, 3), torch.zeros(5, 3), n, ior=1.5, k_s=1, k_b=1, alpha=0.3, beta=2, kappa=0)


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("which", ["normal", "light", "view"])
def test_non_finite_vectors_are_named(which, bad, exact):
    """NaN/Inf in N, L or V: a ValueError naming the argument (the fast path used to fail deep in
    the Smith table, the exact path to return 0)."""
    ok = torch.tensor([[0.0, 0.0, -1.0], [0.3, 0.0, -0.954]], dtype=F64)
    vectors = {"normal": ok, "light": ok, "view": ok}
    vectors[which] = ok.clone()
    vectors[which][1, 0] = bad
    with pytest.raises(ValueError, match=rf"^{which} must be finite; got 1 NaN/Inf value"):
        fmbrdf_stokes(vectors["normal"], vectors["light"], vectors["view"], ior=1.5, k_s=1.0, k_b=0.5, alpha=0.3,
                      beta=2.0, kappa=0.0, exact=exact)


def test_surface_reciprocity():
    rng = np.random.default_rng(1)
    n, l, v = random_geometry(rng, 500, max_deg=85)
    t = build_tables(ior=1.5, alpha=0.3, beta=2.0, kappa=0.0)
    f_lv = surface(n, l, v, t)[:, 0] / (n * l).sum(-1)
    f_vl = surface(n, v, l, t)[:, 0] / (n * v).sum(-1)
    assert torch.allclose(f_lv, f_vl, rtol=1e-3, atol=1e-9)


@pytest.mark.parametrize("alpha,beta", [(0.3, 2.0), (0.05, 1.0), (1.2, 3.0)])
def test_body_reciprocity_at_kappa_zero(alpha, beta):
    rng = np.random.default_rng(2)
    n, l, v = random_geometry(rng, 500, max_deg=85)
    t = build_tables(ior=1.5, alpha=alpha, beta=beta, kappa=0.0)
    f_lv = body(n, l, v, t)[:, 0] / (n * l).sum(-1)
    f_vl = body(n, v, l, t)[:, 0] / (n * v).sum(-1)
    assert torch.allclose(f_lv, f_vl, rtol=2e-3)


def test_body_not_reciprocal_for_kappa_positive_as_spec_says():
    """Spec §7: eq. 20's normalisation breaks reciprocity for κ > 0 (by 1–4.5 % at κ = 20–100)."""
    t = build_tables(ior=1.5, alpha=0.3, beta=2.0, kappa=60.0)
    n, l, v = Z, dirs(20, 0), dirs(70, 180)
    f_lv = body(n, l, v, t)[0] / (n @ l)
    f_vl = body(n, v, l, t)[0] / (n @ v)
    assert 1e-3 < abs(float(f_lv / f_vl) - 1.0) < 0.1


def test_kappa_zero_is_separable():
    """κ = 0: W(θ_V, θ_L, Δφ) = a(θ_V)·b(θ_L), independent of Δφ; the general (Fourier-kernel)
    route at κ → 0 agrees with the separable route."""
    t = build_tables(ior=1.5, alpha=0.4, beta=2.0, kappa=0.0)
    w = lambda tv, tl, dp: float(body(Z, dirs(tl, dp), dirs(tv, 0), t)[0] / math.cos(math.radians(tl)))  # noqa: E731
    assert w(30, 50, 0) == pytest.approx(w(30, 50, 120), rel=1e-9)
    assert w(10, 60, 0) * w(70, 20, 0) == pytest.approx(w(10, 20, 0) * w(70, 60, 0), rel=1e-9)
    k = torch.tensor(1e-9, dtype=F64, requires_grad=True)  # forces the Fourier-kernel path
    tk = build_tables(ior=1.5, alpha=0.4, beta=2.0, kappa=k)
    for tv, tl, dp in [(30, 50, 0), (70, 20, 90), (5, 85, 180)]:
        a = body(Z, dirs(tl, dp), dirs(tv, 0), t)
        b = body(Z, dirs(tl, dp), dirs(tv, 0), tk)
        assert torch.allclose(a, b.detach(), rtol=1e-6, atol=1e-12)


def _collapsed_body_s0(theta_v, theta_l, dphi, alpha, beta, mu):
    """κ → ∞ limit (spec §7): f(n, n_i) D(n) → δ(n − n_i), so
    J∞ = ∫ [n·V]₊ [n·L]₊ D(n) T+(θ_o) T+(θ_i) dω_n; s0 = (1/π)(N·L) J∞ / (P(V) P(L)).
    Independent dense quadrature (θ composite Gauss–Legendre, φ uniform)."""
    a, b = torch.tensor(alpha, dtype=F64), torch.tensor(beta, dtype=F64)
    c = d_normalisation(a, b)
    tq, wq = theta_rule(alpha, beta, 10, max_width=0.02)
    th = torch.tensor(tq)[:, None]
    ph = torch.linspace(0, 2 * math.pi, 4097, dtype=F64)[:-1][None, :]
    nvec = torch.stack([torch.sin(th) * torch.cos(ph), torch.sin(th) * torch.sin(ph), torch.cos(th).expand(-1, ph.shape[1])], -1)
    v, l = dirs(theta_v, 0), dirs(theta_l, dphi)
    co, ci = (nvec @ v).clamp_min(0), (nvec @ l).clamp_min(0)
    integrand = co * ci * fresnel(co, mu).t_plus * fresnel(ci, mu).t_plus * c * d_shape(th, a, b) * torch.sin(th)
    j = (integrand.sum(-1) * (2 * math.pi / 4096) * torch.tensor(wq)).sum()
    pv = projected_area_exact(torch.tensor(math.radians(theta_v), dtype=F64), a, b, c)
    pl = projected_area_exact(torch.tensor(math.radians(theta_l), dtype=F64), a, b, c)
    return float(math.cos(math.radians(theta_l)) * j / (math.pi * pv * pl))


@pytest.fixture(scope="module")
def kappa_tables():
    return {k: build_tables(ior=1.5, alpha=0.4, beta=2.0, kappa=k) for k in (5.0, 50.0, 400.0)}


@pytest.mark.parametrize("geom", [(30, 40, 0), (60, 50, 90), (20, 70, 180)])
def test_large_kappa_collapses_onto_single_integral(geom, kappa_tables):
    tv, tl, dp = geom
    target = _collapsed_body_s0(tv, tl, dp, 0.4, 2.0, 1.5)
    errs = []
    for kappa, t in kappa_tables.items():
        s0 = float(fmbrdf_stokes(Z, dirs(tl, dp), dirs(tv, 0), ior=1.5, k_s=0.0, k_b=1.0, alpha=0.4, beta=2.0, kappa=kappa, tables=t)[0])
        errs.append(abs(s0 / target - 1.0))
    assert errs[2] < min(errs[:2]) and errs[2] < 0.01, errs


def _flat_body(theta_v, theta_l, mu):
    """α → 0 (spec §7): (1/π) T+(θ_L) T-Stokes(θ_V) (N·L); returns (s0, DoLP)."""
    fl = fresnel(torch.tensor(math.cos(math.radians(theta_l)), dtype=F64), mu)
    fv = fresnel(torch.tensor(math.cos(math.radians(theta_v)), dtype=F64), mu)
    s0 = float(fl.t_plus * fv.t_plus) * math.cos(math.radians(theta_l)) / math.pi
    return s0, float(-fv.t_minus / fv.t_plus)


@pytest.mark.parametrize("kappa", [0.0, 50.0])
def test_small_alpha_gives_flat_body_term(kappa):
    for tv, tl, dp in [(20, 30, 0), (50, 40, 120), (70, 10, 60)]:
        ref_s0, ref_dolp = _flat_body(tv, tl, 1.6)
        errs = []
        for alpha in (0.1, 0.01):
            s = fmbrdf_stokes(Z, dirs(tl, dp), dirs(tv, 0), ior=1.6, k_s=0.0, k_b=1.0, alpha=alpha, beta=2.0, kappa=kappa)
            errs.append(abs(float(s[0]) / ref_s0 - 1.0))
        assert errs[1] < errs[0] and errs[1] < 2e-3, errs
        assert float(dolp(s, dim=-1, eps=0.0)) == pytest.approx(ref_dolp, abs=2e-3)


@pytest.mark.parametrize("alpha,beta", [(0.3, 2.0), (1.0, 0.7)])
def test_zero_body_dolp_at_normal_view_for_kappa_zero(alpha, beta):
    t = build_tables(ior=1.5, alpha=alpha, beta=beta, kappa=0.0)
    n = torch.tensor([0.0, 0.0, -1.0], dtype=F64)
    for l in (dirs(150, 0), dirs(120, 40), dirs(100, 250)):  # lights in front of n = −z
        s = body(n, l, n, t)
        assert float(dolp(s, dim=-1, eps=0.0)) < 1e-6


def test_specular_aolp_perpendicular_and_body_aolp_parallel_to_plane_of_incidence():
    """Orthographic camera, lights in the plane of N and V (the plane of incidence)."""
    rng = np.random.default_rng(3)
    v = torch.tensor([0.0, 0.0, -1.0], dtype=F64)
    phi = torch.tensor(rng.uniform(0, 2 * math.pi, 50), dtype=F64)
    tilt = torch.tensor(rng.uniform(0.2, 1.2, 50), dtype=F64)
    n = around(v.expand(50, 3), tilt, phi)
    azimuth = torch.atan2(n[:, 1], n[:, 0])  # plane of incidence in the image (y down)
    l_mirror = 2 * (n @ v)[:, None] * n - v  # specular direction: H = N
    t = build_tables(ior=1.5, alpha=0.2, beta=2.0, kappa=0.0)
    spec = fmbrdf_stokes(n, l_mirror, v, ior=1.5, k_s=1.0, k_b=0.0, alpha=0.2, beta=2.0, kappa=0.0, tables=t)
    assert float(angle_diff_mod_pi(aolp(spec, dim=-1), azimuth + math.pi / 2).max()) < 1e-6
    bod = fmbrdf_stokes(n, v.expand(50, 3), v, ior=1.5, k_s=0.0, k_b=1.0, alpha=0.2, beta=2.0, kappa=0.0, tables=t)
    assert float(angle_diff_mod_pi(aolp(bod, dim=-1), azimuth).max()) < 1e-3


@pytest.mark.parametrize("alpha,beta,kappa", [(0.05, 2.0, 0.0), (0.4, 2.0, 30.0), (1.5, 1.0, 100.0), (0.3, 0.5, 0.0)])
def test_energy_conservation(alpha, beta, kappa):
    """Directional-hemispherical reflectance ∫ s0 (N·V) dω_V ≤ N·L for k_s = k_b = 1 (mid-point rule)."""
    t = build_tables(ior=1.5, alpha=alpha, beta=beta, kappa=kappa)
    nt, npp = 96, 192
    tv = (torch.arange(nt, dtype=F64) + 0.5) * (math.pi / 2 / nt)
    pv = (torch.arange(npp, dtype=F64) + 0.5) * (2 * math.pi / npp)
    tt, pp = torch.meshgrid(tv, pv, indexing="ij")
    v = torch.stack([torch.sin(tt) * torch.cos(pp), torch.sin(tt) * torch.sin(pp), torch.cos(tt)], -1).reshape(-1, 3)
    dw = (torch.sin(tt) * (math.pi / 2 / nt) * (2 * math.pi / npp)).reshape(-1)
    for theta_l in (0.0, 45.0, 80.0):
        l = dirs(theta_l, 30)
        s = fmbrdf_stokes(Z, l, v, ior=1.5, k_s=1.0, k_b=1.0, alpha=alpha, beta=beta, kappa=kappa, tables=t)
        albedo = float((s[:, 0] * v[:, 2] * dw).sum()) / math.cos(math.radians(theta_l))
        assert 0.0 < albedo <= 1.0 + 1e-3, albedo


def test_tables_reused_equal_fresh():
    rng = np.random.default_rng(4)
    n, l, v = random_geometry(rng, 100)
    p = dict(ior=1.7, k_s=0.5, k_b=0.8, alpha=0.25, beta=1.5, kappa=20.0)
    t = build_tables(ior=1.7, alpha=0.25, beta=1.5, kappa=20.0)
    assert torch.equal(fmbrdf_stokes(n, l, v, **p), fmbrdf_stokes(n, l, v, **p, tables=t))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    rng = np.random.default_rng(5)
    n, l, v = random_geometry(rng, 1000)
    p = dict(ior=1.5, k_s=1.0, k_b=0.5, alpha=0.3, beta=2.0, kappa=30.0)
    cpu = fmbrdf_stokes(n, l, v, **p)
    gpu = fmbrdf_stokes(n.cuda(), l.cuda(), v.cuda(), **p)
    assert torch.allclose(cpu, gpu.cpu(), rtol=1e-6, atol=1e-9)
