"""Ray casting a scene into per-pixel geometry buffers, and cast-shadow tests.

Camera frame (OpenCV: x right, y down, z forward), metres; one ray per raw-mosaic pixel.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from polarshape.cameras import Camera
from polarshape.lights import Light
from polarshape.scene.geometry import Shape

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class GeometryBuffers:
    """Per-pixel geometry of one view (a "G-buffer"); H, W = raw-mosaic size.

    Attributes:
        mask: (H, W) bool, the pixel's ray hits an object.
        object_index: (H, W) int64 index into the shape list, −1 where nothing is hit.
        depth: (H, W) z of the hit point in the camera frame, metres; NaN where nothing is hit.
        points: (H, W, 3) hit points, metres; 0 where nothing is hit.
        normals: (H, W, 3) unit normals (outward for closed shapes, turned toward the camera for
            two-sided ones, so N·V > 0 on the visible side); 0 where nothing is hit.
        view: (H, W, 3) unit V, from the surface toward the camera (also set where nothing is hit).
    """

    mask: Tensor
    object_index: Tensor
    depth: Tensor
    points: Tensor
    normals: Tensor
    view: Tensor


def nearest_hits(shapes: Sequence[Shape], origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The first hit of each ray among ``shapes``.

    Args:
        shapes: the scene's shapes.
        origins, directions: (N, 3) rays (unit directions), metres, camera frame.

    Returns:
        t (N,) (``inf`` where every shape is missed), the hit shape's normal there (N, 3) (zero
        where missed) and the index of the shape hit (N,) int64 (−1 where missed).
    """
    best_t = torch.full((origins.shape[0],), math.inf, dtype=origins.dtype, device=origins.device)  # (N,)
    best_n = torch.zeros_like(origins)  # (N, 3)
    index = torch.full((origins.shape[0],), -1, dtype=torch.int64, device=origins.device)  # (N,)
    for k, shape in enumerate(shapes):
        t, n = shape.intersect(origins, directions)
        closer = t < best_t
        best_t = torch.where(closer, t, best_t)
        best_n = torch.where(closer[:, None], n, best_n)
        index = torch.where(closer, torch.full_like(index, k), index)
    return best_t, best_n, index


def rasterize(
    shapes: Sequence[Shape],
    camera: Camera,
    *,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float64,
) -> GeometryBuffers:
    """Cast one ray per pixel of ``camera`` into ``shapes``; the nearest hit wins.

    Example:
        >>> from polarshape.cameras import OrthographicCamera
        >>> from polarshape.scene.geometry import SphereShape
        >>> g = rasterize([SphereShape((0, 0, 1), 0.01)], OrthographicCamera(64, 64, 4e-4))
        >>> g.normals.shape, bool(g.mask[32, 32])
        (torch.Size([64, 64, 3]), True)
    """
    if len(shapes) == 0:
        raise ValueError("the scene has no objects; add at least one shape")
    origins, directions = camera.rays(device=device, dtype=dtype)  # (H, W, 3) each
    h, w = origins.shape[:2]
    o, d = origins.reshape(-1, 3), directions.reshape(-1, 3)  # (P, 3)
    best_t, best_n, index = nearest_hits(shapes, o, d)
    mask = torch.isfinite(best_t)
    points = torch.where(mask[:, None], o + torch.where(mask, best_t, 0.0)[:, None] * d, 0.0)  # (P, 3)
    view = camera.view_directions(torch.where(mask[:, None], points, d))  # (P, 3)
    if not mask.all():
        # V of a background pixel: toward the camera along its ray
        view = torch.where(mask[:, None], view, -d)
    two_sided = torch.tensor([s.two_sided for s in shapes], device=device)[index.clamp_min(0)] & mask  # (P,)
    facing_away = (best_n * view).sum(-1) < 0
    normals = torch.where((two_sided & facing_away)[:, None], -best_n, best_n)
    depth = torch.where(mask, points[:, 2], torch.full_like(best_t, math.nan))
    logger.debug("rasterised %dx%d pixels, %d hits", w, h, int(mask.sum()))
    return GeometryBuffers(
        mask=mask.reshape(h, w),
        object_index=index.reshape(h, w),
        depth=depth.reshape(h, w),
        points=points.reshape(h, w, 3),
        normals=normals.reshape(h, w, 3),
        view=view.reshape(h, w, 3),
    )


