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
pixels (every s-th row and column) and interpolated bilinearly to the others. The rays are cast
against the surface triangulated at every max(1, s // 2)-th row and column (four times the lattice's
density, not every pixel: at full frame the mesh, its ray-casting scene and the albedo look-up of the
hits otherwise cost more than the rays), and only the lattice's rows and columns that received light
are interpolated (none on a convex object).
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

from polarshape.cameras import Camera, OrthographicCamera
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


def _decimated(camera: Camera, step: int, offset: int) -> Camera:
    """``camera`` on the grid of its pixels ``offset + i · step`` (rows and columns)."""
    if step == 1 and offset == 0:
        return camera
    width, height = len(range(offset, camera.width, step)), len(range(offset, camera.height, step))
    if isinstance(camera, OrthographicCamera):
        cx, cy = camera.principal_point
        return OrthographicCamera(width, height, camera.pixel_size_m * step, (cx - offset) / step, (cy - offset) / step,
                                  even=False)
    return replace(camera, width=width, height=height, fx=camera.fx / step, fy=camera.fy / step,
                   cx=(camera.cx - offset) / step, cy=(camera.cy - offset) / step, even=False)


def _span(any_: Tensor, margin: int) -> tuple[int, int]:
    """[first, last + 1) of the True entries of a (N,) bool tensor, widened by ``margin`` (clipped)."""
    index = any_.nonzero().squeeze(1)
    if index.numel() == 0:
        return 0, 0
    return max(0, int(index[0]) - margin), min(any_.numel(), int(index[-1]) + 1 + margin)


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
    stride = _lattice_stride(int(surface.sum()), max_pixels)
    step = max(1, stride // 2)  # the mesh's grid: every step-th row and column
    grid = (slice((stride // 2) % step, None, step),) * 2  # through the lattice's rows and columns when step | stride
    try:
        mesh = depth_to_mesh(depth[grid], surface[grid], camera=_decimated(camera, step, (stride // 2) % step),
                             normals=np.where(surface[grid][..., None], n_np[grid], np.nan))
    except ValueError:  # no pixel of the surface on the mesh's grid
        return BounceEstimate(out, stride, 0.0)
    if len(mesh.faces) == 0:
        return BounceEstimate(out, stride, 0.0)
    material = FMBRDFMaterial(ior=params["ior"], k_s=params["k_s"], k_b=1.0, alpha=params["alpha"],
                              beta=params["beta"], kappa=params.get("kappa", 0.0))
    scene = Scene(camera=camera, objects=(SceneObject(MeshShape(mesh), material),), lights=tuple(lights))

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
    hit = to_numpy(bounce.hits.mask)
    rays_hit = float(hit.mean()) if hit.size else 0.0
    if not hit.any():  # nothing seen of itself (a convex object): no bounce anywhere
        logger.info("interreflection: no ray of %d pixels (stride %d, %d rays each) meets the surface",
                    int(on.sum()), stride, samples)
        return BounceEstimate(out, stride, 0.0)
    # every hit takes the body albedo of the surface point of the mesh's grid nearest to it
    k_b = to_numpy(albedo).astype(np.float64)
    _, nearest = cKDTree(points[grid][surface[grid]]).query(to_numpy(bounce.hits.points)[hit])
    scale = np.zeros(hit.shape)
    scale[hit] = k_b[grid][surface[grid]][nearest]
    bounce = replace(bounce, albedo_scale=torch.as_tensor(scale))
    here = as_t(np.where(on, k_b[rows, cols], 0.0))
    coarse = torch.stack([one_bounce_stokes(scene, g, bounce, light, albedo_scale=here) for light in lights])  # (K, 3, h', w')
    if stride == 1:
        out = coarse.to(device=device, dtype=dtype)
    else:  # bilinear from the lattice (its pixels sit at stride // 2 + i · stride), over the part that received light
        lit = coarse.abs().amax(dim=(0, 1)) > 0  # (h', w')
        r0, r1 = _span(lit.any(1), 1)
        c0, c1 = _span(lit.any(0), 1)  # a lattice cell of 0 around it: the same values as over the whole lattice
        if r1 > r0 and c1 > c0:
            full = F.interpolate(coarse[..., r0:r1, c0:c1], scale_factor=stride, mode="bilinear", align_corners=False)
            y0, x0 = r0 * stride, c0 * stride
            y1, x1 = min(h, y0 + full.shape[-2]), min(w, x0 + full.shape[-1])
            out[..., y0:y1, x0:x1] = full[..., : y1 - y0, : x1 - x0].to(device=device, dtype=dtype)
    out = out * torch.as_tensor(surface, device=device).to(dtype)
    logger.info("interreflection: one bounce estimated on %d pixels (stride %d, %d rays each), %.1f %% of the rays "
                "meet the surface", int(on.sum()), stride, samples, 100 * rays_hit)
    return BounceEstimate(out, stride, rays_hit)
