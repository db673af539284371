"""Tests for polarshape.recover.polarization_cues (azimuth/zenith from AoLP/DoLP, disambiguation)."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.recover.polarization_cues import (
    azimuth_candidates,
    diffuse_dolp,
    disambiguate_azimuth,
    normal_azimuth,
    normals_from_angles,
    normals_from_polarization,
    select_closest_normal,
    specular_dolp,
    stokes_to_aolp_dolp,
    zenith_from_diffuse_dolp,
    zenith_from_specular_dolp,
)

DTYPES = [torch.float32, torch.float64]
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
IOR = 1.5


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.linalg.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1))


def _wrap_pi(x: torch.Tensor) -> torch.Tensor:
    """Wrap to (−π/2, π/2]: difference modulo π."""
    return torch.atan2(torch.sin(2 * x), torch.cos(2 * x)) / 2


def _rho_diffuse_reference(theta: torch.Tensor, mu: float) -> torch.Tensor:
    """The brief's formula, written out independently of the module."""
    s = torch.sin(theta)
    num = (mu - 1 / mu) ** 2 * s**2
    den = 2 + 2 * mu**2 - (mu + 1 / mu) ** 2 * s**2 + 4 * torch.cos(theta) * torch.sqrt(mu**2 - s**2)
    return num / den


