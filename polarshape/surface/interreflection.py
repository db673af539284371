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

Before any ray is cast, :func:`surface_below_tangent_planes` tries to prove that none can meet the surface
(a convex object: every mesh vertex below every lattice point's tangent plane raised by the rays' start-off);
then the stage skips as when no ray met it, without building the ray-casting scene.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
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

__all__ = ["BounceEstimate", "estimate_one_bounce", "surface_below_tangent_planes"]

#: the tiles of :func:`surface_below_tangent_planes`, vertices per side, each size half the one before: every
#: point against every tile of the first size, then only the tiles not cleared, split in four
_TILE_SIZES = (16, 8, 4, 2, 1)
#: (point, tile) pairs bounded at once by :func:`surface_below_tangent_planes` (memory ∝ this)
_PAIRS_CHUNK = 1 << 18
#: the ray caster's float32 rounding (origins, directions, vertices, its hit test: a few units in the last
#: place of the largest coordinate), covered 64 times over: 2⁻¹⁸ of the largest coordinate
_FLOAT32_MARGIN = 2.0**-18


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


@dataclass(frozen=True)
class _Tiles:
    """One level of square tiles of the vertex grid, each as a slab (:func:`surface_below_tangent_planes`):
    every vertex of a tile is c + a m + b with b ⊥ m, |a| ≤ δ, |b| ≤ ρ."""

    slabs: Tensor  # (8, T): c (3), unit m (3), δ, ρ
    witness: Tensor  # (3, T) the tile's vertex nearest c (0 for an empty tile)
    occupied: Tensor  # (T,) bool: the tile holds a vertex
    width: int  # tiles per row


def _tiles(vertices: Tensor, vertex_normals: Tensor, size: int) -> _Tiles:
    """The (Hp / size) × (Wp / size) tiles of ``size``² vertices of the (Hp, Wp, 3) grids (NaN: no vertex)."""
    hp, wp = vertices.shape[:2]
    rows, width = hp // size, wp // size

    def blocks(x: Tensor) -> Tensor:  # (Hp, Wp, 3) → (T, size², 3)
        return x.reshape(rows, size, width, size, 3).transpose(1, 2).reshape(rows * width, size * size, 3)

    v = blocks(vertices)  # (T, s², 3)
    valid = torch.isfinite(v).all(-1)  # (T, s²)
    v = torch.where(valid[..., None], v, 0.0)
    count = valid.sum(1)  # (T,)
    centre = v.sum(1) / count.clamp_min(1)[:, None]  # (T, 3)
    axis = torch.where(valid[..., None], torch.nan_to_num(blocks(vertex_normals), nan=0.0), 0.0).sum(1)  # (T, 3)
    norm = axis.norm(dim=-1, keepdim=True)  # any unit vector bounds; the tile's mean normal bounds best
    axis = torch.where(norm > 1e-12, axis / norm.clamp_min(1e-12), axis.new_tensor([0.0, 0.0, -1.0]))
    d = v - centre[:, None]  # (T, s², 3)
    a = (d * axis[:, None]).sum(-1)  # (T, s²)
    lateral = (d - a[..., None] * axis[:, None]).norm(dim=-1)  # (T, s²)
    thickness = torch.where(valid, a.abs(), 0.0).amax(1, keepdim=True)  # (T, 1)
    radius = torch.where(valid, lateral, 0.0).amax(1, keepdim=True)  # (T, 1)
    nearest = torch.where(valid, d.norm(dim=-1), math.inf).argmin(1)  # (T,)
    witness = v[torch.arange(v.shape[0], device=v.device), nearest]  # (T, 3)
    return _Tiles(torch.cat([centre, axis, thickness, radius], dim=1).T.contiguous(), witness.T.contiguous(),
                  count > 0, width)


