"""Shading a simulated scene: geometry + lights + materials → Stokes per pixel → polariser mosaic.

Data flow per light (spec fmbrdf.md §1, §8), all at raw-mosaic resolution (one ray per sensor
pixel, so the four sites of a super-pixel see four different surface points):

1. :func:`polarshape.scene.raycast.rasterize` gives N, V, hit points (once per view);
2. :func:`shade_stokes`: s = E · f(N, L, V) (zero in cast shadow), in each pixel's Stokes frame;
3. :func:`polarshape.brdf.geometry.sensor_plane_stokes`: the polarisation angle the sensor reports
   (spec §1: the polarisation direction projected along z onto the sensor plane; s0 and DoLP
   unchanged);
4. :func:`mosaic_radiance`: each pixel sees ``I_θ = ½ (s0 + s1 cos 2θ + s2 sin 2θ)`` with θ the
   polariser angle of its site.

Radiance is in the units of the lights' intensity (irradiance 1 at normal incidence = 1).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from torch import Tensor

from polarshape.brdf.geometry import sensor_plane_basis, sensor_plane_stokes
from polarshape.imaging.mosaic import MosaicLayout
from polarshape.lights import Light
from polarshape.scene.objects import Scene
from polarshape.scene.raycast import GeometryBuffers, cast_shadow_mask

logger = logging.getLogger(__name__)


def albedo_scale_map(scene: Scene, geometry: GeometryBuffers) -> Tensor:
    """(H, W) per-pixel albedo multiplier from the objects' textures (1 where untextured/empty)."""
    scale = torch.ones_like(geometry.depth)
    for k, obj in enumerate(scene.objects):
        if obj.texture is None:
            continue
        sel = geometry.object_index == k  # (H, W)
        if sel.any():
            scale[sel] = obj.texture(geometry.points[sel])
    return scale


def shade_stokes(
    scene: Scene,
    geometry: GeometryBuffers,
    light: Light,
    *,
    shadows: bool = True,
    albedo_scale: Tensor | None = None,
) -> Tensor:
    """Stokes radiance of every pixel under one light, in each pixel's Stokes frame (spec §1, §8).

    Args:
        scene: the scene ``geometry`` was rasterised from.
        geometry: per-pixel buffers (H, W).
        light: the light that is on.
        shadows: test cast shadows (False: only attached shadows, via the BRDF).
        albedo_scale: (H, W) albedo multipliers (default: from the objects' textures).

    Returns:
        (3, H, W) (s0, s1, s2); 0 on the background and in shadow.
    """
    light_dir, irradiance, _ = light.illuminate(geometry.points)  # (H, W, 3), (H, W), _
    lit = geometry.mask.clone()
    if shadows:
        lit &= ~cast_shadow_mask(scene.shapes, geometry, light)
    if albedo_scale is None:
        albedo_scale = albedo_scale_map(scene, geometry)
    out = torch.zeros(*geometry.depth.shape, 3, dtype=geometry.points.dtype, device=geometry.points.device)  # (H, W, 3)
    for k, obj in enumerate(scene.objects):
        sel = lit & (geometry.object_index == k)  # (H, W)
        if not sel.any():
            continue
        s = obj.material.stokes(geometry.normals[sel], light_dir[sel], geometry.view[sel], albedo_scale[sel])  # (M, 3)
        out[sel] = s.to(out.dtype) * irradiance[sel][:, None]
    return out.permute(2, 0, 1)


def polariser_angle_map(
    layout: MosaicLayout, height: int, width: int, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64
) -> Tensor:
    """(H, W) polariser angle θ (radians, our convention) of every raw-mosaic pixel: site (i, j)
    of the layout repeated over the sensor (H, W even)."""
    if height % 2 or width % 2:
        raise ValueError(f"mosaic height and width must be even, got {height}x{width}")
    sites = layout.angles_rad(device=device, dtype=dtype).reshape(2, 2)  # (2, 2)
    return sites.repeat(height // 2, width // 2)


def mosaic_radiance(stokes: Tensor, angle_map: Tensor) -> Tensor:
    """Each raw pixel behind its own polariser: I = ½ (s0 + s1 cos 2θ + s2 sin 2θ) (spec §1).

    Args:
        stokes: (..., 3, H, W) Stokes at mosaic resolution, sensor-plane angles.
        angle_map: (H, W) polariser angle of each pixel, radians.

    Returns:
        (..., H, W) radiance behind the polarisers.
    """
    s0, s1, s2 = stokes.unbind(-3)
    two = 2.0 * angle_map.to(stokes.dtype)
    return 0.5 * (s0 + s1 * torch.cos(two) + s2 * torch.sin(two))


def render_mosaics(
    scene: Scene,
    layout: MosaicLayout,
    *,
    lights: Sequence[int] | None = None,
    geometry: GeometryBuffers | None = None,
    shadows: bool = True,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """Noise-free raw-mosaic radiance for the given lights (default: all).

    Returns:
        (K, H, W) radiance, one mosaic per light index in ``lights``.
    """
    if geometry is None:
        geometry = scene.rasterize(device=device, dtype=dtype)
    indices = range(len(scene.lights)) if lights is None else lights
    h, w = geometry.depth.shape
    angle_map = polariser_angle_map(layout, h, w, device=geometry.depth.device, dtype=geometry.depth.dtype)
    albedo = albedo_scale_map(scene, geometry)
    basis = sensor_plane_basis(geometry.view)
    out = []
    for i in indices:
        stokes = shade_stokes(scene, geometry, scene.lights[i], shadows=shadows, albedo_scale=albedo)
        out.append(mosaic_radiance(sensor_plane_stokes(stokes, basis=basis), angle_map))
    return torch.stack(out)
