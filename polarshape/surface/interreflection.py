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

Before any ray is cast, :func:`tangent_plane_open_points` tries to prove that none can meet the surface
(a convex object: every mesh vertex below every lattice point's tangent plane raised by the rays' start-off).
A recovered convex object is often not quite convex at its rim (steep normals integrated): a few lattice points
there have a vertex just above their plane. Those points' rays alone are then tested against the few triangles
above their planes (:func:`rays_may_meet_triangles`, exact up to a margin wider than the ray caster's rounding).
When every ray is proven to miss, the stage skips as when no ray met it, without building the ray-casting scene
(nor importing open3d); more than a few hundred open points (a concavity) or any ray that may hit: the rays are cast.
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
from polarshape.scene.interreflection import HemisphereRays, hemisphere_hits, hemisphere_rays, one_bounce_stokes
from polarshape.scene.materials import FMBRDFMaterial
from polarshape.scene.objects import Scene, SceneObject
from polarshape.scene.raycast import GeometryBuffers
from polarshape.surface.mesh import depth_to_mesh

logger = logging.getLogger(__name__)

__all__ = ["BounceEstimate", "estimate_one_bounce", "rays_may_meet_triangles", "surface_below_tangent_planes",
           "tangent_plane_open_points"]

#: the tiles of :func:`tangent_plane_open_points`, vertices per side, each size half the one before: every
#: point against every tile of the first size, then only the tiles not cleared, split in four
_TILE_SIZES = (16, 8, 4, 2, 1)
#: (point, tile) pairs bounded at once by :func:`tangent_plane_open_points` (memory ∝ this)
_PAIRS_CHUNK = 1 << 18
#: the ray caster's float32 rounding (origins, directions, vertices, its hit test: a few units in the last
#: place of the largest coordinate), covered 64 times over: 2⁻¹⁸ of the largest coordinate
_FLOAT32_MARGIN = 2.0**-18
#: the most points left open by the tangent-plane test whose rays are tested one by one against the triangles they
#: may reach (a convex object whose recovered rim is not quite convex: a handful); more: a concavity, cast the rays
_MAX_OPEN_POINTS = 256
#: open points whose reachable triangles are found at once (memory ∝ this × the mesh's vertices and faces)
_OPEN_POINTS_CHUNK = 16
#: the most (ray, triangle) pairs tested in all before the ray caster is the cheaper way to decide
_MAX_RAY_TRIANGLE_PAIRS = 1 << 20


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


def _start_planes(points: Tensor, normals: Tensor, offset: float, scale: float) -> Tensor:
    """(4, P) the planes a vertex must reach for a ray of a point to meet it: n̂ (3) and n̂·p + threshold, with
    threshold = offset·|n| − the float32 margin (:func:`tangent_plane_open_points`); points, normals (P, 3)."""
    length = normals.norm(dim=-1, keepdim=True)  # (P, 1)
    unit = normals / length  # (P, 3)
    threshold = offset * length - _FLOAT32_MARGIN * scale  # (P, 1): n̂·(v − p) at or above it, a ray may hit v
    return torch.cat([unit, (unit * points).sum(-1, keepdim=True) + threshold], dim=1).T.contiguous()


def _coordinate_scale(vertices: Tensor, points: Tensor) -> float:
    """The largest coordinate of the finite ``vertices`` (…, 3) and of ``points`` (P, 3): the scale of the ray
    caster's float32 rounding."""
    return max(float(torch.nan_to_num(vertices, nan=0.0).abs().max()), float(points.abs().max()))


def tangent_plane_open_points(vertices: Tensor, vertex_normals: Tensor, points: Tensor, normals: Tensor,
                              offset: float, *, limit: int) -> Tensor | None:
    """The points some of whose rays of :func:`polarshape.scene.interreflection.hemisphere_hits` may meet the
    surface, by the tangent-plane bound; None when there are more than ``limit`` of them.

    Those rays start at o = p + offset · n (the shape's start-off, along the normal n they are cast
    about) into the hemisphere of n (n·ω > 0) and meet triangles whose corners are mesh vertices. A hit
    q = o + t ω (t ≥ 0) has n̂·(q − p) = offset·|n| + t n̂·ω ≥ offset·|n|, and a linear function's largest
    value on a triangle is at a corner; so when every vertex v has n̂·(v − p) < offset·|n| (less the ray
    caster's float32 rounding, :data:`_FLOAT32_MARGIN`), no ray of p can meet the surface: p is closed.
    The test is exact, not sampled: every point of a convex object is closed; a concave one, or a surface
    too noisy to clear, has open points (then their rays decide, :func:`rays_may_meet_triangles`).

    The largest n̂·(v − p) over the vertices is bounded tile by tile, from square tiles of
    ``_TILE_SIZES[0]``² vertices (every point against every tile) down to single vertices: with a tile's
    vertices v = c + a m + b (b ⊥ m, |a| ≤ δ, |b| ≤ ρ; m the tile's mean normal, though any unit vector
    would do), n̂·(v − p) ≤ n̂·(c − p) + |n̂·m| δ + |n̂ − (n̂·m) m| ρ. A tile whose bound is below the
    threshold is cleared with all its vertices; the others are split into their four sub-tiles, and on
    single vertices (δ = ρ = 0) the bound is the value itself. The vertex nearest each top tile's centre is
    checked exactly first: on a concave surface one of them is usually above some point's plane, and the
    search stops as soon as more than ``limit`` points are open (a point found open is bounded no further).

    Args:
        vertices: (Hm, Wm, 3) the mesh's vertices on its grid (a superset does too), NaN where none.
        vertex_normals: (Hm, Wm, 3) normals on that grid (NaN allowed): they only orient the tiles.
        points: (P, 3) the points the rays leave from.
        normals: (P, 3) the (nonzero) normals they are cast about.
        offset: the start-off along the normals (metres, the shape's ``surface_error_rel · bounding_radius``).
        limit: the most open points returned (0: stop at the first).

    Returns:
        (O,) int64 indices into ``points``, ascending, of the open points (empty: no ray can meet the
        surface), or None when more than ``limit`` points are open.
    """
    vertices = vertices.to(torch.float64)
    points, normals = points.to(vertices), normals.to(vertices)
    nothing = torch.zeros(0, dtype=torch.int64, device=vertices.device)
    if points.shape[0] == 0 or not torch.isfinite(vertices).all(-1).any():
        return nothing
    rays = _start_planes(points, normals, offset, _coordinate_scale(vertices, points))  # (4, P)
    top = _TILE_SIZES[0]
    hm, wm = vertices.shape[:2]
    pad = (0, 0, 0, -wm % top, 0, -hm % top)  # the grids padded to whole top tiles
    vertices = F.pad(vertices, pad, value=math.nan)
    vertex_normals = F.pad(vertex_normals.to(vertices), pad, value=math.nan)
    tiles = [_tiles(vertices, vertex_normals, size) for size in _TILE_SIZES]
    sub = torch.arange(2, device=vertices.device)
    is_open = torch.zeros(points.shape[0], dtype=torch.bool, device=vertices.device)  # (P,)

    def too_many(opened: Tensor) -> bool:
        """Mark the points ``opened`` (N,) open; whether more than ``limit`` are."""
        is_open[opened] = True
        return int(is_open.sum()) > limit

    def split(level: int, point: Tensor, tile: Tensor) -> tuple[Tensor, Tensor]:
        """The (point, tile) pairs (N,) of ``level`` as the pairs of their tiles' occupied sub-tiles (N'',)."""
        row, col = tile // tiles[level].width, tile % tiles[level].width
        child = ((2 * row[:, None, None] + sub[:, None]) * tiles[level + 1].width
                 + 2 * col[:, None, None] + sub).reshape(-1)  # (N·4,)
        point = point.repeat_interleave(4)
        keep = tiles[level + 1].occupied[child]
        return point[keep], child[keep]

    def searched(level: int, point: Tensor, tile: Tensor) -> bool:
        """Every (point, tile) pair (N,) of ``level`` bounded, its open points marked (depth first, in chunks);
        False when more than ``limit`` points are open."""
        for start in range(0, point.numel(), _PAIRS_CHUNK):
            i, t = point[start:start + _PAIRS_CHUNK], tile[start:start + _PAIRS_CHUNK]
            closed = ~is_open[i]  # a point already open needs no more bounds
            i, t = i[closed], t[closed]
            open_ = _slab_bound(rays[:, i], tiles[level].slabs[:, t]) >= 0  # (N,)
            if level == len(tiles) - 1:
                if bool(open_.any()) and too_many(i[open_]):
                    return False
            elif not searched(level + 1, *split(level, i[open_], t[open_])):
                return False
        return True

    first = tiles[0].occupied.nonzero().squeeze(1)  # (T0,)
    slabs, witness = tiles[0].slabs[:, first], tiles[0].witness[:, first]  # (8, T0), (3, T0)
    blocks = -(-points.shape[0] * first.numel() // _PAIRS_CHUNK)  # every point against every top tile, in blocks
    for block in range(blocks):  # of every blocks-th point: each spans the surface, the first finds a concavity
        among = torch.arange(block, points.shape[0], blocks, device=vertices.device)  # (C,)
        above = (rays[:3, among].T @ witness >= rays[3, among, None]).any(1)  # (C,) a vertex above: open at once
        if bool(above.any()) and too_many(among[above]):
            return None
        among = among[~above]
        open_ = _slab_bound(rays[:, among], slabs, dense=True) >= 0  # (C, T0)
        i, t = open_.nonzero().unbind(1)
        if not searched(1, *split(0, among[i], first[t])):
            return None
    return is_open.nonzero().squeeze(1)


def surface_below_tangent_planes(vertices: Tensor, vertex_normals: Tensor, points: Tensor, normals: Tensor,
                                 offset: float) -> bool:
    """Whether no ray of :func:`polarshape.scene.interreflection.hemisphere_hits` can meet the surface: every
    mesh vertex below every point's tangent plane raised by the rays' start-off (a convex object).

    :func:`tangent_plane_open_points` (its arguments, the same shapes) with no open point allowed; it stops
    at the first open one.
    """
    return tangent_plane_open_points(vertices, vertex_normals, points, normals, offset, limit=0) is not None


def rays_may_meet_triangles(origins: Tensor, directions: Tensor, triangles: Tensor, margin: float) -> Tensor:
    """Whether each ray comes within reach of its triangle: a conservative ray–triangle test.

    The ray o + t ω, t ≥ −margin, is tested against the triangle's prism widened by ``margin`` on each of
    its five sides (the slab |n̂·(x − a)| ≤ margin about the triangle's plane, the three edges' outward
    in-plane half-planes moved out by margin): every intersection of the set of t each side admits
    (Cyrus–Beck clipping, float64). The prism holds every point within ``margin`` of the triangle, so a
    ray that a float32 ray caster (rounding ≪ ``margin``) finds hitting the triangle is True here; a
    False is a proven miss. Degenerate triangles (no area) are True.

    Args:
        origins: (N, 3) ray starts.
        directions: (N, 3) unit ray directions.
        triangles: (N, 3, 3) each ray's triangle's corners (a, b, c).
        margin: the widening (metres), > 0.

    Returns:
        (N,) bool: True where the ray may meet its triangle.
    """
    a, b, c = triangles.unbind(1)  # (N, 3) each
    normal = torch.linalg.cross(b - a, c - a)  # (N, 3)
    area2 = normal.norm(dim=-1, keepdim=True)  # (N, 1)
    longest = torch.stack([(b - a).norm(dim=-1), (c - b).norm(dim=-1), (a - c).norm(dim=-1)], -1).amax(-1)  # (N,)
    degenerate = area2.squeeze(-1) <= 1e-12 * longest * longest
    unit = normal / area2.clamp_min(torch.finfo(normal.dtype).tiny)  # (N, 3)
    # each side: outward unit s_k through a_k; the ray is inside where s_k·(o + t ω − a_k) ≤ margin
    sides = [unit, -unit]
    anchors = [a, a]
    for start, end in ((a, b), (b, c), (c, a)):
        out = torch.linalg.cross(end - start, unit)  # (N, 3) in the plane, away from the third corner
        sides.append(out / out.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(out.dtype).tiny))
        anchors.append(start)
    side = torch.stack(sides)  # (5, N, 3)
    slope = (side * directions).sum(-1)  # (5, N)
    room = margin - (side * (origins - torch.stack(anchors))).sum(-1)  # (5, N): slope · t ≤ room
    ratio = room / torch.where(slope == 0, 1.0, slope)
    low = torch.where(slope < 0, ratio, -math.inf).amax(0).clamp_min(-margin)  # (N,)
    high = torch.where(slope > 0, ratio, math.inf).amin(0)  # (N,)
    never = ((slope == 0) & (room < 0)).any(0)  # parallel to a side and outside it
    return degenerate | ((low <= high) & ~never)


def _open_rays_miss(vertices: Tensor, faces: Tensor, rays: HemisphereRays, planes: Tensor, margin: float) -> bool:
    """Whether every ray of ``rays`` (the open points' (O, S) rays) is proven to miss every triangle that has a
    corner on or above its point's plane (``planes`` (4, O), :func:`_start_planes`; the triangles below it cannot
    be met, :func:`tangent_plane_open_points`), by :func:`rays_may_meet_triangles`; False too when there are more
    than ``_MAX_RAY_TRIANGLE_PAIRS`` such (ray, triangle) pairs (the ray caster is then the cheaper test).
    ``vertices`` (M, 3) and ``faces`` (F, 3) are the mesh's (the ray caster's)."""
    samples = rays.directions.shape[1]
    budget = _MAX_RAY_TRIANGLE_PAIRS
    for start in range(0, planes.shape[1], _OPEN_POINTS_CHUNK):
        chunk = slice(start, start + _OPEN_POINTS_CHUNK)
        reach = planes[:3, chunk].T @ vertices.T >= planes[3, chunk, None]  # (C, M) vertices on or above the plane
        point, face = reach[:, faces].any(-1).nonzero().unbind(1)  # (Q,) each: the triangles a ray may reach
        budget -= point.numel() * samples
        if budget < 0:
            return False
        origins = rays.origins[chunk][point].reshape(-1, 3)  # (Q·S, 3)
        directions = rays.directions[chunk][point].reshape(-1, 3)  # (Q·S, 3)
        triangles = vertices[faces[face]].repeat_interleave(samples, dim=0)  # (Q·S, 3, 3)
        if bool(rays_may_meet_triangles(origins, directions, triangles, margin).any()):
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
    offset = shape.surface_error_rel * shape.bounding_radius
    grid_points = as_t(np.where(surface[grid][..., None], points[grid], np.nan))  # (Hm, Wm, 3)
    open_ = tangent_plane_open_points(grid_points, as_t(n_np[grid]), g.points[on], g.normals[on], offset,
                                      limit=_MAX_OPEN_POINTS)  # (O,) or None: a concavity
    if open_ is not None and open_.numel() == 0:
        # every mesh point below every lattice point's tangent plane (a convex object): no ray cast
        logger.info("interreflection: no ray of %d pixels (stride %d, %d rays each) can meet the surface: it lies "
                    "below each pixel's tangent plane", int(on.sum()), stride, samples)
        return BounceEstimate(out, stride, 0.0)
    if open_ is not None:  # a few pixels' planes cut the surface (a rim not quite convex): their rays decide
        scale = _coordinate_scale(grid_points, g.points[on])
        planes = _start_planes(g.points[on][open_], g.normals[on][open_], offset, scale)  # (4, O)
        open_rays = hemisphere_rays(scene, g, samples, seed=seed, rows=open_)  # (O, S): the lattice's in raster order
        if _open_rays_miss(torch.as_tensor(np.asarray(mesh.vertices, dtype=np.float64)),
                           torch.as_tensor(np.asarray(mesh.faces, dtype=np.int64)), open_rays, planes,
                           _FLOAT32_MARGIN * scale):
            logger.info("interreflection: no ray of %d pixels (stride %d, %d rays each) can meet the surface: it "
                        "lies below each pixel's tangent plane but for %d pixels, whose rays miss it",
                        int(on.sum()), stride, samples, open_.numel())
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
