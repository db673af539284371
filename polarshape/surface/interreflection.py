"""Light the object sends onto itself, estimated from a recovered surface (concave objects).

A cup, a crater or a fold reflects light onto itself: inside the concavity the photos are brighter
than the lights alone explain, and a fit that knows only direct light bends the normals to explain
the excess. :func:`estimate_one_bounce` renders that excess from the current estimate — the surface
integrated from the recovered normals, triangulated (:func:`polarshape.surface.mesh.depth_to_mesh`),
with the recovered material and per-pixel body albedo — with the simulator's one-bounce renderer
(:mod:`polarshape.scene.interreflection`: hemisphere rays from every pixel's point, the FMBRDF at
both ends, the bounced light taken as unpolarised). The pipeline (``interreflection:`` in the run
configuration) subtracts it from the Stokes images and re-fits, a fixed point of a few iterations.

The bounce is smooth across a surface, so it is rendered on a lattice of at most ``max_pixels``
pixels (every s-th row and column) and interpolated bilinearly to the others.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import Tensor

from polarshape.cameras import Camera
from polarshape.checks import to_numpy
from polarshape.lights import Lights
from polarshape.scene.geometry import MeshShape
from polarshape.scene.interreflection import hemisphere_hits, one_bounce_stokes
from polarshape.scene.materials import FMBRDFMaterial
from polarshape.scene.objects import Scene, SceneObject
from polarshape.scene.raycast import GeometryBuffers
from polarshape.surface.mesh import depth_to_mesh

logger = logging.getLogger(__name__)

__all__ = ["BounceEstimate", "estimate_one_bounce"]


@dataclass(frozen=True)
class BounceEstimate:
    """The once-bounced light of every pixel and light.

    Attributes:
        stokes: (K, 3, H, W) Stokes (each pixel's frame, the capture's units); 0 where not estimated.
        stride: the lattice step it was rendered on (1 = every pixel).
        rays_hit: fraction of the hemisphere rays that met the surface (0 for a convex object).
    """

    stokes: Tensor
    stride: int
    rays_hit: float


def _lattice_stride(pixels: int, max_pixels: int) -> int:
    return max(1, math.ceil(math.sqrt(pixels / max(max_pixels, 1))))


def estimate_one_bounce(normals: Tensor, albedo: Tensor, depth: np.ndarray, camera: Camera, view: Tensor,
                        lights: Lights, params: dict[str, float], *, samples: int = 32, max_pixels: int = 16384,
                        seed: int = 0) -> BounceEstimate:
    """One bounce of the capture's lights off the recovered surface.

    Args:
        normals: (H, W, 3) recovered unit normals (NaN or 0 outside the surface), camera frame.
        albedo: (H, W) per-pixel body albedo k_b (the capture's units).
        depth: (H, W) integrated camera-frame z, NaN outside the surface.
        camera: the super-pixel camera the depth was integrated with.
        view: (H, W, 3) unit view directions (surface → camera).
        lights: the capture's K lights.
        params: the recovered FMBRDF parameters (``ior``, ``k_s``, ``alpha``, ``beta``, ``kappa``).
        samples: hemisphere rays per pixel.
        max_pixels: the most pixels the bounce is rendered at (a lattice above it).
        seed: seed of the ray directions.

    Returns:
        :class:`BounceEstimate` with (K, 3, H, W) Stokes on the device and dtype of ``normals``.
    """
    dtype, device = normals.dtype, normals.device
    h, w = depth.shape
    n_np = to_numpy(normals).astype(np.float64)
    surface = np.isfinite(depth) & np.all(np.isfinite(n_np), axis=-1)
    out = torch.zeros(len(lights), 3, h, w, dtype=dtype, device=device)
    if surface.sum() < 4:
        return BounceEstimate(out, 1, 0.0)
    mesh = depth_to_mesh(depth, surface, camera=camera, normals=np.where(surface[..., None], n_np, np.nan))
    if len(mesh.faces) == 0:
        return BounceEstimate(out, 1, 0.0)
    material = FMBRDFMaterial(ior=params["ior"], k_s=params["k_s"], k_b=1.0, alpha=params["alpha"],
                              beta=params["beta"], kappa=params.get("kappa", 0.0))
    scene = Scene(camera=camera, objects=(SceneObject(MeshShape(mesh), material),), lights=tuple(lights))

    stride = _lattice_stride(int(surface.sum()), max_pixels)
    rows, cols = slice(stride // 2, None, stride), slice(stride // 2, None, stride)
    points = camera.unproject(depth)  # (H, W, 3)
    on = surface[rows, cols]  # (h', w')
    as_t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
    g = GeometryBuffers(
        mask=torch.as_tensor(on), object_index=torch.where(torch.as_tensor(on), 0, -1),
        depth=as_t(np.where(on, depth[rows, cols], np.nan)), points=as_t(np.where(on[..., None], points[rows, cols], 0.0)),
        normals=as_t(np.where(on[..., None], n_np[rows, cols], 0.0)),
        view=as_t(to_numpy(view)[rows, cols]),
    )
    bounce = hemisphere_hits(scene, g, samples, seed=seed)
    # every hit takes the body albedo of the recovered surface point nearest to it
    k_b = to_numpy(albedo).astype(np.float64)
    tree = cKDTree(points[surface])
    hit = to_numpy(bounce.hits.mask)
    scale = np.zeros(hit.shape)
    if hit.any():
        _, nearest = tree.query(to_numpy(bounce.hits.points)[hit])
        scale[hit] = k_b[surface][nearest]
    bounce = replace(bounce, albedo_scale=torch.as_tensor(scale))
    here = as_t(np.where(on, k_b[rows, cols], 0.0))
    coarse = torch.stack([one_bounce_stokes(scene, g, bounce, light, albedo_scale=here) for light in lights])  # (K, 3, h', w')
    rays_hit = float(hit.mean()) if hit.size else 0.0
    if stride == 1:
        out = coarse.to(device=device, dtype=dtype)
    else:  # bilinear from the lattice (its pixels sit at stride // 2 + i · stride)
        full = F.interpolate(coarse, scale_factor=stride, mode="bilinear", align_corners=False)
        out[..., : min(h, full.shape[-2]), : min(w, full.shape[-1])] = full[..., :h, :w].to(device=device, dtype=dtype)
    out = out * torch.as_tensor(surface, device=device).to(dtype)
    logger.info("interreflection: one bounce estimated on %d pixels (stride %d, %d rays each), %.1f %% of the rays "
                "meet the surface", int(on.sum()), stride, samples, 100 * rays_hit)
    return BounceEstimate(out, stride, rays_hit)
