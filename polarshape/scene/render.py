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

Colour sensors (``bayer``, :mod:`polarshape.imaging.colour`): each raw pixel sees only its own
colour, so its Stokes vector is that colour's; with white lights the colours differ only in the body
albedo, and the Stokes vector is linear in it, so the colour is selected before shading (step 2) by
scaling each pixel's body albedo with its colour's factor (:func:`colour_albedo_map`) — the same as
rendering (3, 3, H, W) per-colour Stokes and keeping each pixel's channel, at a third of the cost,
and before the polariser step (4), which stays colour-blind.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from torch import Tensor

from polarshape.brdf.geometry import sensor_plane_basis, sensor_plane_stokes
from polarshape.imaging.analyser import analysed_intensity
from polarshape.imaging.colour import pixel_colours
from polarshape.imaging.mosaic import MosaicLayout
from polarshape.lights import Light
from polarshape.scene.materials import colour_albedo_factors
from polarshape.scene.objects import Scene
from polarshape.scene.raycast import GeometryBuffers, cast_shadow_mask
from polarshape.scene.sensor_defects import SensorMaps

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


def colour_albedo_map(scene: Scene, geometry: GeometryBuffers, bayer: str) -> Tensor:
    """(H, W) per-pixel body-albedo multiplier selecting each raw pixel's colour channel.

    Pixel (y, x) behind colour c on a surface of material m gets
    ``colour_albedo_factors(m)[c]`` (1 for grey materials and off the objects).

    Args:
        scene: the scene ``geometry`` was rasterised from.
        geometry: per-pixel buffers at raw-mosaic resolution (2H, 2W).
        bayer: Bayer pattern of the 2×2 polariser blocks (:data:`polarshape.imaging.colour.BAYER_PATTERNS`).
    """
    h, w = geometry.depth.shape
    colour = pixel_colours(bayer, h, w, device=geometry.depth.device)  # (2H, 2W) 0 R, 1 G, 2 B
    scale = torch.ones_like(geometry.depth)
    materials = scene.material_index(geometry)  # (2H, 2W)
    for m, material in enumerate(scene.materials):
        factors = geometry.depth.new_tensor(colour_albedo_factors(material))  # (3,)
        scale = torch.where(materials == m, factors[colour], scale)
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
    return shade_directions(scene, geometry, light_dir, irradiance, lit, albedo_scale)


def shade_directions(scene: Scene, geometry: GeometryBuffers, light_dir: Tensor, irradiance: Tensor, lit: Tensor,
                     albedo_scale: Tensor) -> Tensor:
    """Stokes radiance of every pixel for light arriving from its own direction (spec §1, §8).

    Args:
        scene: the scene ``geometry`` was rasterised from (its objects' materials).
        geometry: per-pixel buffers (H, W) (any 2-D batch: secondary hits too).
        light_dir: (H, W, 3) unit directions surface → light.
        irradiance: (H, W) irradiance at normal incidence from that direction.
        lit: (H, W) bool, the pixels to shade (others are 0).
        albedo_scale: (H, W) albedo multipliers.

    Returns:
        (3, H, W) (s0, s1, s2) in each pixel's Stokes frame.
    """
    out = torch.zeros(*geometry.depth.shape, 3, dtype=geometry.points.dtype, device=geometry.points.device)  # (H, W, 3)
    materials = scene.material_index(geometry)  # (H, W): objects of two parts shade each with its own
    for m, material in enumerate(scene.materials):
        sel = lit & (materials == m)  # (H, W)
        if not sel.any():
            continue
        s = material.stokes(geometry.normals[sel], light_dir[sel], geometry.view[sel], albedo_scale[sel])  # (M, 3)
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


def mosaic_radiance(stokes: Tensor, angle_map: Tensor, diattenuation: Tensor | float = 1.0,
                    gain: Tensor | float = 1.0) -> Tensor:
    """Each raw pixel behind its own analyser: I = ½ g (s0 + D (s1 cos 2θ + s2 sin 2θ)) (spec §1;
    :func:`polarshape.imaging.analyser.analysed_intensity`, the one formula). D = 1, g = 1 is the
    ideal polariser ``½ (s0 + s1 cos 2θ + s2 sin 2θ)`` (bit-identical to it).

    Args:
        stokes: (..., 3, H, W) Stokes at mosaic resolution, sensor-plane angles.
        angle_map: (H, W) analyser angle of each pixel, radians.
        diattenuation: (H, W) or scalar D in (0, 1] (real sensors: :mod:`polarshape.scene.sensor_defects`).
        gain: (H, W) or scalar relative response.

    Returns:
        (..., H, W) radiance behind the analysers.
    """
    return analysed_intensity(stokes, angle_map.to(stokes.dtype), diattenuation, gain)


def render_mosaics(
    scene: Scene,
    layout: MosaicLayout,
    *,
    lights: Sequence[int] | None = None,
    geometry: GeometryBuffers | None = None,
    shadows: bool = True,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float64,
    bayer: str | None = None,
    sensor_maps: SensorMaps | None = None,
) -> Tensor:
    """Noise-free raw-mosaic radiance for the given lights (default: all).

    ``sensor_maps``: a real sensor's per-pixel analysers and gains
    (:meth:`polarshape.scene.sensor_defects.SensorDefects.draw`, on the geometry's device); None = ideal.

    ``bayer``: a colour polarisation sensor's Bayer pattern (each pixel sees its own colour,
    :func:`colour_albedo_map`); None = mono.

    Returns:
        (K, H, W) radiance, one mosaic per light index in ``lights``.
    """
    if geometry is None:
        geometry = scene.rasterize(device=device, dtype=dtype)
    indices = range(len(scene.lights)) if lights is None else lights
    h, w = geometry.depth.shape
    angle_map = polariser_angle_map(layout, h, w, device=geometry.depth.device, dtype=geometry.depth.dtype)
    albedo = albedo_scale_map(scene, geometry)
    if bayer is not None:
        albedo = albedo * colour_albedo_map(scene, geometry, bayer)
    basis = sensor_plane_basis(geometry.view)
    out = []
    for i in indices:
        stokes = shade_stokes(scene, geometry, scene.lights[i], shadows=shadows, albedo_scale=albedo)
        plane = sensor_plane_stokes(stokes, basis=basis)
        if sensor_maps is None:
            out.append(mosaic_radiance(plane, angle_map))
        else:
            out.append(mosaic_radiance(plane, sensor_maps.angle_rad, sensor_maps.diattenuation, sensor_maps.gain))
    return torch.stack(out)
