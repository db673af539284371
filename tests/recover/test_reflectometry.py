"""Tests of polarshape.recover.reflectometry: closed-form albedos, eq. 25 weights, fits with known normals."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.brdf import build_tables, fmbrdf_stokes
from polarshape.brdf.params import FMBRDFParams
from polarshape.recover.observations import Observations
from polarshape.recover.reflectometry import (
    eq25_loss,
    eq25_weights,
    fit_reflectance,
    huber,
    objective,
    render_parts,
    solve_albedos,
)


def _scene(p: int = 400, k: int = 10, seed: int = 0, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor, Tensor]:
    gen = torch.Generator().manual_seed(seed)
    # normals over a hemisphere facing the camera (n_z < 0), lights at 10–55° from the view axis
    theta = torch.rand(p, generator=gen, dtype=dtype) * 1.2
    phi = torch.rand(p, generator=gen, dtype=dtype) * 2 * math.pi
    normals = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), -theta.cos()], -1)
    lt = torch.linspace(0.17, 0.95, k, dtype=dtype)
    lp = torch.arange(k, dtype=dtype) * 2.4
    lights = torch.stack([lt.sin() * lp.cos(), lt.sin() * lp.sin(), -lt.cos()], -1)
    view = torch.tensor([0.0, 0.0, -1.0], dtype=dtype).expand(p, 3)
    return normals, lights, view


Tensor = torch.Tensor


def _observe(normals: Tensor, lights: Tensor, view: Tensor, truth: dict, k_b: Tensor, noise: float = 0.0, seed: int = 1) -> Observations:
    s = fmbrdf_stokes(normals[:, None], lights[None], view[:, None], k_b=k_b[:, None], **truth)  # (P, K, 3)
    if noise:
        gen = torch.Generator().manual_seed(seed)
        s = s + noise * torch.randn(s.shape, generator=gen, dtype=s.dtype)
    p, k = s.shape[:2]
    return Observations(s, torch.ones(p, k, dtype=s.dtype), lights.expand(p, k, 3), torch.ones(p, k, dtype=s.dtype), view)


@pytest.mark.parametrize("kappa", [0.0, 20.0])
def test_render_parts_sum_to_fmbrdf(kappa: float) -> None:
    n, l, v = _scene(50, 6)
    tables = build_tables(ior=1.5, alpha=0.3, beta=2.0, kappa=kappa)
    obs = _observe(n, l, v, dict(ior=1.5, k_s=1.0, alpha=0.3, beta=2.0, kappa=kappa), torch.full((50,), 0.5, dtype=n.dtype))
    surf, body = render_parts(tables, n, obs)
    torch.testing.assert_close(surf * 1.0 + 0.5 * body, obs.stokes, atol=1e-10, rtol=1e-8)


def test_render_parts_chunks_and_autograd_give_the_same_parts(monkeypatch: pytest.MonkeyPatch) -> None:
    """Chunks of a few pixels (without autograd) give the parts of one chunk for everything, and the
    autograd path (one chunk) the same parts, with normal gradients independent of the chunk setting."""
    import polarshape.recover.reflectometry as reflectometry

    n, l, v = _scene(40, 5)
    tables = build_tables(ior=1.5, alpha=0.3, beta=2.0, kappa=20.0)
    gen = torch.Generator().manual_seed(2)
    obs = Observations(torch.zeros(40, 5, 3, dtype=n.dtype), torch.ones(40, 5, dtype=n.dtype), l.expand(40, 5, 3),
                       0.5 + torch.rand(40, 5, generator=gen, dtype=n.dtype), v)
    results = []
    for chunk in (1 << 30, 7 * 5 + 3):  # one chunk; chunks of 7 pixels (the last one shorter)
        monkeypatch.setattr(reflectometry, "RENDER_CHUNK", chunk)
        with torch.no_grad():
            parts = render_parts(tables, n, obs)
        nn = n.clone().requires_grad_(True)
        surf, body = render_parts(tables, nn, obs)
        (surf * surf.detach().sign()).sum().add(body.sum()).backward()
        results.append((*parts, surf.detach(), body.detach(), nn.grad))
    for a, b in zip(results[0][:4], results[1][:4]):
        torch.testing.assert_close(a, b, rtol=1e-15, atol=0.0)
    torch.testing.assert_close(results[0][4], results[1][4], rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(results[0][0], results[0][2], rtol=1e-15, atol=0.0)


@pytest.mark.parametrize("per_pixel", [True, False])
def test_solve_albedos_exact_on_noise_free_data(per_pixel: bool) -> None:
    n, l, v = _scene(80, 8)
    gen = torch.Generator().manual_seed(3)
    k_b = 0.2 + torch.rand(80, generator=gen, dtype=n.dtype) if per_pixel else torch.full((80,), 0.7, dtype=n.dtype)
    obs = _observe(n, l, v, dict(ior=1.5, k_s=2.0, alpha=0.3, beta=2.0, kappa=0.0), k_b)
    surf, body = render_parts(build_tables(ior=1.5, alpha=0.3, beta=2.0, kappa=0.0), n, obs)
    k_s_fit, k_b_fit = solve_albedos(surf, body, obs, per_pixel=per_pixel)
    assert abs(float(k_s_fit) - 2.0) < 1e-8
    lit = body[..., 0].sum(1) > 0
    torch.testing.assert_close(k_b_fit[lit], k_b[lit], atol=1e-8, rtol=1e-8)


def test_huber_is_quadratic_then_linear() -> None:
    r = torch.tensor([0.5, -1.0, 3.0])
    torch.testing.assert_close(huber(r, 1.0), torch.tensor([0.125, 0.5, 2.5]))


def test_eq25_weights_change_outlier_weights() -> None:
    dolp = torch.cat([torch.full((95,), 0.05), torch.full((5,), 0.6)])
    dolp = dolp + 0.001 * torch.arange(100) / 100  # some spread for the MAD
    valid = torch.ones(100, dtype=torch.bool)
    valid[0] = False
    w = eq25_weights(dolp, valid)
    assert float(w[0]) == 0.0
    torch.testing.assert_close(w[1:95], torch.ones(94))
    torch.testing.assert_close(w[95:], torch.full((5,), 94 / 5))  # inliers / outliers
    # all alike: no outliers, weights are the validity
    same = eq25_weights(torch.full((10,), 0.1), torch.ones(10, dtype=torch.bool))
    torch.testing.assert_close(same, torch.ones(10))


def test_eq25_loss_zero_at_truth_and_positive_off() -> None:
    s = torch.tensor([[1.0, 0.1, 0.0], [0.5, 0.0, 0.05]])
    valid = torch.ones(2, dtype=torch.bool)
    w = torch.ones(2)
    assert float(eq25_loss(s, s, valid, w)) == pytest.approx(0.0, abs=1e-10)
    assert float(eq25_loss(s * torch.tensor([1.1, 1.0, 1.0]), s, valid, w)) > 0


@pytest.mark.parametrize("alpha", [0.05, 0.3, 0.8])
def test_fit_recovers_parameters_with_known_normals(alpha: float) -> None:
    n, l, v = _scene(600, 12)
    gen = torch.Generator().manual_seed(5)
    k_b = 0.3 + 0.4 * torch.rand(600, generator=gen, dtype=n.dtype)
    truth = dict(ior=1.6, k_s=1.0, alpha=alpha, beta=2.0, kappa=0.0)
    obs = _observe(n, l, v, truth, k_b, noise=1e-3)
    fit = fit_reflectance(n, obs, delta=3e-3)
    assert abs(fit.params.ior - 1.6) <= 0.05
    assert abs(fit.params.alpha - alpha) <= 0.1 * alpha
    assert abs(fit.params.k_s - 1.0) <= 0.1
    lit = obs.stokes[..., 0].amax(1) > 0.05
    assert float((fit.k_b[lit] - k_b[lit]).abs().median()) < 0.02
    assert fit.loss <= objective(FMBRDFParams(ior=1.5, alpha=0.5, beta=2.0), n, obs, delta=3e-3)


def test_fit_global_albedo_and_eq25_objective() -> None:
    n, l, v = _scene(300, 10)
    k_b = torch.full((300,), 0.5, dtype=n.dtype)
    obs = _observe(n, l, v, dict(ior=1.5, k_s=1.0, alpha=0.25, beta=2.0, kappa=0.0), k_b)
    fit = fit_reflectance(n, obs, per_pixel_albedo=False)
    assert fit.params.k_b == pytest.approx(0.5, rel=0.02)
    assert abs(fit.params.alpha - 0.25) < 0.025
    fit25 = fit_reflectance(n, obs, per_pixel_albedo=False, objective_kind="eq25")
    assert abs(fit25.params.alpha - 0.25) < 0.05
    assert fit25.loss < 1e-3


def test_fit_kappa_only_parameters_requested_move() -> None:
    n, l, v = _scene(200, 8)
    obs = _observe(n, l, v, dict(ior=1.5, k_s=1.0, alpha=0.3, beta=2.0, kappa=0.0), torch.full((200,), 0.5, dtype=n.dtype))
    fit = fit_reflectance(n, obs, init=FMBRDFParams(ior=1.4, alpha=0.35, beta=2.5), grid_search=False, fit_names=("alpha",))
    assert fit.params.ior == 1.4 and fit.params.beta == 2.5
    assert fit.params.alpha != 0.35
    assert all(math.isfinite(v) for v in fit.params.as_dict().values())


@pytest.mark.parametrize("start", [dict(ior=1.05, alpha=0.01, beta=0.4), dict(ior=3.0, alpha=2.5, beta=6.0, kappa=100.0)])
def test_fit_from_parameter_bounds_stays_finite(start: dict) -> None:
    n, l, v = _scene(150, 8)
    obs = _observe(n, l, v, dict(ior=1.5, k_s=1.0, alpha=0.3, beta=2.0, kappa=0.0), torch.full((150,), 0.5, dtype=n.dtype))
    fit = fit_reflectance(n, obs, init=FMBRDFParams(**start), grid_search=False, fit_kappa="kappa" in start, max_iter=3)
    assert all(math.isfinite(x) for x in fit.params.as_dict().values())
    assert math.isfinite(fit.loss) and bool(torch.isfinite(fit.k_b).all())


@pytest.mark.parametrize("alpha", [0.05, 0.3])
def test_fit_from_a_single_polarimetric_image(alpha: float) -> None:
    """One light (K = 1): the normals' spread across the object still constrains the material
    (measured, per-pixel albedo: α 0.0494 / 0.308, μ 1.600 / 1.598 for truth 0.05 / 0.3, 1.6;
    α = 0.8 is weakly constrained by one image: μ 1.52)."""
    n, l, v = _scene(2000, 3)
    gen = torch.Generator().manual_seed(5)
    k_b = 0.3 + 0.4 * torch.rand(2000, generator=gen, dtype=n.dtype)
    obs = _observe(n, l[1:2], v, dict(ior=1.6, k_s=1.0, alpha=alpha, beta=2.0, kappa=0.0), k_b, noise=1e-3)
    assert obs.stokes.shape[1] == 1
    fit = fit_reflectance(n, obs, delta=3e-3)
    assert abs(fit.params.ior - 1.6) <= 0.05, fit.params
    assert abs(fit.params.alpha - alpha) <= 0.1 * alpha, fit.params
    assert abs(fit.params.k_s - 1.0) <= 0.1, fit.params
    assert bool(torch.isfinite(fit.k_b).all())


def test_reported_body_albedo_is_robust_to_a_few_absurd_pixels() -> None:
    """FMBRDFParams.k_b from a per-pixel fit is the median: 2 % of pixels with a 100× albedo (what a
    block straddling a texture edge can get) leave it at the bulk's value; the mean would not."""
    n, l, v = _scene(400, 10)
    k_b = torch.full((400,), 0.5, dtype=n.dtype)
    k_b[::50] = 50.0
    obs = _observe(n, l, v, dict(ior=1.5, k_s=1.0, alpha=0.3, beta=2.0, kappa=0.0), k_b)
    fit = fit_reflectance(n, obs, init=FMBRDFParams(ior=1.5, alpha=0.3, beta=2.0), grid_search=False, max_iter=2)
    assert float(fit.k_b.mean()) > 1.0  # the per-pixel albedos do hold the outliers
    assert fit.params.k_b == pytest.approx(0.5, rel=0.02)
