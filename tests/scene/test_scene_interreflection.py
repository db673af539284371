"""One bounce of light off the scene (polarshape.scene.interreflection), and the crater shape."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.scene.config import load_scene_config, parse_scene_config
from polarshape.scene.interreflection import hemisphere_directions, hemisphere_hits, hemisphere_rays, one_bounce_stokes
from polarshape.scene.render import shade_stokes

REPO = Path(__file__).resolve().parents[2]


def _scene(objects: list[dict], lights: list[dict], size: int = 16, pixel: float = 1e-3, samples: int = 64) -> dict:
    return {
        "format": "polarshape-scene/1",
        "camera": {"projection": "orthographic", "width": size, "height": size, "pixel_size_m": pixel},
        "sensor": {"shot_noise": "none", "read_noise_e": 0.0},
        "objects": objects,
        "lights": lights,
        "render": {"interreflection": {"samples": samples, "seed": 1}},
    }


def test_hemisphere_directions_are_unit_uniform_and_above_the_surface() -> None:
    n = torch.nn.functional.normalize(torch.randn(500, 3, dtype=torch.float64), dim=-1)
    w = hemisphere_directions(n, 64, torch.Generator().manual_seed(0))  # (P, S, 3)
    assert w.shape == (500, 64, 3)
    assert torch.allclose(w.norm(dim=-1), torch.ones(500, 64, dtype=torch.float64))
    cos = (w * n[:, None]).sum(-1)
    assert bool((cos > 0).all())
    # uniform over the hemisphere: cos θ uniform on (0, 1) (mean ½, mean of cos² ⅓)
    assert abs(float(cos.mean()) - 0.5) < 0.01 and abs(float((cos**2).mean()) - 1 / 3) < 0.01


def test_hemisphere_directions_of_some_rows_are_those_of_all() -> None:
    n = torch.nn.functional.normalize(torch.randn(300, 3, dtype=torch.float64), dim=-1)
    rows = torch.tensor([0, 7, 299, 150])
    every = hemisphere_directions(n, 16, torch.Generator().manual_seed(4))  # (P, S, 3)
    some = hemisphere_directions(n, 16, torch.Generator().manual_seed(4), rows=rows)  # (R, S, 3)
    assert torch.equal(some, every[rows])


def test_hemisphere_rays_are_the_rays_cast() -> None:
    """hemisphere_hits casts hemisphere_rays (its directions, starts off the surface by the shape's tolerance);
    ``rows`` gives some pixels' rays, the same as among all."""
    d = _scene([{"shape": {"type": "sphere", "center": [0.0, 0.0, 0.5], "radius": 0.006},
                 "material": {"model": "lambertian", "k_d": 0.5}}], [{"direction": [0.0, 0.0, -1.0]}], samples=8)
    with SimulatedCamera(parse_scene_config(d)) as cam:
        scene, g = cam.scene, cam.geometry
        rays = hemisphere_rays(scene, g, 8, seed=2)
        hits = hemisphere_hits(scene, g, 8, seed=2)
        rows = torch.tensor([3, 0, rays.pixels.numel() - 1])
        some = hemisphere_rays(scene, g, 8, seed=2, rows=rows)
    assert torch.equal(rays.pixels, hits.pixels) and torch.equal(rays.directions, hits.directions)
    points = g.points.reshape(-1, 3)[rays.pixels]  # (P, 3)
    offset = scene.shapes[0].surface_error_rel * scene.shapes[0].bounding_radius
    assert torch.allclose(rays.origins[:, 0], points + offset * g.normals.reshape(-1, 3)[rays.pixels])
    assert torch.equal(some.pixels, rays.pixels[rows]) and torch.equal(some.directions, rays.directions[rows])
    assert torch.equal(some.origins, rays.origins[rows])


def test_floor_beside_a_lit_wall_receives_half_its_radiance() -> None:
    """A Lambertian floor (albedo ρ_f) facing the camera beside an infinite lit Lambertian wall: the wall
    fills half of every floor point's hemisphere (view factor ½, at any distance), so one bounce adds
    the radiance ρ_f · L_w / 2 with L_w = ρ_w / π · E cos θ_w — an answer the renderer does not contain."""
    rho_f, rho_w = 0.6, 0.8
    light = [-0.6, 0.0, -0.8]  # lights the wall's front (facing −x) at cos 0.6, the floor at 0.8
    d = _scene(
        [{"shape": {"type": "plane", "point": [0.0, 0.0, 0.5], "normal": [0.0, 0.0, -1.0], "size": [0.1, 0.1]},
          "material": {"model": "lambertian", "k_d": rho_f}},
         {"shape": {"type": "plane", "point": [0.02, 0.0, 0.5], "normal": [-1.0, 0.0, 0.0]},
          "material": {"model": "lambertian", "k_d": rho_w}, "in_mask": False}],
        [{"direction": light}], samples=1024,
    )
    with SimulatedCamera(parse_scene_config(d)) as cam:
        scene, g = cam.scene, cam.geometry
        bounce = one_bounce_stokes(scene, g, hemisphere_hits(scene, g, 1024, seed=3), scene.lights[0])
    floor = g.mask & (g.object_index == 0)
    expected = rho_f * (rho_w / math.pi * 0.6) / 2.0
    s0 = bounce[0][floor]
    assert abs(float(s0.mean()) / expected - 1.0) < 0.02
    assert float(s0.std()) / expected < 0.1  # each pixel's estimate, not only the mean
    assert float(bounce[1:].abs().max()) < 1e-12  # Lambertian: the bounced light leaves unpolarised


def test_a_convex_sphere_does_not_light_itself() -> None:
    d = _scene([{"shape": {"type": "sphere", "center": [0.0, 0.0, 0.5], "radius": 0.006},
                 "material": {"model": "fmbrdf", "k_b": 0.6, "alpha": 0.3}}],
               [{"zenith_deg": 30, "azimuth_deg": 0}])
    with SimulatedCamera(parse_scene_config(d)) as cam:
        b = one_bounce_stokes(cam.scene, cam.geometry, cam._bounce, cam.scene.lights[0])  # noqa: SLF001
    assert float(b.abs().max()) == 0.0


def test_crater_scene_bounces_inside_the_dish_only() -> None:
    d = load_scene_config(REPO / "configs" / "scenes" / "crater.yaml").model_dump(mode="json")
    d["camera"].update(width=64, height=64, pixel_size_m=4e-4)
    d["objects"][0]["shape"]["resolution"] = 129
    d["render"]["interreflection"]["samples"] = 32
    with SimulatedCamera(parse_scene_config(d)) as cam:
        scene, g = cam.scene, cam.geometry
        direct = shade_stokes(scene, g, scene.lights[0])[0]
        bounce = one_bounce_stokes(scene, g, cam._bounce, scene.lights[0])  # noqa: SLF001
        with_bounce = cam.radiance(0)
    assert bool(torch.isfinite(bounce).all())
    rho = torch.hypot(g.points[..., 0], g.points[..., 1])
    inside, plate = g.mask & (rho < 0.006), g.mask & (rho > 0.0085)
    ratio = float(bounce[0][inside].mean() / direct[inside].mean())
    assert 0.03 < ratio < 0.5  # a few to tens of per cent of the direct light, as in a real dish
    assert float(bounce[0][plate].abs().max()) == 0.0  # the flat plate sees only the sky
    # the camera renders it: its radiance differs from the direct light's where the dish is
    d["render"]["interreflection"] = None
    with SimulatedCamera(parse_scene_config(d)) as cam:
        direct_only = cam.radiance(0)
    assert float((with_bounce - direct_only)[inside].mean()) > 0
    assert torch.equal(with_bounce[plate], direct_only[plate])


def test_crater_shape_is_validated() -> None:
    d = load_scene_config(REPO / "configs" / "scenes" / "crater.yaml").model_dump(mode="json")
    d["objects"][0]["shape"]["half_width"] = 0.005  # smaller than the dish
    with pytest.raises(ValueError, match="objects.0.shape.crater: half_width 0.005 must exceed the dish radius"):
        parse_scene_config(d)
