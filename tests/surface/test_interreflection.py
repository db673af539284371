"""Tests of polarshape.surface.interreflection: one bounce estimated from a recovered surface."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarshape.cameras import OrthographicCamera, PerspectiveCamera
from polarshape.lights import DirectionalLight, Lights
from polarshape.scene.geometry import crater_depth_map
import polarshape.surface.interreflection as interreflection
from polarshape.surface.interreflection import estimate_one_bounce, surface_below_tangent_planes

PARAMS = {"ior": 1.5, "k_s": 1.0, "alpha": 0.3, "beta": 2.0, "kappa": 0.0}
LIGHTS = Lights(tuple(
    DirectionalLight((math.sin(math.radians(z)) * math.cos(math.radians(a)),
                      math.sin(math.radians(z)) * math.sin(math.radians(a)), -math.cos(math.radians(z))))
    for z, a in ((10, 0), (35, 120), (50, 240))
))


def _crater(n: int) -> tuple[np.ndarray, torch.Tensor, OrthographicCamera, np.ndarray]:
    """An n×n orthographic view of a plate with a dish (the crater scene's shape): depth, normals, camera, dish mask."""
    pixel = 0.0256 / n
    camera = OrthographicCamera(n, n, pixel, even=False)
    depth, normals = crater_depth_map(n, pixel, radius=0.008, depth=0.004, half_width=0.0115, distance=0.5)
    return depth, torch.tensor(normals), camera, np.nan_to_num(depth, nan=0.5) > 0.5  # the dish: below the plate


def _bounce(depth: np.ndarray, normals: torch.Tensor, camera, max_pixels: int):  # noqa: ANN001, ANN202
    n = depth.shape[0]
    view = torch.zeros(n, n, 3, dtype=normals.dtype)
    view[..., 2] = -1.0
    return estimate_one_bounce(normals, torch.full((n, n), 0.7, dtype=normals.dtype), depth, camera, view, LIGHTS,
                               PARAMS, samples=32, max_pixels=max_pixels)


def _sphere(n: int) -> tuple[np.ndarray, torch.Tensor, OrthographicCamera]:
    """An n×n orthographic view of a sphere of radius 0.45 (image widths) at z = 2: depth, normals, camera."""
    camera = OrthographicCamera(n, n, 1.0 / n, even=False)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    x, y = (xx - (n - 1) / 2) / n, (yy - (n - 1) / 2) / n
    disc = np.hypot(x, y) < 0.45
    zz = np.sqrt(np.clip(0.45**2 - x**2 - y**2, 0, None))
    depth = np.where(disc, 2.0 - zz, np.nan)
    normals = torch.tensor(np.where(disc[..., None], np.stack([x, y, -zz], -1) / 0.45, np.nan))
    return depth, normals, camera


def test_convex_surface_bounces_nothing() -> None:
    depth, normals, camera = _sphere(64)
    b = _bounce(depth, normals, camera, max_pixels=256)  # a lattice (stride 4) and a mesh of every 2nd pixel
    assert b.stride > 1 and b.rays_hit == 0.0
    assert b.stokes.shape == (3, 3, 64, 64) and torch.all(b.stokes == 0)


def test_convex_surface_casts_no_ray(monkeypatch: pytest.MonkeyPatch) -> None:
    """The convex test decides before any ray is cast (no ray-casting scene, no open3d)."""
    def no_rays(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("rays cast on a convex surface")

    monkeypatch.setattr(interreflection, "hemisphere_hits", no_rays)
    depth, normals, camera = _sphere(64)
    b = _bounce(depth, normals, camera, max_pixels=256)
    assert b.rays_hit == 0.0 and torch.all(b.stokes == 0)
    with pytest.raises(AssertionError, match="rays cast"):  # a concave one still casts its rays
        _bounce(*_crater(48)[:3], max_pixels=256)


def _grid_points(depth: np.ndarray, normals: torch.Tensor, camera, stride: int):  # noqa: ANN001, ANN202
    """The vertex grid (H, W, 3) and the lattice's points and normals (P, 3) of a depth map, as the estimator
    forms them."""
    points = torch.as_tensor(camera.unproject(depth))  # (H, W, 3)
    on = torch.isfinite(points).all(-1) & torch.isfinite(normals).all(-1)
    lattice = (slice(stride // 2, None, stride),) * 2
    return torch.where(on[..., None], points, math.nan), points[lattice][on[lattice]], normals[lattice][on[lattice]]


def _heights(vertices: torch.Tensor, points: torch.Tensor, normals: torch.Tensor) -> float:
    """The largest n̂·(v − p) over every vertex v and point p (brute force)."""
    v = vertices[torch.isfinite(vertices).all(-1)]  # (M, 3)
    n = normals / normals.norm(dim=-1, keepdim=True)
    return float((n @ v.T - (n * points).sum(-1, keepdim=True)).max())


def test_sphere_and_plane_lie_below_their_tangent_planes() -> None:
    depth, normals, camera = _sphere(64)
    vertices, points, lattice_normals = _grid_points(depth, normals, camera, 2)
    assert surface_below_tangent_planes(vertices, normals, points, lattice_normals, offset=1e-3 * 0.45)
    # a tilted plane: every vertex on every tangent plane
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float64) / 64
    plane = 2.0 + 0.3 * xx - 0.2 * yy
    n = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64).expand(64, 64, 3) / math.sqrt(1.13)
    vertices, points, lattice_normals = _grid_points(plane, n, camera, 3)
    assert surface_below_tangent_planes(vertices, n, points, lattice_normals, offset=1e-3)


def test_crater_rises_above_its_tangent_planes() -> None:
    depth, normals, camera, _ = _crater(64)
    vertices, points, lattice_normals = _grid_points(depth, normals, camera, 2)
    assert not surface_below_tangent_planes(vertices, normals, points, lattice_normals, offset=1e-3 * 0.0115)


@pytest.mark.parametrize("stride", [1, 3])
def test_tangent_plane_test_is_exact(stride: int) -> None:
    """On a bumpy sphere the answer flips where the brute-force largest height crosses the start-off."""
    depth, normals, camera = _sphere(50)
    gen = torch.Generator().manual_seed(3)
    bumps = 0.2 * torch.rand(normals.shape, generator=gen, dtype=normals.dtype) - 0.1
    noisy = normals + bumps  # not unit, and off the depth's own normals
    vertices, points, lattice_normals = _grid_points(depth - 1.9, noisy, camera, stride)  # near the origin
    highest = _heights(vertices, points, lattice_normals)
    assert highest > 1e-4  # the bumps lift vertices above their neighbours' planes
    shortest, longest = (float(x) for x in lattice_normals.norm(dim=-1).aminmax())  # rays start offset · |n| above
    assert surface_below_tangent_planes(vertices, noisy, points, lattice_normals, offset=1.05 * highest / shortest)
    assert not surface_below_tangent_planes(vertices, noisy, points, lattice_normals, offset=0.95 * highest / longest)


def test_coarse_mesh_keeps_the_bounce_in_a_dish() -> None:
    """The lattice's mesh (every stride // 2-th pixel) gives the bounce of the mesh of every pixel."""
    depth, normals, camera, dish = _crater(96)
    fine = _bounce(depth, normals, camera, max_pixels=96 * 96)  # every pixel, the mesh of every pixel
    coarse = _bounce(depth, normals, camera, max_pixels=400)  # stride 5: a mesh of every 2nd pixel
    assert fine.stride == 1 and coarse.stride == 5
    assert torch.isfinite(coarse.stokes).all()
    assert coarse.rays_hit == pytest.approx(fine.rays_hit, rel=0.15)
    s_fine, s_coarse = fine.stokes[:, 0][:, torch.as_tensor(dish)], coarse.stokes[:, 0][:, torch.as_tensor(dish)]
    assert float(s_fine.mean()) > 0
    assert float(s_coarse.mean()) == pytest.approx(float(s_fine.mean()), rel=0.1)
    # nothing bounces onto the plate far from the dish, and nothing outside the surface
    far = ~np.isfinite(depth) | (np.hypot(*np.mgrid[0:96, 0:96] - 47.5) > 45)
    assert torch.all(coarse.stokes[..., torch.as_tensor(far)] == 0)


def test_perspective_camera_mesh_grid() -> None:
    depth, normals, _, dish = _crater(96)
    camera = PerspectiveCamera(96, 96, fx=0.5 / (0.0256 / 96), fy=0.5 / (0.0256 / 96), cx=47.5, cy=47.5, even=False)
    b = _bounce(depth, normals, camera, max_pixels=400)
    assert b.stride == 5 and b.rays_hit > 0
    assert float(b.stokes[:, 0][:, torch.as_tensor(dish)].mean()) > 0
