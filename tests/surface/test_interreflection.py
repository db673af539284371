"""Tests of polarshape.surface.interreflection: one bounce estimated from a recovered surface."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarshape.cameras import OrthographicCamera, PerspectiveCamera
from polarshape.lights import DirectionalLight, Lights
from polarshape.scene.geometry import crater_depth_map
from polarshape.surface.interreflection import estimate_one_bounce

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


def test_convex_surface_bounces_nothing() -> None:
    n = 64
    camera = OrthographicCamera(n, n, 1.0 / n, even=False)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    x, y = (xx - (n - 1) / 2) / n, (yy - (n - 1) / 2) / n
    disc = np.hypot(x, y) < 0.45
    zz = np.sqrt(np.clip(0.45**2 - x**2 - y**2, 0, None))
    depth = np.where(disc, 2.0 - zz, np.nan)
    normals = torch.tensor(np.where(disc[..., None], np.stack([x, y, -zz], -1) / 0.45, np.nan))
    b = _bounce(depth, normals, camera, max_pixels=256)  # a lattice (stride 4) and a mesh of every 2nd pixel
    assert b.stride > 1 and b.rays_hit == 0.0
    assert b.stokes.shape == (3, 3, n, n) and torch.all(b.stokes == 0)


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