def _slab_bound(rays: Tensor, slabs: Tensor, *, dense: bool = False) -> Tensor:
    """n̂·(v − p) − threshold bounded over each tile's vertices v, from ``rays`` (4, ·) = (n̂, n̂·p + threshold)
    and ``slabs`` (8, ·) (:class:`_Tiles`): n̂·(c − p) + |n̂·m| δ + |n̂ − (n̂·m) m| ρ − threshold; (N,) for N
    columns of each (pairs), or (P, T) for every column of ``rays`` against every column of ``slabs`` (``dense``).
    Rows of components, not columns: every operation runs on contiguous rows."""
    if dense:
        along = rays[:3].T @ slabs[3:6]  # (P, T)
        towards = rays[:3].T @ slabs[:3] - rays[3][:, None]
    else:
        along = rays[0] * slabs[3] + rays[1] * slabs[4] + rays[2] * slabs[5]  # (N,)
        towards = rays[0] * slabs[0] + rays[1] * slabs[1] + rays[2] * slabs[2] - rays[3]
    return towards + along.abs() * slabs[6] + (1.0 - along * along).clamp_min(0.0).sqrt() * slabs[7]


def surface_below_tangent_planes(vertices: Tensor, vertex_normals: Tensor, points: Tensor, normals: Tensor,
                                 offset: float) -> bool:
    """Whether no ray of :func:`polarshape.scene.interreflection.hemisphere_hits` can meet the surface.

    Those rays start at o = p + offset · n (the shape's start-off, along the normal n they are cast
    about) into the hemisphere of n (n·ω > 0) and meet triangles whose corners are mesh vertices. A hit
    q = o + t ω (t ≥ 0) has n̂·(q − p) = offset·|n| + t n̂·ω ≥ offset·|n|, and a linear function's largest
    value on a triangle is at a corner; so when every vertex v has n̂·(v − p) < offset·|n| (less the ray
    caster's float32 rounding, :data:`_FLOAT32_MARGIN`), no ray can meet the surface. The test is exact,
    not sampled: a convex object passes it; a concave one, or a surface too noisy to clear, does not
    (then the rays decide).

    The largest n̂·(v − p) over the vertices is bounded tile by tile, from square tiles of
    ``_TILE_SIZES[0]``² vertices (every point against every tile) down to single vertices: with a tile's
    vertices v = c + a m + b (b ⊥ m, |a| ≤ δ, |b| ≤ ρ; m the tile's mean normal, though any unit vector
    would do), n̂·(v − p) ≤ n̂·(c − p) + |n̂·m| δ + |n̂ − (n̂·m) m| ρ. A tile whose bound is below the
    threshold is cleared with all its vertices; the others are split into their four sub-tiles, and on
    single vertices (δ = ρ = 0) the bound is the value itself. The vertex nearest each top tile's centre is
    checked exactly first: on a concave surface one of them is usually above some point's plane.

    Args:
        vertices: (Hm, Wm, 3) the mesh's vertices on its grid (a superset does too), NaN where none.
        vertex_normals: (Hm, Wm, 3) normals on that grid (NaN allowed): they only orient the tiles.
        points: (P, 3) the points the rays leave from.
        normals: (P, 3) the (nonzero) normals they are cast about.
        offset: the start-off along the normals (metres, the shape's ``surface_error_rel · bounding_radius``).

    Returns:
        True when no ray can meet the surface, False when one may.
    """
    vertices = vertices.to(torch.float64)
    points, normals = points.to(vertices), normals.to(vertices)
    if points.shape[0] == 0 or not torch.isfinite(vertices).all(-1).any():
        return True
    length = normals.norm(dim=-1, keepdim=True)  # (P, 1)
    unit = normals / length  # (P, 3)
    scale = max(float(torch.nan_to_num(vertices, nan=0.0).abs().max()), float(points.abs().max()))
    threshold = offset * length - _FLOAT32_MARGIN * scale  # (P, 1): n̂·(v − p) at or above it, a ray may hit v
    rays = torch.cat([unit, (unit * points).sum(-1, keepdim=True) + threshold], dim=1).T.contiguous()  # (4, P)
    top = _TILE_SIZES[0]
    hm, wm = vertices.shape[:2]
    pad = (0, 0, 0, -wm % top, 0, -hm % top)  # the grids padded to whole top tiles
    vertices = F.pad(vertices, pad, value=math.nan)
    vertex_normals = F.pad(vertex_normals.to(vertices), pad, value=math.nan)
    tiles = [_tiles(vertices, vertex_normals, size) for size in _TILE_SIZES]
    sub = torch.arange(2, device=vertices.device)

    def split(level: int, point: Tensor, tile: Tensor) -> tuple[Tensor, Tensor]:
        """The (point, tile) pairs (N,) of ``level`` as the pairs of their tiles' occupied sub-tiles (N'',)."""
        row, col = tile // tiles[level].width, tile % tiles[level].width
        child = ((2 * row[:, None, None] + sub[:, None]) * tiles[level + 1].width
                 + 2 * col[:, None, None] + sub).reshape(-1)  # (N·4,)
        point = point.repeat_interleave(4)
        keep = tiles[level + 1].occupied[child]
        return point[keep], child[keep]

    def cleared(level: int, point: Tensor, tile: Tensor) -> bool:
        """Whether every (point, tile) pair (N,) of ``level`` is below its threshold (depth first, in chunks)."""
        for start in range(0, point.numel(), _PAIRS_CHUNK):
            i, t = point[start:start + _PAIRS_CHUNK], tile[start:start + _PAIRS_CHUNK]
            open_ = _slab_bound(rays[:, i], tiles[level].slabs[:, t]) >= 0  # (N,)
            if level == len(tiles) - 1:
                if bool(open_.any()):
                    return False
            elif not cleared(level + 1, *split(level, i[open_], t[open_])):
                return False
        return True

    first = tiles[0].occupied.nonzero().squeeze(1)  # (T0,)
    slabs, witness = tiles[0].slabs[:, first], tiles[0].witness[:, first]  # (8, T0), (3, T0)
    blocks = -(-points.shape[0] * first.numel() // _PAIRS_CHUNK)  # every point against every top tile, in blocks
    for block in range(blocks):  # of every blocks-th point: each spans the surface, the first finds a concavity
        among = torch.arange(block, points.shape[0], blocks, device=vertices.device)  # (C,)
        if bool((rays[:3, among].T @ witness >= rays[3, among, None]).any()):  # a vertex above: found at once
            return False
        open_ = _slab_bound(rays[:, among], slabs, dense=True) >= 0  # (C, T0)
        i, t = open_.nonzero().unbind(1)
        if not cleared(1, *split(0, among[i], first[t])):
            return False
    return True


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
    # the rays' start-off is the shape's (hemisphere_hits); the mesh's vertices are points[grid] on surface[grid]
    # (up to the decimated camera's float64 rounding, far inside the test's margin)
    shape = scene.shapes[0]
    if surface_below_tangent_planes(as_t(np.where(surface[grid][..., None], points[grid], np.nan)), as_t(n_np[grid]),
                                    g.points[on], g.normals[on], shape.surface_error_rel * shape.bounding_radius):
        # every mesh point below every lattice point's tangent plane (a convex object): no ray cast
        logger.info("interreflection: no ray of %d pixels (stride %d, %d rays each) can meet the surface: it lies "
                    "below each pixel's tangent plane", int(on.sum()), stride, samples)
        return BounceEstimate(out, stride, 0.0)
    bounce = hemisphere_hits(scene, g, samples, seed=seed)
    hit = to_numpy(bounce.hits.mask)
    rays_hit = float(hit.mean()) if hit.size else 0.0
    if not hit.any():  # nothing seen of itself (a convex object): no bounce anywhere
        logger.info("interreflection: no ray of %d pixels (stride %d, %d rays each) meets the surface",
                    int(on.sum()), stride, samples)
        return BounceEstimate(out, stride, 0.0)
    from scipy.spatial import cKDTree  # only when rays met the surface

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