def _fresnel(theta: torch.Tensor, mu: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Power reflectances R_s, R_p for light from air at incidence theta."""
    ci = torch.cos(theta)
    ct = torch.sqrt(1 - (torch.sin(theta) / mu) ** 2)
    r_s = (ci - mu * ct) / (ci + mu * ct)
    r_p = (mu * ci - ct) / (mu * ci + ct)
    return r_s**2, r_p**2


def _grid(dtype: torch.dtype, zen_lo: float = 2.0, zen_hi: float = 88.0, n_zen: int = 40, n_az: int = 36):
    """Normals (Z, A, 3) on a zenith × azimuth grid (orthographic, n_z < 0); zenith, azimuth (Z, A)."""
    zen = torch.deg2rad(torch.linspace(zen_lo, zen_hi, n_zen, dtype=torch.float64))
    az = torch.linspace(-math.pi + 0.05, math.pi - 0.05, n_az, dtype=torch.float64)
    zz, aa = torch.meshgrid(zen, az, indexing="ij")
    normals = torch.stack([zz.sin() * aa.cos(), zz.sin() * aa.sin(), -zz.cos()], dim=-1)
    return normals.to(dtype), zz.to(dtype), aa.to(dtype)


def _diffuse_stokes(normals: torch.Tensor, mu: float, s0: float = 0.8) -> torch.Tensor:
    """Spec §5 transmitted Stokes: s0 (1, −(T−/T+) cos 2ψ, −(T−/T+) sin 2ψ), −T−/T+ = ρ_d."""
    n64 = normals.double()
    theta = torch.atan2(n64[..., :2].norm(dim=-1), -n64[..., 2])
    psi = torch.atan2(n64[..., 1], n64[..., 0])
    rho = _rho_diffuse_reference(theta, mu)
    stokes = s0 * torch.stack(
        [torch.ones_like(rho), rho * torch.cos(2 * psi), rho * torch.sin(2 * psi)], dim=-1
    )
    return stokes.to(normals.dtype)


def _specular_stokes(normals: torch.Tensor, mu: float) -> torch.Tensor:
    """Spec §5 reflected Stokes: R+ (1, −(R−/R+) cos 2ψ, −(R−/R+) sin 2ψ)."""
    n64 = normals.double()
    theta = torch.atan2(n64[..., :2].norm(dim=-1), -n64[..., 2])
    psi = torch.atan2(n64[..., 1], n64[..., 0])
    r_s, r_p = _fresnel(theta, mu)
    r_plus, r_minus = (r_s + r_p) / 2, (r_s - r_p) / 2
    stokes = torch.stack([r_plus, -r_minus * torch.cos(2 * psi), -r_minus * torch.sin(2 * psi)], dim=-1)
    return stokes.to(normals.dtype)


def _perturb(normals: torch.Tensor, angle_deg: float, seed: int) -> torch.Tensor:
    """Rotate each normal by exactly angle_deg about a random axis perpendicular to it."""
    gen = torch.Generator().manual_seed(seed)
    rand = torch.randn(normals.shape, generator=gen, dtype=torch.float64).to(normals.dtype)
    axis = torch.linalg.cross(normals, rand, dim=-1)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    delta = math.radians(angle_deg)
    return math.cos(delta) * normals + math.sin(delta) * axis


# ------------------------------------------------------------------------------------------
# DoLP models
# ------------------------------------------------------------------------------------------


def test_diffuse_dolp_matches_formula_and_fresnel_transmission() -> None:
    theta = torch.linspace(0.0, math.radians(89.5), 200, dtype=torch.float64)
    for mu in (1.3, 1.5, 1.9):
        rho = diffuse_dolp(theta, mu)
        torch.testing.assert_close(rho, _rho_diffuse_reference(theta, mu))
        r_s, r_p = _fresnel(theta, mu)
        t_s, t_p = 1 - r_s, 1 - r_p
        torch.testing.assert_close(rho, (t_p - t_s) / (t_p + t_s))  # = −T−/T+ (spec §5)
        assert bool((rho.diff() > 0).all()), "ρ_d must increase with the zenith"
    torch.testing.assert_close(
        diffuse_dolp(torch.tensor(math.pi / 2, dtype=torch.float64), IOR),
        torch.tensor((IOR**2 - 1) / (IOR**2 + 1), dtype=torch.float64),
    )


def test_specular_dolp_is_fresnel_ratio_with_brewster_peak() -> None:
    theta = torch.linspace(0.0, math.radians(89.5), 200, dtype=torch.float64)
    r_s, r_p = _fresnel(theta, IOR)
    torch.testing.assert_close(specular_dolp(theta, IOR), (r_s - r_p) / (r_s + r_p))
    brewster = torch.tensor(math.atan(IOR), dtype=torch.float64)
    torch.testing.assert_close(specular_dolp(brewster, IOR), torch.tensor(1.0, dtype=torch.float64))


@pytest.mark.parametrize("dtype", DTYPES)
def test_zenith_inversions_round_trip(dtype: torch.dtype) -> None:
    theta = torch.linspace(0.0, math.radians(89.0), 300, dtype=torch.float64)
    mu = torch.tensor([1.3, 1.5, 1.8], dtype=torch.float64)[:, None]  # tensor ior broadcasts
    rho = diffuse_dolp(theta, mu).to(dtype)
    zen, in_range = zenith_from_diffuse_dolp(rho, mu.to(dtype))
    assert zen.dtype == dtype and bool(in_range.all())
    # ρ_d ∝ θ² near 0: a rounding of ρ moves θ by ~eps/θ, so compare away from 0 in float32
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    near_zero = theta < (math.radians(2.0) if dtype == torch.float32 else 1e-6)
    err = (zen.double() - theta).abs()[:, ~near_zero]
    assert float(err.max()) < tol, f"max zenith error {float(err.max()):.2e} rad"

    spec_theta = torch.cat(
        [torch.linspace(0.05, math.atan(IOR) - 0.05, 50), torch.linspace(math.atan(IOR) + 0.05, 1.5, 50)]
    ).double()
    branches, ok = zenith_from_specular_dolp(specular_dolp(spec_theta, IOR).to(dtype), IOR)
    assert branches.shape == (100, 2) and bool(ok.all())
    best = (branches.double() - spec_theta[:, None]).abs().min(-1).values
    assert float(best.max()) < (1e-4 if dtype == torch.float32 else 1e-9)
    assert bool((branches[:, 0] <= branches[:, 1]).all())
    # the other branch is genuinely different (the ambiguity is real) and has the same DoLP
    torch.testing.assert_close(
        specular_dolp(branches[:, 0], IOR), specular_dolp(branches[:, 1], IOR), atol=2e-5, rtol=1e-4
    )


def test_out_of_range_dolp_is_clamped_and_flagged() -> None:
    dolp = torch.tensor([-0.1, 0.0, 0.2, 0.5, 1.5, math.nan, math.inf], dtype=torch.float64)
    zen, ok = zenith_from_diffuse_dolp(dolp, IOR)  # max ρ_d = 0.3846 for μ = 1.5
    assert ok.tolist() == [False, True, True, False, False, False, False]
    assert bool(torch.isfinite(zen).all())
    assert float(zen[0]) < 1e-12 and float(zen[5]) < 1e-12
    torch.testing.assert_close(zen[3], torch.tensor(math.pi / 2, dtype=torch.float64), atol=1e-9, rtol=0)
    branches, ok_s = zenith_from_specular_dolp(dolp, IOR)
    assert ok_s.tolist() == [False, True, True, True, False, False, False]
    assert bool(torch.isfinite(branches).all())
    torch.testing.assert_close(
        branches[4], torch.full((2,), math.atan(IOR), dtype=torch.float64), atol=1e-9, rtol=0
    )
    with pytest.raises(ValueError, match="ior"):
        zenith_from_diffuse_dolp(dolp, 1.0)


# ------------------------------------------------------------------------------------------
# AoLP, azimuth candidates, disambiguation
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_diffuse_azimuth_and_zenith_recovered(dtype: torch.dtype) -> None:
    normals, zen, az = _grid(dtype)
    stokes = _diffuse_stokes(normals, IOR)
    aolp, dolp = stokes_to_aolp_dolp(stokes)
    # azimuth = AoLP (mod π), exactly
    assert float(_wrap_pi(aolp.double() - az.double()).abs().max()) < (
        1e-5 if dtype == torch.float32 else 1e-12
    )
    candidates = azimuth_candidates(aolp, "diffuse")
    hit = _wrap_pi(candidates - az.unsqueeze(-1)).abs().min(-1).values
    assert float(hit.max()) < 1e-5
    assert float(((candidates[..., 0] - candidates[..., 1]).abs() - math.pi).abs().max()) < 1e-5
    zenith, ok = zenith_from_diffuse_dolp(dolp, IOR)
    assert bool(ok.all())
    mask = zen.double() > math.radians(5.0) if dtype == torch.float32 else torch.ones_like(ok)
    err = (zenith.double() - zen.double()).abs()[mask]
    assert float(err.max()) < 1e-4, f"max zenith error {float(err.max()):.2e} rad"


@pytest.mark.parametrize("dtype", DTYPES)
def test_disambiguation_with_noisy_reference_restores_normal(dtype: torch.dtype) -> None:
    # a reference 20° off cannot be nearer the wrong (π-flipped) azimuth once the zenith is > 20°
    normals, _, _ = _grid(dtype, zen_lo=25.0, zen_hi=88.0)
    stokes = _diffuse_stokes(normals, IOR)
    reference = _perturb(normals, 20.0, seed=3)
    assert float(torch.rad2deg(_angle(reference, normals)).min()) > 19.9
    result = normals_from_polarization(stokes, reference, IOR, model="diffuse", dolp_noise=0.005)
    err = _angle(result.normals.double(), normals.double())
    assert float(err.max()) < 1e-4, f"max error {float(err.max()):.2e} rad"
    torch.testing.assert_close(result.normals.norm(dim=-1), torch.ones(normals.shape[:-1], dtype=dtype))
    assert result.normals.dtype == dtype
    # the azimuth-only helper agrees
    aolp, _ = stokes_to_aolp_dolp(stokes)
    chosen, index = disambiguate_azimuth(azimuth_candidates(aolp), reference)
    torch.testing.assert_close(torch.cos(chosen), torch.cos(normal_azimuth(normals)), atol=1e-5, rtol=0)
    assert index.dtype == torch.int64
    # without the reference the flipped candidate would be wrong by 2θ: the choice matters
    flipped = normals_from_polarization(stokes, -reference * torch.tensor([1.0, 1.0, -1.0], dtype=dtype), IOR)
    assert float(_angle(flipped.normals.double(), normals.double()).min()) > math.radians(40.0)


def test_confidence_tracks_dolp_and_margin() -> None:
    normals, zen, _ = _grid(torch.float64, zen_lo=10.0, zen_hi=80.0, n_zen=8, n_az=12)
    stokes = _diffuse_stokes(normals, IOR)
    result = normals_from_polarization(stokes, normals, IOR, dolp_noise=0.01)
    conf_by_zenith = result.confidence.mean(-1)
    assert bool((conf_by_zenith.diff() > 0).all()), conf_by_zenith.tolist()  # grows with DoLP
    assert float(result.confidence[0].max()) < 0.5 and float(result.confidence[-1].min()) > 0.9
    assert bool(((result.confidence >= 0) & (result.confidence <= 1)).all())
    # a reference at 90° in azimuth to the truth is equidistant from both candidates → 0 margin
    sideways = normals_from_angles(zen, normal_azimuth(normals) + math.pi / 2)
    ambiguous = normals_from_polarization(stokes, sideways, IOR, dolp_noise=0.01)
    assert float(ambiguous.confidence.max()) < 1e-6


def test_specular_aolp_perpendicular_to_azimuth() -> None:
    normals, zen, az = _grid(torch.float64, zen_lo=10.0, zen_hi=85.0)
    stokes = _specular_stokes(normals, IOR)
    aolp, dolp = stokes_to_aolp_dolp(stokes)
    # AoLP ⟂ azimuth: the difference is π/2 modulo π
    offset = _wrap_pi(aolp - az)
    assert float((offset.abs() - math.pi / 2).abs().max()) < 1e-9
    candidates = azimuth_candidates(aolp, "specular")
    assert float(_wrap_pi(candidates - az.unsqueeze(-1)).abs().min(-1).values.max()) < 1e-9
    diffuse_candidates = azimuth_candidates(aolp, "diffuse")  # the wrong model is 90° off
    assert float(_wrap_pi(diffuse_candidates - az.unsqueeze(-1)).abs().min(-1).values.min()) > 1.5
    branches, ok = zenith_from_specular_dolp(dolp, IOR)
    assert bool(ok.all())
    assert float((branches - zen.unsqueeze(-1)).abs().min(-1).values.max()) < 1e-6
    # with a reference 5° off, the closest of the 4 candidates is the true normal wherever the two
    # zenith branches are more than 15° apart (near Brewster's angle they merge: inherent)
    reference = _perturb(normals, 5.0, seed=4)
    result = normals_from_polarization(stokes, reference, IOR, model="specular")
    separated = (branches[..., 1] - branches[..., 0]) > math.radians(15.0)
    assert float(separated.float().mean()) > 0.6
    err = _angle(result.normals, normals)[separated]
    assert float(err.max()) < 1e-6


def test_zenith_from_reference_uses_aolp_azimuth_only() -> None:
    normals, zen, az = _grid(torch.float64, zen_lo=25.0, zen_hi=85.0, n_zen=6, n_az=10)
    stokes = _diffuse_stokes(normals, IOR)
    reference = normals_from_angles(zen + math.radians(3.0), az + math.radians(15.0))
    result = normals_from_polarization(stokes, reference, 1.2, zenith_from="reference")  # wrong μ: unused
    torch.testing.assert_close(result.zenith, zen + math.radians(3.0))
    torch.testing.assert_close(torch.cos(result.azimuth - az), torch.ones_like(az))


# ------------------------------------------------------------------------------------------
# Layouts, frames, robustness
# ------------------------------------------------------------------------------------------


def test_channel_first_layout_and_ambiguity() -> None:
    normals, _, _ = _grid(torch.float64, n_zen=5, n_az=7)
    stokes = _diffuse_stokes(normals, IOR)  # (5, 7, 3)
    aolp, dolp = stokes_to_aolp_dolp(stokes)
    aolp_cf, dolp_cf = stokes_to_aolp_dolp(stokes.permute(2, 0, 1))  # (3, 5, 7)
    torch.testing.assert_close(aolp_cf, aolp)
    torch.testing.assert_close(dolp_cf, dolp)
    result = normals_from_polarization(stokes.permute(2, 0, 1), normals, IOR)
    assert result.normals.shape == (5, 7, 3)
    with pytest.raises(ValueError, match="ambiguous"):
        stokes_to_aolp_dolp(torch.ones(3, 4, 3))
    a0, _ = stokes_to_aolp_dolp(torch.ones(3, 4, 3), channel_dim=0)
    assert a0.shape == (4, 3)
    with pytest.raises(ValueError, match="reference_normals must have shape"):
        normals_from_polarization(stokes, normals[:2], IOR)
    with pytest.raises(ValueError, match="model"):
        normals_from_polarization(stokes, normals, IOR, model="glossy")  # type: ignore[arg-type]


def test_perspective_view_frame_round_trip() -> None:
    gen = torch.Generator().manual_seed(5)
    p = 300
    view = torch.tensor([0.25, -0.15, -1.0], dtype=torch.float64) + 0.1 * torch.randn(
        p, 3, generator=gen, dtype=torch.float64
    )
    view = view / view.norm(dim=-1, keepdim=True)
    zen = torch.deg2rad(25.0 + 60.0 * torch.rand(p, generator=gen, dtype=torch.float64))
    az = (torch.rand(p, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi
    normals = normals_from_angles(zen, az, view)
    torch.testing.assert_close((normals * view).sum(-1), torch.cos(zen))
    torch.testing.assert_close(normal_azimuth(normals, view), az)
    rho = _rho_diffuse_reference(zen, IOR)
    stokes = torch.stack([torch.ones_like(rho), rho * torch.cos(2 * az), rho * torch.sin(2 * az)], dim=-1)
    result = normals_from_polarization(stokes, _perturb(normals, 15.0, seed=6), IOR, view_dirs=view)
    assert float(_angle(result.normals, normals).max()) < 1e-6
    # orthographic view_dirs equal the default
    ortho = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(p, 3)
    a = normals_from_polarization(stokes, normals, IOR, view_dirs=ortho)
    b = normals_from_polarization(stokes, normals, IOR)
    torch.testing.assert_close(a.normals, b.normals)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_degenerate_pixels_fall_back_to_reference(device: str, dtype: torch.dtype) -> None:
    stokes = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [-1.0, 0.1, 0.0],
            [math.nan, 0.1, 0.2],
            [1.0, math.inf, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.9, 0.0],
            [1e-30, 1e-30, 0.0],
        ],
        dtype=dtype,
        device=device,
    )
    reference = torch.tensor([[0.3, 0.1, -0.9]], dtype=dtype, device=device).expand(7, 3).clone()
    reference[1] = math.nan  # a broken reference as well
    for model in ("diffuse", "specular"):
        result = normals_from_polarization(stokes, reference, IOR, model=model)
        for field in ("normals", "confidence", "zenith", "azimuth", "aolp", "dolp"):
            assert bool(torch.isfinite(getattr(result, field)).all()), (model, field)
        torch.testing.assert_close(result.normals.norm(dim=-1), torch.ones(7, dtype=dtype, device=device))
        assert float(result.confidence[:4].abs().max()) == 0.0  # unusable Stokes
        ref_unit = reference[0] / reference[0].norm()
        torch.testing.assert_close(result.normals[0], ref_unit)
        assert float(result.confidence[4]) == 0.0  # DoLP 0: no information
    diffuse = normals_from_polarization(stokes, reference, IOR)
    assert not bool(diffuse.in_range[5]) and float(diffuse.confidence[5]) == 0.0  # DoLP 0.9 > ρ_max


def test_select_closest_normal_margin() -> None:
    ref = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    cands = torch.tensor([[[0.6, 0.0, -0.8], [0.0, 0.0, -1.0], [-0.6, 0.0, -0.8]]], dtype=torch.float64)
    normal, index, margin = select_closest_normal(cands, ref)
    assert int(index[0]) == 1 and float(margin[0]) == 1.0
    torch.testing.assert_close(normal, ref)
    _, _, tie = select_closest_normal(cands[:, [0, 2]], ref)
    assert float(tie[0]) == 0.0
