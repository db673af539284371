"""Shading a simulated scene: geometry + lights + materials → Stokes per pixel → polariser mosaic.

Data flow per light (spec fmbrdf.md §1, §8), all at raw-mosaic resolution (one ray per sensor
pixel, so the four sites of a super-pixel see four different surface points):

1. :func:`polarshape.scene.raycast.rasterize` gives N, V, hit points (once per view);
2. :func:`shade_stokes`: s = E · f(N, L, V) (zero in cast shadow), in each pixel's Stokes frame;
3. :func:`sensor_plane_stokes`: the polarisation angle the sensor reports (spec §1: the
   polarisation direction projected along z onto the sensor plane; s0 and DoLP unchanged);
4. :func:`mosaic_radiance`: each pixel sees ``I_θ = ½ (s0 + s1 cos 2θ + s2 sin 2θ)`` with θ the
   polariser angle of its site.

Radiance is in the units of the lights' intensity (irradiance 1 at normal incidence = 1).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from torch import Tensor

from polarshape.brdf.geometry import stokes_frame
from polarshape.imaging.mosaic import MosaicLayout
from polarshape.scene.lights import Light
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


def sensor_plane_basis(view: Tensor) -> Tensor:
    """Per pixel, how the Stokes frame projects onto the sensor plane (spec §1).

    Args:
        view: (..., 3) V of each pixel.

    Returns:
        (..., 2, 2) M = [[e_x·x̂, e_y·x̂], [e_x·ŷ, e_y·ŷ]]: a polarisation direction
        e = cos φ e_x + sin φ e_y is seen in the sensor plane along M (cos φ, sin φ).
        Identity for orthographic cameras.
    """
    e_x, e_y = stokes_frame(view)  # (..., 3) each
    return torch.stack([torch.stack([e_x[..., 0], e_y[..., 0]], -1), torch.stack([e_x[..., 1], e_y[..., 1]], -1)], -2)


def sensor_plane_stokes(stokes: Tensor, view: Tensor | None = None, *, basis: Tensor | None = None) -> Tensor:
    """Re-express Stokes vectors with the angle the sensor reports (spec §1, perspective cameras).

    A polarisation direction e = cos φ e_x + sin φ e_y (φ = AoLP in the pixel's Stokes frame) is
    observed at atan2(e·ŷ, e·x̂). s0 and the DoLP are kept. Computed without angles: with
    p = M (cos φ, sin φ) (see :func:`sensor_plane_basis`), the quadratic forms p_x², p_y², p_x p_y
    are linear in lin·cos²φ = (lin + s1)/2, lin·sin²φ = (lin − s1)/2, lin·sin φ cos φ = s2/2
    (lin = √(s1² + s2²)). Identity for orthographic cameras (e_x = x̂, e_y = ŷ).

    Args:
        stokes: (..., 3, H, W) Stokes in the per-pixel frames.
        view: (H, W, 3) V of each pixel (or give ``basis``).
        basis: (H, W, 2, 2) precomputed :func:`sensor_plane_basis` (cheaper for many lights).

    Returns:
        Same shape as ``stokes``.
    """
    if basis is None:
        if view is None:
            raise ValueError("sensor_plane_stokes needs view (H, W, 3) or basis (H, W, 2, 2)")
        basis = sensor_plane_basis(view.to(stokes.dtype))
    basis = basis.to(stokes.dtype)
    a, b = basis[..., 0, 0], basis[..., 0, 1]  # (H, W)
    c, d = basis[..., 1, 0], basis[..., 1, 1]
    s0, s1, s2 = stokes.unbind(-3)
    lin = torch.sqrt(s1 * s1 + s2 * s2)
    cc, ss, cs = 0.5 * (lin + s1), 0.5 * (lin - s1), 0.5 * s2  # lin·cos²φ, lin·sin²φ, lin·sinφ cosφ
    pxx = a * a * cc + 2 * a * b * cs + b * b * ss  # lin · p_x²
    pyy = c * c * cc + 2 * c * d * cs + d * d * ss  # lin · p_y²
    pxy = a * c * cc + (a * d + b * c) * cs + b * d * ss  # lin · p_x p_y
    norm = pxx + pyy
    ok = norm > 0
    safe = torch.where(ok, norm, torch.ones_like(norm))
    s1_out = torch.where(ok, lin * (pxx - pyy) / safe, 0.0)
    s2_out = torch.where(ok, lin * 2 * pxy / safe, 0.0)
    return torch.stack([s0, s1_out, s2_out], dim=-3)


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
