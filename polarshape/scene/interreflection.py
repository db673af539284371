"""One bounce of light off the scene itself (interreflection), for concave objects.

A visible point x sees, besides the lights, the surface points y_j its hemisphere looks at; each sends
toward x the light it reflects from the lights (direct light at y_j, cast shadows included). With S
stratified directions ω_j of the hemisphere about N_x, one bounce adds, per light,

    s(x) += Σ_j  f(N_x, ω_j, V_x) · L_o(y_j → x) · Δω,     Δω = 2π / S,

where ``f(N, ω, V)`` is the material's Stokes vector for unit irradiance at normal incidence from ω
(N·ω inside, :meth:`Material.stokes`) and ``L_o(y → x)`` is the radiance y sends toward x — its s0,
rendered by :func:`polarshape.scene.render.shade_stokes` with the view from y toward x. The light
arriving from y_j is taken as unpolarised (its own polarisation from the first reflection is dropped;
the second reflection's polarisation is kept); bounces after the first are left out. The directions
follow a Fibonacci lattice on the hemisphere (uniform in cos θ and golden-angle in φ, jittered per
pixel from a seeded generator), so S need not be a square and neighbouring pixels do not share
aliasing. The hemisphere rays are cast once per view (:func:`hemisphere_hits`) and reused for every
light (:func:`one_bounce_stokes`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from polarshape.brdf.geometry import tangent_basis
from polarshape.lights import Light
from polarshape.scene.objects import Scene
from polarshape.scene.raycast import GeometryBuffers, nearest_hits
from polarshape.scene.render import albedo_scale_map, shade_directions, shade_stokes

logger = logging.getLogger(__name__)

__all__ = ["HemisphereHits", "HemisphereRays", "hemisphere_directions", "hemisphere_hits", "hemisphere_rays",
           "one_bounce_stokes"]

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
#: pixels per chunk of hemisphere rays (chunk × samples rays at once)
_CHUNK_PIXELS = 4096


@dataclass(frozen=True)
class HemisphereHits:
    """What the hemisphere rays of the visible pixels of one view hit.

    Attributes:
        pixels: (P,) int64 flat indices (into H·W) of the pixels that cast rays.
        directions: (P, S, 3) unit ray directions, from the pixel's point outward.
        hits: (P, S) buffers of the points hit (``mask`` False where a ray leaves the scene);
            ``view`` is −direction (from the hit back toward the pixel's point), normals face it.
        albedo_scale: (P, S) texture multipliers at the hits.
        solid_angle: Δω = 2π / S, steradians.
    """

    pixels: Tensor
    directions: Tensor
    hits: GeometryBuffers
    albedo_scale: Tensor
    solid_angle: float


def hemisphere_directions(normals: Tensor, samples: int, generator: torch.Generator | None = None, *,
                          rows: Tensor | None = None) -> Tensor:
    """(P, S) unit directions on the hemispheres about ``normals`` (P, 3): cos θ uniform in strata,
    φ on the golden-angle lattice, both jittered per pixel (uniform density 1 / 2π per steradian).

    Args:
        normals: (P, 3) unit normals.
        samples: S ≥ 1 directions per pixel.
        generator: random source on the normals' device (None: torch's global one).
        rows: (R,) indices into P: only these normals' directions, each the same as in the call without
            ``rows`` (the random draws of all P are made, the trigonometry of R).

    Returns:
        (P, S, 3) unit vectors with ``ω · N > 0`` ((R, S, 3) with ``rows``).
    """
    if samples < 1:
        raise ValueError(f"samples must be ≥ 1; got {samples}")
    p = normals.shape[0]
    dtype, device = normals.dtype, normals.device
    j = torch.arange(samples, dtype=dtype, device=device)  # (S,)
    jitter = torch.rand(p, samples, dtype=dtype, device=device, generator=generator)  # (P, S)
    turn = torch.rand(p, 1, dtype=dtype, device=device, generator=generator) * (2.0 * math.pi)  # (P, 1)
    if rows is not None:
        normals, jitter, turn = normals[rows], jitter[rows], turn[rows]  # (R, 3), (R, S), (R, 1)
    cos_t = ((j + jitter) / samples).clamp(1e-6, 1.0)  # (P, S) stratified, never grazing exactly
    sin_t = torch.sqrt((1.0 - cos_t * cos_t).clamp_min(0.0))
    phi = j * _GOLDEN_ANGLE + turn  # (P, S)
    t1, t2 = tangent_basis(normals)  # (P, 3) each
    return (sin_t * torch.cos(phi)).unsqueeze(-1) * t1.unsqueeze(1) + (sin_t * torch.sin(phi)).unsqueeze(-1) * t2.unsqueeze(1) \
        + cos_t.unsqueeze(-1) * normals.unsqueeze(1)


@dataclass(frozen=True)
class HemisphereRays:
    """The hemisphere rays of the visible pixels of one view (:func:`hemisphere_rays`).

    Attributes:
        pixels: (P,) int64 flat indices (into H·W) of the pixels that cast rays.
        origins: (P, S, 3) the rays' starts: each pixel's point moved off the surface along its normal.
        directions: (P, S, 3) unit ray directions, from the pixel's point outward.
    """

    pixels: Tensor
    origins: Tensor
    directions: Tensor


def hemisphere_rays(scene: Scene, geometry: GeometryBuffers, samples: int, *, seed: int = 0,
                    rows: Tensor | None = None) -> HemisphereRays:
    """The ``samples`` hemisphere rays of every visible pixel of ``geometry`` that :func:`hemisphere_hits` casts.

    The rays start off the surface by the pixel's shape's tolerance (``surface_error_rel · bounding_radius``,
    along the pixel's normal, as the shadow rays of :func:`polarshape.scene.raycast.cast_shadow_mask` do);
    their directions are :func:`hemisphere_directions` from a generator seeded with ``seed``.

    ``rows`` ((R,) indices into the P visible pixels, in raster order): only those pixels' rays, each the
    same as among all P.
    """
    device, dtype = geometry.points.device, geometry.points.dtype
    generator = torch.Generator(device=device).manual_seed(int(seed))
    pixels = geometry.mask.reshape(-1).nonzero().squeeze(1)  # (P,)
    normals = geometry.normals.reshape(-1, 3)[pixels]  # (P, 3)
    directions = hemisphere_directions(normals, samples, generator, rows=rows)  # (P, S, 3) or (R, S, 3)
    if rows is not None:
        pixels, normals = pixels[rows], normals[rows]  # (R,), (R, 3)
    points = geometry.points.reshape(-1, 3)[pixels]  # (P, 3)
    tolerance = torch.tensor([s.surface_error_rel * s.bounding_radius for s in scene.shapes], dtype=dtype, device=device)
    offset = tolerance[geometry.object_index.reshape(-1)[pixels]]  # (P,)
    origins = (points + offset[:, None] * normals).unsqueeze(1).expand_as(directions)  # (P, S, 3)
    return HemisphereRays(pixels, origins, directions)


def hemisphere_hits(scene: Scene, geometry: GeometryBuffers, samples: int, *, seed: int = 0) -> HemisphereHits:
    """Cast the ``samples`` hemisphere rays of every visible pixel of ``geometry`` (:func:`hemisphere_rays`)
    into ``scene``."""
    rays = hemisphere_rays(scene, geometry, samples, seed=seed)
    pixels, origins, directions = rays.pixels, rays.origins, rays.directions  # (P,), (P, S, 3), (P, S, 3)
    t, n, index = nearest_hits(scene.shapes, origins.reshape(-1, 3), directions.reshape(-1, 3))  # (P·S,) …
    d = directions.reshape(-1, 3)
    hit = torch.isfinite(t)
    hit_points = torch.where(hit[:, None], origins.reshape(-1, 3) + torch.where(hit, t, 0.0)[:, None] * d, 0.0)
    view = -d
    n = torch.where(((n * view).sum(-1) < 0)[:, None], -n, n)  # the side the ray arrives from
    p, s = directions.shape[:2]
    hits = GeometryBuffers(
        mask=hit.reshape(p, s), object_index=index.reshape(p, s),
        depth=torch.where(hit, hit_points[:, 2], torch.full_like(t, math.nan)).reshape(p, s),
        points=hit_points.reshape(p, s, 3), normals=n.reshape(p, s, 3), view=view.reshape(p, s, 3),
    )
    logger.debug("interreflection: %d pixels × %d rays, %.1f %% hit the scene", p, s, 100.0 * float(hit.float().mean()) if p else 0.0)
    return HemisphereHits(pixels=pixels, directions=directions, hits=hits, albedo_scale=albedo_scale_map(scene, hits),
                          solid_angle=2.0 * math.pi / samples)


def _pixel_buffers(geometry: GeometryBuffers, pixels: Tensor, samples: int) -> GeometryBuffers:
    """The buffers of ``pixels`` (P,) of ``geometry`` repeated for S samples: (P, S) views, no copies."""
    def rows(x: Tensor) -> Tensor:
        flat = x.reshape(-1, *x.shape[2:])[pixels]  # (P, …)
        return flat.unsqueeze(1).expand(flat.shape[0], samples, *flat.shape[1:])

    return GeometryBuffers(mask=rows(geometry.mask), object_index=rows(geometry.object_index), depth=rows(geometry.depth),
                           points=rows(geometry.points), normals=rows(geometry.normals), view=rows(geometry.view))


def one_bounce_stokes(scene: Scene, geometry: GeometryBuffers, bounce: HemisphereHits, light: Light, *,
                      shadows: bool = True, albedo_scale: Tensor | None = None) -> Tensor:
    """The once-bounced Stokes radiance of every pixel under one light (module docstring).

    Args:
        scene: the scene.
        geometry: the view's buffers (H, W).
        bounce: :func:`hemisphere_hits` of that view.
        light: the light that is on.
        shadows: cast shadows at the bounce points.
        albedo_scale: (H, W) albedo multipliers of the view (default: from the textures).

    Returns:
        (3, H, W), in each pixel's Stokes frame; add it to :func:`shade_stokes`'s direct radiance.
    """
    h, w = geometry.depth.shape
    out = torch.zeros(3, h * w, dtype=geometry.points.dtype, device=geometry.points.device)  # (3, H·W)
    if bounce.pixels.numel() == 0:
        return out.reshape(3, h, w)
    if albedo_scale is None:
        albedo_scale = albedo_scale_map(scene, geometry)
    samples = bounce.directions.shape[1]
    for start in range(0, bounce.pixels.numel(), _CHUNK_PIXELS):
        rows = slice(start, start + _CHUNK_PIXELS)
        pixels = bounce.pixels[rows]  # (C,)
        hits = GeometryBuffers(*(getattr(bounce.hits, f)[rows] for f in GeometryBuffers.__dataclass_fields__))
        radiance = shade_stokes(scene, hits, light, shadows=shadows, albedo_scale=bounce.albedo_scale[rows])[0]  # (C, S)
        here = _pixel_buffers(geometry, pixels, samples)  # (C, S)
        lit = radiance > 0
        stokes = shade_directions(scene, here, bounce.directions[rows], radiance * bounce.solid_angle, lit,
                                  albedo_scale.reshape(-1)[pixels].unsqueeze(1).expand(-1, samples))  # (3, C, S)
        out[:, pixels] = stokes.sum(-1)
    return out.reshape(3, h, w)
