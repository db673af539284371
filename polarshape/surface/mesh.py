"""Meshes from depth maps and oriented point clouds, and their atomic export (PLY, OBJ).

Camera frame (spec §1): x right, y down, z forward; pixel (u, v) = (column, row), pixel centres at
integer coordinates. A depth map gives one camera-frame point per valid pixel, the camera's
:meth:`~polarshape.cameras.OrthographicCamera.unproject` (a :mod:`polarshape.cameras` camera at the
depth map's grid):
- orthographic: P = ((u − c_x)·s, (v − c_y)·s, z), s = ``pixel_size_m``, (c_x, c_y) the principal
  point (default the grid centre ((W−1)/2, (H−1)/2));
- perspective: P = z·K⁻¹(u, v, 1)ᵀ.
Faces are wound so that their normals face the camera (n·V > 0, V from the surface to the camera),
which is the orientation of polarshape's normals.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh
from numpy.typing import NDArray

from polarshape.cameras import Camera
from polarshape.checks import to_numpy
from polarshape.io.atomic import atomic_write_bytes

logger = logging.getLogger(__name__)


def _grid_normals(points: NDArray[np.float64], valid: NDArray[np.bool_], view: NDArray[np.float64]) -> NDArray[np.float64]:
    """Camera-facing unit normals of a point grid from neighbour differences.

    Args:
        points: (H, W, 3) camera-frame points.
        valid: (H, W) pixels with a point.
        view: (H, W, 3) unit directions from each point to the camera (the fallback normal).

    Returns:
        (H, W, 3) normals ∝ P_v × P_u (central differences where both neighbours are valid, else
        one-sided), the view direction where a pixel has no neighbour along u or v.
    """
    p = np.where(valid[..., None], points, np.nan)

    def _diff(axis: int) -> NDArray[np.float64]:
        fwd = np.full_like(p, np.nan)
        bwd = np.full_like(p, np.nan)
        sl_hi = [slice(None)] * 2
        sl_lo = [slice(None)] * 2
        sl_hi[axis] = slice(1, None)
        sl_lo[axis] = slice(None, -1)
        step = p[tuple(sl_hi)] - p[tuple(sl_lo)]
        fwd[tuple(sl_lo)] = step
        bwd[tuple(sl_hi)] = step
        central = 0.5 * (fwd + bwd)
        return np.where(np.isnan(central), np.where(np.isnan(fwd), bwd, fwd), central)

    p_u, p_v = _diff(1), _diff(0)
    n = np.cross(p_v, p_u)  # faces the camera for a depth map (module docstring)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = np.isfinite(norm[..., 0]) & (norm[..., 0] > 0)
    n = np.where(ok[..., None], n / np.where(ok[..., None], norm, 1.0), view)
    flip = np.sum(n * view, axis=-1) < 0
    return np.where(flip[..., None], -n, n)


def _vertex_colors(colors: Any, valid: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """(H, W), (H, W, 3) or (H, W, 4) colours (float in [0, 1] or uint8) → (V, 4) RGBA uint8."""
    c = to_numpy(colors)
    if c.shape[:2] != valid.shape or c.ndim not in (2, 3) or (c.ndim == 3 and c.shape[2] not in (3, 4)):
        raise ValueError(f"colors must have shape (H, W), (H, W, 3) or (H, W, 4) with (H, W) = {valid.shape}; got {c.shape}")
    if c.ndim == 2:
        c = np.repeat(c[..., None], 3, axis=2)
    c = c[valid]
    if c.dtype != np.uint8:
        c = np.round(np.clip(np.nan_to_num(c.astype(np.float64), nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    if c.shape[1] == 3:
        c = np.concatenate([c, np.full((c.shape[0], 1), 255, np.uint8)], axis=1)
    return c


def depth_to_mesh(
    depth: Any,
    mask: Any | None = None,
    *,
    camera: Camera,
    normals: Any | None = None,
    colors: Any | None = None,
) -> trimesh.Trimesh:
    """Triangulate a depth map: one vertex per valid pixel, two triangles per 2×2 block of valid pixels.

    Args:
        depth: (H, W) camera-frame z (metres), NaN where unknown.
        mask: optional (H, W) bool; valid pixels = mask ∧ finite depth ∧ in front of the camera
            (depth > 0 in perspective).
        camera: a :mod:`polarshape.cameras` camera at the depth map's grid (for a capture:
            ``camera.superpixel("centre", ...)``).
        normals: optional (H, W, 3) camera-frame unit normals for the vertex normals; where absent (or
            NaN) they are computed from the point grid.
        colors: optional (H, W), (H, W, 3) or (H, W, 4) vertex colours, float in [0, 1] (e.g. an albedo
            map) or uint8.

    Returns:
        trimesh.Trimesh (not processed: vertex i is the i-th valid pixel in raster order), faces wound
        so that their normals face the camera, vertex normals set, vertex colours if given.
    """
    points = camera.unproject(depth)  # (H, W, 3)
    view = to_numpy(camera.view_directions(torch.from_numpy(points)))  # (H, W, 3) unit, surface → camera
    z = points[..., 2]
    # Seen by the camera: the way back to it points towards −z (always, orthographic; z > 0, perspective).
    valid = np.isfinite(z) & (view[..., 2] < 0)
    if mask is not None:
        m = to_numpy(mask)
        if m.shape != z.shape:
            raise ValueError(f"mask must have shape (H, W) = {z.shape} to match depth; got {m.shape}")
        valid &= m.astype(bool)
    if not valid.any():
        raise ValueError("depth has no valid pixel (finite, inside the mask): nothing to mesh")
    h, w = z.shape
    index = np.full((h, w), -1, dtype=np.int64)
    index[valid] = np.arange(int(valid.sum()))
    vertices = points[valid]  # (V, 3)

    # 2×2 blocks a b / c d: triangles (a, c, b), (b, c, d) face the camera (−z on screen, y down).
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    full = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    a, b, c, d = a[full], b[full], c[full], d[full]
    faces = np.concatenate([np.stack([a, c, b], axis=1), np.stack([b, c, d], axis=1)])  # (F, 3)

    computed = _grid_normals(points, valid, view)  # (H, W, 3)
    if normals is not None:
        n = to_numpy(normals).astype(np.float64)
        if n.shape != points.shape:
            raise ValueError(f"normals must have shape (H, W, 3) = {points.shape}; got {n.shape}")
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        usable = np.isfinite(norm[..., 0]) & (norm[..., 0] > 1e-6)
        n = np.where(usable[..., None], n / np.where(usable[..., None], norm, 1.0), computed)
    else:
        n = computed
    vertex_normals = n[valid]  # (V, 3)

    mesh = trimesh.Trimesh(
        vertices=vertices,
        faces=faces.reshape(-1, 3),
        vertex_normals=vertex_normals,
        vertex_colors=_vertex_colors(colors, valid) if colors is not None else None,
        process=False,
        validate=False,
    )
    logger.debug("depth_to_mesh: %d vertices, %d faces", vertices.shape[0], faces.shape[0])
    return mesh


def poisson_mesh(
    points: Any,
    normals: Any,
    depth: int = 8,
    *,
    watertight: bool = False,
    density_quantile: float = 0.02,
) -> trimesh.Trimesh:
    """Screened Poisson surface reconstruction (open3d) of an oriented point cloud.

    Args:
        points: (N, 3) points (any frame, e.g. camera frame, metres).
        normals: (N, 3) outward unit normals (for a depth map: camera-facing normals).
        depth: octree depth (resolution 2^depth across the bounding box).
        watertight: keep the closed Poisson surface as it is (no trimming).
        density_quantile: without ``watertight``, remove vertices whose Poisson density (number of
            supporting samples) is below this quantile: trims the surface that Poisson extrapolates
            far from the data (e.g. behind an open, one-view surface).

    Returns:
        trimesh.Trimesh with vertex normals.
    """
    import open3d as o3d

    p = to_numpy(points).astype(np.float64)
    n = to_numpy(normals).astype(np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape:
        raise ValueError(f"points and normals must both have shape (N, 3); got {p.shape} and {n.shape}")
    keep = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(n), axis=1)
    if keep.sum() < 4:
        raise ValueError(f"poisson_mesh needs at least 4 finite oriented points; got {int(keep.sum())}")
    if not 0 <= density_quantile < 1:
        raise ValueError(f"density_quantile must be in [0, 1); got {density_quantile}")
    if not 1 <= depth <= 16:
        raise ValueError(f"depth (octree depth) must be in 1..16; got {depth}")
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(p[keep])
    cloud.normals = o3d.utility.Vector3dVector(n[keep])
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=depth)
    densities = np.asarray(densities)
    if not watertight and density_quantile > 0:
        mesh.remove_vertices_by_mask(densities < np.quantile(densities, density_quantile))
    mesh.compute_vertex_normals()
    out = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices),
        faces=np.asarray(mesh.triangles),
        vertex_normals=np.asarray(mesh.vertex_normals),
        process=False,
    )
    logger.info("poisson_mesh: %d points → %d vertices, %d faces (depth %d)", int(keep.sum()), len(out.vertices), len(out.faces), depth)
    return out


def write_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike[str], overwrite: bool = False) -> Path:
    """Write a mesh atomically as binary PLY or OBJ, with vertex normals (and vertex colours if any).

    Args:
        mesh: the mesh.
        path: destination ending in .ply or .obj.
        overwrite: replace an existing file (otherwise :class:`polarshape.io.atomic.OutputExistsError`).

    Returns:
        The path written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    normals = np.asarray(mesh.vertex_normals)  # computed from faces if the mesh has none
    if suffix == ".ply":
        data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=True)
    elif suffix == ".obj":
        text = trimesh.exchange.obj.export_obj(mesh, include_normals=True, include_color=True, include_texture=False)
        data = text.encode("utf-8")
    else:
        raise ValueError(f"{path}: mesh files must end in .ply or .obj; got {path.suffix!r}")
    written = atomic_write_bytes(path, data, overwrite=overwrite)
    logger.info("wrote %s (%d vertices, %d faces, %d normals)", path, len(mesh.vertices), len(mesh.faces), len(normals))
    return written