def cast_shadow_mask(shapes: Sequence[Shape], geometry: GeometryBuffers, light: Light) -> Tensor:
    """Pixels in cast shadow: the surface faces the light (N·L > 0) but another part of the scene
    blocks the segment toward it. Attached shadow (N·L ≤ 0) is *not* flagged here (the BRDF is
    zero there anyway).

    Shadow rays start at the hit point offset along N by the hit shape's
    ``surface_error_rel × bounding_radius`` (exact shapes: 1e-6 R; tessellated ones: 1e-3 R,
    above the ≈1e-4 R gap between facets and the surface they stand for), or by 64 ulps of the
    point's coordinates if that is more (float32), and stop at the light (point lights) or go on
    forever (directional).

    Args:
        shapes: the shapes ``geometry`` was rasterised from (same order).
        geometry: the view's buffers.
        light: a directional or point light.

    Returns:
        (H, W) bool.
    """
    light_dir, _, dist = light.illuminate(geometry.points)  # (H, W, 3), _, (H, W)
    facing = geometry.mask & ((geometry.normals * light_dir).sum(-1) > 0)  # (H, W)
    shadow = torch.zeros_like(facing)
    if not facing.any():
        return shadow
    tolerance = torch.tensor(
        [s.surface_error_rel * s.bounding_radius for s in shapes], dtype=geometry.points.dtype, device=geometry.points.device
    )  # (S,)
    points = geometry.points[facing]  # (M, 3)
    # at least a few ulps of the coordinates, or float32 points would start inside their surface
    rounding = 64 * torch.finfo(points.dtype).eps * points.abs().amax(dim=-1)  # (M,)
    offset = torch.maximum(tolerance[geometry.object_index[facing]], rounding)  # (M,)
    origins = points + offset[:, None] * geometry.normals[facing]  # (M, 3)
    directions = light_dir[facing]  # (M, 3)
    t_max = dist[facing] - offset  # (M,)
    blocked = torch.zeros(origins.shape[0], dtype=torch.bool, device=origins.device)
    for shape in shapes:
        blocked |= shape.occluded(origins, directions, t_max)
    shadow[facing] = blocked
    return shadow


def superpixel_ground_truth(geometry: GeometryBuffers, object_mask: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Ground truth at super-pixel resolution (capture-format.md ``ground_truth/``).

    A super-pixel is on the object when all four of its sites are; its normal is the normalised
    mean of the four normals and its depth their mean.

    Args:
        geometry: buffers at raw-mosaic resolution (2H, 2W).
        object_mask: (2H, 2W) bool, which hits count as the object (default ``geometry.mask``).

    Returns:
        ``(normals, depth, mask)``: (H, W, 3) unit camera-frame normals, NaN off the object;
        (H, W) depth (z, metres), NaN off the object; (H, W) bool.
    """
    mask = geometry.mask if object_mask is None else object_mask
    h2, w2 = mask.shape
    blocks = mask.reshape(h2 // 2, 2, w2 // 2, 2)
    sp_mask = blocks.all(dim=3).all(dim=1)  # (H, W)
    n = geometry.normals.reshape(h2 // 2, 2, w2 // 2, 2, 3).sum(dim=(1, 3))  # (H, W, 3)
    n = torch.nn.functional.normalize(n, dim=-1)
    z = torch.nan_to_num(geometry.depth).reshape(h2 // 2, 2, w2 // 2, 2).mean(dim=(1, 3))  # (H, W)
    nan = torch.full_like(z, math.nan)
    return torch.where(sp_mask[..., None], n, nan[..., None]), torch.where(sp_mask, z, nan), sp_mask
