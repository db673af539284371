"""Tests for polarshape.recover.photometric (Lambertian photometric stereo, plain and robust)."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.recover.photometric import PSReason, lambertian_ps, robust_lambertian_ps

DTYPES = [torch.float32, torch.float64]
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
VIEW = (0.0, 0.0, -1.0)


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle between (..., 3) vectors in radians, via atan2 (stable near 0)."""
    return torch.atan2(torch.linalg.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1))


def _sphere(
    size: int = 48, dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Orthographic sphere: normals (H, W, 3) facing the camera (n_z < 0), mask (H, W), albedo (H, W)."""
    coords = torch.linspace(-1.0, 1.0, size, dtype=torch.float64)
    y, x = torch.meshgrid(coords, coords, indexing="ij")  # y down
    r2 = x**2 + y**2
    mask = r2 < 0.95
    normals = torch.stack([x, y, -(1.0 - r2).clamp_min(0.0).sqrt()], dim=-1)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    albedo = 0.4 + 0.3 * (x + 1.0) / 2.0  # spatially varying
    return normals.to(dtype), mask, albedo.to(dtype)


def _lights(k: int = 12, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """K unit directions surface → light around the view axis, elevations 30°/45°/60° from it."""
    theta = torch.deg2rad(torch.tensor([30.0, 45.0, 60.0] * ((k + 2) // 3), dtype=torch.float64)[:k])
    phi = torch.arange(k, dtype=torch.float64) * 2.0 * math.pi / k
    lights = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), -theta.cos()], dim=-1)
    return lights.to(dtype)


def _render(normals: torch.Tensor, albedo: torch.Tensor, lights: torch.Tensor) -> torch.Tensor:
    """Lambertian (K, P) intensities with attached shadows; normals (P, 3), albedo (P,)."""
    return albedo * (lights @ normals.T).clamp_min(0.0)


def _blinn_phong(normals: torch.Tensor, lights: torch.Tensor, k_s: float, shininess: float) -> torch.Tensor:
    """Specular lobe k_s (N·H)^shininess for lit observations, (K, P)."""
    view = torch.tensor(VIEW, dtype=normals.dtype)
    half = lights + view
    half = half / half.norm(dim=-1, keepdim=True)
    lit = (lights @ normals.T) > 0
    return k_s * (half @ normals.T).clamp_min(0.0) ** shininess * lit


@pytest.fixture()
def scene() -> dict[str, torch.Tensor]:
    normals_img, mask, albedo_img = _sphere()
    normals, albedo = normals_img[mask], albedo_img[mask]  # (P, 3), (P,)
    lights = _lights()
    clean = _render(normals, albedo, lights)
    all_lit = ((lights @ normals.T) > 0).all(0)
    return {"normals": normals, "albedo": albedo, "lights": lights, "clean": clean, "all_lit": all_lit}


# ------------------------------------------------------------------------------------------
# Accuracy on synthetic renders
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_noise_free_is_exact(dtype: torch.dtype) -> None:
    normals_img, mask, albedo_img = _sphere(dtype=torch.float64)
    normals, albedo = normals_img[mask], albedo_img[mask]
    lights = _lights()
    intensity = _render(normals, albedo, lights)
    assert not ((lights @ normals.T) > 0).all(), "the scene must contain attached shadows"
    all_lit = ((lights @ normals.T) > 0).all(0)

    # plain PS is exact where no light is shadowed
    n_plain, a_plain = lambertian_ps(intensity[:, all_lit].to(dtype), lights.to(dtype))
    err_plain = _angle(n_plain.double(), normals[all_lit])
    assert float(err_plain.max()) < 1e-4
    torch.testing.assert_close(a_plain.double(), albedo[all_lit], atol=1e-5, rtol=1e-5)

    # robust PS is exact everywhere (it drops the shadowed observations)
    result = robust_lambertian_ps(intensity.to(dtype), lights.to(dtype))
    assert bool(result.valid.all()), torch.bincount(result.reason).tolist()
    err = _angle(result.normals.double(), normals)
    assert float(err.max()) < 1e-4, f"max error {float(err.max()):.2e} rad"
    torch.testing.assert_close(result.albedo.double(), albedo, atol=1e-5, rtol=1e-5)
    assert result.normals.dtype == dtype and result.albedo.dtype == dtype


def test_noisy_mean_error_below_half_degree(scene: dict[str, torch.Tensor]) -> None:
    gen = torch.Generator().manual_seed(0)
    noisy = scene["clean"] + 0.002 * torch.randn(scene["clean"].shape, generator=gen, dtype=torch.float64)
    lit = scene["all_lit"]
    n_plain, _ = lambertian_ps(noisy[:, lit], scene["lights"])
    err_plain = torch.rad2deg(_angle(n_plain, scene["normals"][lit])).mean()
    assert float(err_plain) < 0.5, f"plain PS mean error {float(err_plain):.3f}° on unshadowed pixels"

    result = robust_lambertian_ps(noisy, scene["lights"], noise_std=0.002)
    valid_fraction = float(result.valid.float().mean())
    err = torch.rad2deg(_angle(result.normals, scene["normals"]))[result.valid].mean()
    assert valid_fraction > 0.97, f"only {valid_fraction:.3f} of the pixels valid"
    assert float(err) < 0.5, f"robust PS mean error {float(err):.3f}° (all pixels, shadows included)"


def test_specular_highlights_plain_degrades_robust_recovers(scene: dict[str, torch.Tensor]) -> None:
    gen = torch.Generator().manual_seed(1)
    spec = _blinn_phong(scene["normals"], scene["lights"], k_s=0.5, shininess=60.0)
    assert float((spec > 0.05).any(0).float().mean()) > 0.3, "highlights must touch many pixels"
    intensity = scene["clean"] + spec + 0.002 * torch.randn(spec.shape, generator=gen, dtype=torch.float64)

    n_plain, _ = lambertian_ps(intensity, scene["lights"])
    result = robust_lambertian_ps(intensity, scene["lights"], noise_std=0.002)
    plain_err = float(torch.rad2deg(_angle(n_plain, scene["normals"])).mean())
    robust_err = float(torch.rad2deg(_angle(result.normals, scene["normals"]))[result.valid].mean())
    # plain PS on the same pixels, shadow-free ones only, to separate highlights from shadows
    lit = scene["all_lit"]
    n_plain_lit, _ = lambertian_ps(intensity[:, lit], scene["lights"])
    plain_lit_err = float(torch.rad2deg(_angle(n_plain_lit, scene["normals"][lit])).mean())
    message = (
        f"plain PS {plain_err:.2f}° (unshadowed pixels {plain_lit_err:.2f}°), robust PS {robust_err:.2f}° "
        f"on {float(result.valid.float().mean()):.3f} valid pixels"
    )
    assert float(result.valid.float().mean()) > 0.95, message
    assert robust_err < 0.6, message
    assert plain_lit_err > 3.0 and plain_err > 5.0 * robust_err, message
    # the removed observations are the bright specular ones
    removed = ~result.used & (scene["clean"] > 0.02)
    assert float(spec[removed].mean()) > 10.0 * float(spec[result.used].mean()), message


# ------------------------------------------------------------------------------------------
# Shapes, light intensities, point lights, masks, flip rule
# ------------------------------------------------------------------------------------------


def test_image_shape_matches_flat_shape() -> None:
    normals_img, mask, albedo_img = _sphere(size=24)
    lights = _lights(9)
    flat_normals = normals_img.reshape(-1, 3)
    intensity = _render(flat_normals, albedo_img.reshape(-1), lights)  # (K, P)
    n_flat, a_flat = lambertian_ps(intensity, lights)
    n_img, a_img = lambertian_ps(intensity.reshape(9, 24, 24), lights)
    assert n_img.shape == (24, 24, 3) and a_img.shape == (24, 24)
    torch.testing.assert_close(n_img.reshape(-1, 3), n_flat)
    torch.testing.assert_close(a_img.reshape(-1), a_flat)
    robust = robust_lambertian_ps(intensity.reshape(9, 24, 24), lights, mask=mask)
    assert robust.normals.shape == (24, 24, 3) and robust.valid.shape == (24, 24)
    assert robust.used.shape == (9, 24, 24)
    assert bool((robust.reason[~mask] == PSReason.MASKED).all())
    assert bool(robust.valid[mask].all())
    torch.testing.assert_close(
        robust.normals[~mask], torch.tensor(VIEW, dtype=torch.float64).expand(int((~mask).sum()), 3)
    )
    assert float(robust.albedo[~mask].abs().max()) == 0.0


def test_light_intensity_is_divided_out(scene: dict[str, torch.Tensor]) -> None:
    lit = scene["all_lit"]
    power = torch.linspace(0.5, 2.0, 12, dtype=torch.float64)
    intensity = scene["clean"][:, lit] * power[:, None]
    normals, albedo = lambertian_ps(intensity, scene["lights"], light_intensity=power)
    assert float(_angle(normals, scene["normals"][lit]).max()) < 1e-8
    torch.testing.assert_close(albedo, scene["albedo"][lit])
    # ignoring the light powers gives a wrong answer: the parameter matters
    wrong, _ = lambertian_ps(intensity, scene["lights"])
    assert float(_angle(wrong, scene["normals"][lit]).mean()) > 1e-3


def test_point_lights_per_pixel_directions_and_falloff() -> None:
    gen = torch.Generator().manual_seed(2)
    p = 200
    points = torch.stack(
        [
            torch.rand(p, generator=gen, dtype=torch.float64) - 0.5,
            torch.rand(p, generator=gen, dtype=torch.float64) - 0.5,
            torch.full((p,), 2.0, dtype=torch.float64),
        ],
        dim=-1,
    )  # (P, 3) surface points, camera frame
    normals = torch.tensor([0.2, -0.1, -1.0], dtype=torch.float64) + 0.2 * torch.randn(
        p, 3, generator=gen, dtype=torch.float64
    )
    normals = normals / normals.norm(dim=-1, keepdim=True)
    positions = torch.tensor(
        [
            [0.6, 0.0, 0.0],
            [-0.6, 0.2, 0.0],
            [0.0, 0.6, 0.1],
            [0.1, -0.6, 0.0],
            [0.4, 0.4, -0.2],
            [-0.4, -0.4, 0.2],
        ],
        dtype=torch.float64,
    )  # (K, 3)
    to_light = positions[:, None, :] - points[None]  # (K, P, 3)
    dist2 = (to_light**2).sum(-1)
    directions = to_light / dist2.sqrt()[..., None]
    falloff = 1.0 / dist2  # (K, P)
    intensity = 0.7 * falloff * (directions * normals[None]).sum(-1).clamp_min(0.0)
    assert bool(((directions * normals[None]).sum(-1) > 0).all())
    result = robust_lambertian_ps(intensity, directions, light_intensity=falloff)
    assert bool(result.valid.all())
    assert float(_angle(result.normals, normals).max()) < 1e-8
    torch.testing.assert_close(result.albedo, torch.full((p,), 0.7, dtype=torch.float64))
    plain, _ = lambertian_ps(intensity, directions, light_intensity=falloff)
    assert float(_angle(plain, normals).max()) < 1e-8


def test_observation_mask_excludes_observations(scene: dict[str, torch.Tensor]) -> None:
    lit = scene["all_lit"]
    corrupted = scene["clean"][:, lit].clone()
    corrupted[0] += 0.3  # a bad first image
    keep = torch.ones_like(corrupted, dtype=torch.bool)
    keep[0] = False
    normals, _ = lambertian_ps(corrupted, scene["lights"], mask=keep)
    assert float(_angle(normals, scene["normals"][lit]).max()) < 1e-8
    unmasked, _ = lambertian_ps(corrupted, scene["lights"])
    assert float(_angle(unmasked, scene["normals"][lit]).mean()) > 1e-2


def test_flip_rule_mirrors_back_facing_solution() -> None:
    lights = torch.tensor(
        [[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]], dtype=torch.float64
    )
    back = torch.tensor([[0.3, 0.2, 0.0]], dtype=torch.float64)
    back[0, 2] = math.sqrt(1.0 - 0.13)  # n_z > 0: facing away from the camera
    intensity = 0.5 * (lights @ back.T)  # (K, 1), all positive
    normals, albedo = lambertian_ps(intensity, lights)
    expected = back * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    torch.testing.assert_close(normals, expected)
    torch.testing.assert_close(albedo, torch.tensor([0.5], dtype=torch.float64))
    result = robust_lambertian_ps(intensity, lights)
    assert int(result.reason[0]) == PSReason.BACK_FACING and not bool(result.valid[0])
    torch.testing.assert_close(result.normals, expected)
    # with a tilted view direction the mirror plane follows V
    view = torch.tensor([0.6, 0.0, -0.8], dtype=torch.float64)
    tilted, _ = lambertian_ps(intensity, lights, view_dirs=view)
    assert float((tilted[0] * view).sum()) >= 0.0
    torch.testing.assert_close(tilted[0] - back[0], -2.0 * float((back[0] * view).sum()) * view)


def test_saturated_observations_dropped_when_saturation_given(scene: dict[str, torch.Tensor]) -> None:
    lit = scene["all_lit"]
    bright = (scene["clean"][:, lit] * 2.5).clamp_max(1.0)  # clipped at 1
    assert bool((bright >= 1.0).any())
    result = robust_lambertian_ps(bright, scene["lights"], saturation=1.0)
    err_sat = _angle(result.normals, scene["normals"][lit])[result.valid]
    assert float(result.valid.float().mean()) > 0.9
    assert float(err_sat.max()) < 1e-6
    assert not bool((result.used & (bright >= 1.0)).any())


# ------------------------------------------------------------------------------------------
# Degenerate inputs and input validation
# ------------------------------------------------------------------------------------------


def _coplanar_lights() -> torch.Tensor:
    """Three directions in the x–z plane (through the origin): rank 2."""
    c = math.sqrt(0.5)
    return torch.tensor([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [-c, 0.0, -c]], dtype=torch.float64)


@pytest.mark.parametrize("solver", [lambertian_ps, robust_lambertian_ps])
def test_two_lights_raise(solver) -> None:
    lights = _lights(2)
    with pytest.raises(ValueError, match="at least 3 lights"):
        solver(torch.rand(2, 10, dtype=torch.float64), lights)


@pytest.mark.parametrize("solver", [lambertian_ps, robust_lambertian_ps])
def test_coplanar_lights_raise(solver) -> None:
    with pytest.raises(ValueError, match="coplanar"):
        solver(torch.rand(3, 10, dtype=torch.float64), _coplanar_lights())


def test_allow_degenerate_returns_finite_invalid() -> None:
    for lights in (_lights(2), _coplanar_lights(), _lights(1)):
        k = lights.shape[0]
        intensity = torch.rand(k, 5, 6, dtype=torch.float64)
        result = robust_lambertian_ps(intensity, lights, allow_degenerate=True)
        assert not bool(result.valid.any())
        assert bool(
            torch.isin(result.reason, torch.tensor([PSReason.TOO_FEW_LIGHTS, PSReason.ILL_CONDITIONED])).all()
        )
        assert bool(torch.isfinite(result.normals).all()) and bool(torch.isfinite(result.albedo).all())
        torch.testing.assert_close(result.normals.norm(dim=-1), torch.ones(5, 6, dtype=torch.float64))
        normals, albedo = lambertian_ps(intensity, lights, allow_degenerate=True)
        assert bool(torch.isfinite(normals).all()) and bool((albedo >= 0).all())
    # one light: the minimum-norm answer is the light direction itself
    single = _lights(1)
    normals, _ = lambertian_ps(torch.full((1, 4), 0.3, dtype=torch.float64), single, allow_degenerate=True)
    torch.testing.assert_close(normals, single.expand(4, 3))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("device", DEVICES)
def test_no_nan_for_extreme_inputs(dtype: torch.dtype, device: str) -> None:
    lights = _lights(8, dtype).to(device)
    inputs = {
        "dark": torch.zeros(8, 7, 5, dtype=dtype, device=device),
        "saturated": torch.ones(8, 7, 5, dtype=dtype, device=device),
        "tiny": torch.full((8, 7, 5), 1e-30, dtype=dtype, device=device),
        "nan": torch.full((8, 7, 5), math.nan, dtype=dtype, device=device),
        "mixed": torch.rand(8, 7, 5, dtype=dtype, device=device).masked_fill(
            torch.rand(8, 7, 5, device=device) < 0.3, math.inf
        ),
    }
    for name, intensity in inputs.items():
        normals, albedo = lambertian_ps(intensity, lights)
        assert bool(torch.isfinite(normals).all()) and bool(torch.isfinite(albedo).all()), name
        assert bool((albedo >= 0).all()), name
        for saturation in (None, 1.0):
            result = robust_lambertian_ps(intensity, lights, saturation=saturation)
            for field in ("normals", "albedo", "condition"):
                value = getattr(result, field)
                assert not bool(torch.isnan(value).any()), (name, field)
            assert bool(torch.isfinite(result.normals).all()), name
            torch.testing.assert_close(
                result.normals.norm(dim=-1), torch.ones(7, 5, dtype=dtype, device=device)
            )
            assert result.normals.device.type == device
    dark = robust_lambertian_ps(inputs["dark"], lights)
    assert bool((dark.reason == PSReason.TOO_FEW_LIGHTS).all())
    saturated = robust_lambertian_ps(inputs["saturated"], lights, saturation=1.0)
    assert bool((saturated.reason == PSReason.TOO_FEW_LIGHTS).all())
    assert bool((saturated.normals[..., 2] < 0).all())
    # single light, degenerate mode: finite as well
    one = robust_lambertian_ps(
        torch.rand(1, 7, 5, dtype=dtype, device=device), lights[:1], allow_degenerate=True
    )
    assert bool(torch.isfinite(one.normals).all()) and not bool(one.valid.any())


def test_too_few_usable_and_ill_conditioned_pixels_are_flagged() -> None:
    lights = _lights(6)
    normal = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    intensity = _render(normal, torch.tensor([0.5], dtype=torch.float64), lights).repeat(1, 3)  # (6, 3)
    intensity[2:, 0] = 0.0  # pixel 0: only two lit observations
    intensity[:, 1] = 0.0
    intensity[0, 1] = intensity[3, 1] = 0.2  # pixel 1: two opposite lights and ...
    intensity[1, 1] = 0.2  # ... a third one: fine
    result = robust_lambertian_ps(intensity, lights)
    assert int(result.reason[0]) == PSReason.TOO_FEW_LIGHTS
    assert int(result.n_used[0]) == 2
    assert bool(result.valid[2])
    # nearly coplanar usable lights → ILL_CONDITIONED
    tight = torch.tensor(
        [[0.0, 0.0, -1.0], [0.02, 0.0, -1.0], [0.0, 0.02, -1.0], [0.7, 0.0, -0.7], [0.0, 0.7, -0.7]],
        dtype=torch.float64,
    )
    tight = tight / tight.norm(dim=-1, keepdim=True)
    obs = (tight @ normal.T).clamp_min(0.0)  # (5, 1)
    obs[3:] = 0.0  # the well-separated lights are (cast-)shadowed
    flagged = robust_lambertian_ps(obs, tight)
    assert int(flagged.reason[0]) == PSReason.ILL_CONDITIONED
    assert float(flagged.condition[0]) > 30.0


def test_input_validation_messages() -> None:
    lights = _lights(4)
    with pytest.raises(ValueError, match="unit direction"):
        lambertian_ps(torch.rand(4, 3), lights.float() * 2.0)
    with pytest.raises(ValueError, match="lights must have shape"):
        lambertian_ps(torch.rand(4, 3, dtype=torch.float64), lights[:3])
    with pytest.raises(ValueError, match="light_intensity"):
        lambertian_ps(torch.rand(4, 3, dtype=torch.float64), lights, light_intensity=-torch.ones(4))
    with pytest.raises(ValueError, match="mask must have"):
        lambertian_ps(torch.rand(4, 3, dtype=torch.float64), lights, mask=torch.ones(5, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"\(K, P\)"):
        lambertian_ps(torch.rand(4, dtype=torch.float64), lights)
    with pytest.raises(ValueError, match="NaN or Inf"):
        lambertian_ps(torch.rand(4, 3, dtype=torch.float64), lights.clone().fill_(math.nan))
    with pytest.raises(ValueError, match="dark_rel"):
        robust_lambertian_ps(torch.rand(4, 3, dtype=torch.float64), lights, dark_rel=-1.0)


def test_plain_ps_is_differentiable() -> None:
    normals_img, mask, albedo_img = _sphere(size=8)
    lights = _lights(6)
    intensity = _render(normals_img[mask][:5], albedo_img[mask][:5], lights).clone().requires_grad_(True)

    def outputs(i: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return lambertian_ps(i, lights)

    assert torch.autograd.gradcheck(outputs, (intensity,))


def test_directional_lights_with_per_pixel_intensity() -> None:
    """Shared directions (K, 3) with per-pixel irradiance (K, P): each pixel's E scales its own
    observations (this combination used to fail in the light-geometry check)."""
    gen = torch.Generator().manual_seed(0)
    k, p = 6, 42
    t = torch.linspace(0.3, 0.8, k, dtype=torch.float64)
    phi = torch.arange(k, dtype=torch.float64) * 2.1
    lights = torch.stack([t.sin() * phi.cos(), t.sin() * phi.sin(), -t.cos()], -1)
    normal = torch.nn.functional.normalize(torch.tensor([0.1, -0.2, -1.0], dtype=torch.float64), dim=0)
    e = 0.5 + torch.rand(k, p, generator=gen, dtype=torch.float64)
    intensity = 0.7 * e * (lights @ normal).clamp_min(0).unsqueeze(1)
    robust = robust_lambertian_ps(intensity, lights, e)
    for normals, albedo in (lambertian_ps(intensity, lights, e), (robust.normals, robust.albedo)):
        torch.testing.assert_close(normals, normal.expand(p, 3))
        torch.testing.assert_close(albedo, torch.full((p,), 0.7, dtype=torch.float64))
