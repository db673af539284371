"""Shapes a simulated scene is made of, with ray intersection and shadow-ray occlusion.

All coordinates are in the camera frame (OpenCV: x right, y down, z forward), in metres.
Every shape answers two questions for a batch of rays ``o + t d`` (``d`` unit):

* :meth:`Shape.intersect` — the first hit ``t > 0`` and the outward unit normal there;
* :meth:`Shape.occluded` — whether anything lies on the ray for ``t`` in ``(0, t_max)``
  (the shadow-ray test).

Sphere and plane are intersected analytically. Meshes (:class:`MeshShape`) and the procedural
non-convex shapes (:class:`BlobShape`, :class:`TorusShape`) are ray cast with open3d's embree
backend (float32); the procedural shapes then refine the hit with Newton steps on their implicit
surface in the input precision, so their hit points and normals are analytic, not faceted.
"""

from __future__ import annotations

import functools
import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from polarshape.checks import to_numpy

if TYPE_CHECKING:  # trimesh (~1 s to import, networkx with it) is imported where a mesh is made or read
    import trimesh

logger = logging.getLogger(__name__)

#: Smallest ray parameter counted as a hit, relative to the shape's bounding radius (avoids
#: re-hitting the surface a ray starts on).
_T_EPS_REL = 1e-9


def _as_vec3(values: Sequence[float], name: str) -> tuple[float, float, float]:
    if len(values) != 3:
        raise ValueError(f"{name} must have 3 components (x, y, z), got {list(values)}")
    return (float(values[0]), float(values[1]), float(values[2]))


def _unit3(values: Sequence[float], name: str) -> tuple[float, float, float]:
    x, y, z = _as_vec3(values, name)
    norm = math.sqrt(x * x + y * y + z * z)
    if not norm > 0.0:
        raise ValueError(f"{name} must be a non-zero vector, got {list(values)}")
    return (x / norm, y / norm, z / norm)


def _check_rays(origins: Tensor, directions: Tensor) -> None:
    if origins.ndim != 2 or origins.shape[-1] != 3 or origins.shape != directions.shape:
        raise ValueError(
            "rays must be given as origins and directions of shape (N, 3); got "
            f"{tuple(origins.shape)} and {tuple(directions.shape)}"
        )


def _vec(values: Sequence[float], like: Tensor) -> Tensor:
    return torch.tensor(values, dtype=like.dtype, device=like.device)


class Shape(ABC):
    """A closed or open surface in the camera frame.

    Attributes:
        center: (3,) a reference point (metres) used for spherical texture mapping.
        bounding_radius: radius (metres) of a sphere about ``center`` that holds the shape; sets
            the scale of numerical tolerances such as the shadow-ray offset.
    """

    center: tuple[float, float, float]
    bounding_radius: float
    #: How far (relative to ``bounding_radius``) a computed hit point may lie off the surface that
    #: shadow rays test against; shadow rays start this far out along the normal. Analytic shapes
    #: are exact to rounding; tessellated ones differ from their facets by the chord sagitta.
    surface_error_rel: float = 1e-6
    #: True when the surface has two usable sides (a plane): the normal is then turned toward
    #: the viewer. Closed shapes keep their outward normal.
    two_sided: bool = False

    @abstractmethod
    def intersect(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """First intersection of each ray with the shape.

        Args:
            origins: (N, 3) ray origins, metres, camera frame.
            directions: (N, 3) unit ray directions.

        Returns:
            ``(t, normals)``: (N,) distance along the ray (``inf`` where the ray misses) and
            (N, 3) unit outward normals at the hit (zero where missed), same dtype/device as input.
        """

    @abstractmethod
    def occluded(self, origins: Tensor, directions: Tensor, t_max: Tensor) -> Tensor:
        """Whether the shape blocks each ray for ``0 < t < t_max``.

        Args:
            origins: (N, 3) ray origins (already offset from the surface they start on).
            directions: (N, 3) unit directions.
            t_max: (N,) upper bound on ``t`` (``inf`` for directional lights).

        Returns:
            (N,) bool.
        """


class SphereShape(Shape):
    """A sphere, intersected analytically.

    Args:
        center: (x, y, z) centre, metres, camera frame.
        radius: radius, metres (> 0).
    """

    def __init__(self, center: Sequence[float], radius: float) -> None:
        if not radius > 0:
            raise ValueError(f"sphere radius must be > 0 metres, got {radius}")
        self.center = _as_vec3(center, "sphere center")
        self.radius = float(radius)
        self.bounding_radius = self.radius

    def _roots(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        oc = origins - _vec(self.center, origins)  # (N, 3)
        b = (oc * directions).sum(-1)  # (N,)
        c = (oc * oc).sum(-1) - self.radius**2  # (N,)
        disc = b * b - c
        sq = torch.sqrt(disc.clamp_min(0.0))
        inf = torch.full_like(b, math.inf)
        t0 = torch.where(disc >= 0, -b - sq, inf)
        t1 = torch.where(disc >= 0, -b + sq, inf)
        return t0, t1

    def intersect(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        _check_rays(origins, directions)
        t0, t1 = self._roots(origins, directions)
        eps = _T_EPS_REL * self.radius
        t = torch.where(t0 > eps, t0, torch.where(t1 > eps, t1, torch.full_like(t0, math.inf)))
        hit = torch.isfinite(t)
        points = origins + torch.where(hit, t, 0.0)[:, None] * directions
        normals = torch.nn.functional.normalize(points - _vec(self.center, origins), dim=-1)
        return t, torch.where(hit[:, None], normals, 0.0)

    def occluded(self, origins: Tensor, directions: Tensor, t_max: Tensor) -> Tensor:
        t, _ = self.intersect(origins, directions)
        return t < t_max


class PlaneShape(Shape):
    """A plane, infinite or a finite rectangle, intersected analytically; two-sided.

    Args:
        point: (x, y, z) a point on the plane (the rectangle's centre), metres.
        normal: (x, y, z) plane normal (normalised here).
        size: optional (width, height) of a rectangle centred on ``point``, metres, along the
            in-plane axes ``e1 = normalise(x̂ − (x̂·n) n)`` and ``e2 = n × e1``; None = infinite.
    """

    two_sided = True

    def __init__(
        self,
        point: Sequence[float],
        normal: Sequence[float],
        size: Sequence[float] | None = None,
    ) -> None:
        self.center = _as_vec3(point, "plane point")
        self.normal = _unit3(normal, "plane normal")
        self.axes = plane_axes(self.normal)
        if size is not None:
            if len(size) != 2 or not (size[0] > 0 and size[1] > 0):
                raise ValueError(f"plane size must be [width, height] > 0 metres, got {list(size)}")
            self.size: tuple[float, float] | None = (float(size[0]), float(size[1]))
            self.bounding_radius = 0.5 * math.hypot(*self.size)
        else:
            self.size = None
            # an infinite plane has no size; its distance from the camera sets the tolerances
            self.bounding_radius = max(1e-6, math.sqrt(sum(c * c for c in self.center)))

    def intersect(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        _check_rays(origins, directions)
        n = _vec(self.normal, origins)  # (3,)
        p0 = _vec(self.center, origins)  # (3,)
        denom = directions @ n  # (N,)
        safe = torch.where(denom.abs() > 1e-12, denom, torch.ones_like(denom))
        t = ((p0 - origins) @ n) / safe
        valid = (denom.abs() > 1e-12) & (t > _T_EPS_REL * self.bounding_radius)
        if self.size is not None:
            local = origins + torch.where(valid, t, 0.0)[:, None] * directions - p0  # (N, 3)
            e1, e2 = (_vec(a, origins) for a in self.axes)
            valid &= (local @ e1).abs() <= 0.5 * self.size[0]
            valid &= (local @ e2).abs() <= 0.5 * self.size[1]
        t = torch.where(valid, t, torch.full_like(t, math.inf))
        normals = torch.where(valid[:, None], n.expand_as(origins), 0.0)
        return t, normals

    def occluded(self, origins: Tensor, directions: Tensor, t_max: Tensor) -> Tensor:
        t, _ = self.intersect(origins, directions)
        return t < t_max


def plane_axes(normal: Sequence[float]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """In-plane unit axes (e1, e2) of a plane with unit ``normal``: e1 = normalise(x̂ − (x̂·n)n)
    (ŷ instead when n ∥ x̂), e2 = n × e1."""
    n = np.asarray(normal, dtype=np.float64)
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - ref.dot(n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return tuple(float(v) for v in e1), tuple(float(v) for v in e2)


class _Open3DRaycaster:
    """Triangle-mesh ray casting with open3d (embree, float32, CPU)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        import open3d as o3d  # heavy import; only needed for mesh shapes

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
        )

    def cast(self, origins: Tensor, directions: Tensor) -> dict[str, np.ndarray]:
        """Cast (N, 3) rays; returns numpy ``t_hit`` (N,), ``primitive_ids`` (N,),
        ``primitive_uvs`` (N, 2) barycentrics (hit = (1−u−v) v0 + u v1 + v v2) and
        ``primitive_normals`` (N, 3)."""
        rays = to_numpy(torch.cat([origins, directions], dim=-1), np.float32)
        out = self.scene.cast_rays(self._o3d.core.Tensor(np.ascontiguousarray(rays)))
        return {key: out[key].numpy() for key in ("t_hit", "primitive_ids", "primitive_uvs", "primitive_normals")}


def _orthonormal_from_euler_deg(rotation_deg: Sequence[float]) -> np.ndarray:
    """(3, 3) rotation R = Rz · Ry · Rx from angles (x, y, z) in degrees (fixed camera axes: about x
    first, then y, then z)."""
    rx, ry, rz = (math.radians(float(a)) for a in _as_vec3(rotation_deg, "rotation_deg"))
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_y @ r_x


class MeshShape(Shape):
    """A triangle mesh (anything trimesh loads), ray cast with open3d.

    Args:
        mesh: the mesh, vertices in metres in the camera frame.
        smooth: interpolate vertex normals with the hit's barycentric coordinates (True) or use
            the flat face normals (False).

    The hit distance comes from open3d in float32 (≈1e-7 relative); normals are computed from
    trimesh's float64 vertex or face normals.
    """

    surface_error_rel = 1e-3

    def __init__(self, mesh: trimesh.Trimesh, *, smooth: bool = True) -> None:
        if len(mesh.faces) == 0:
            raise ValueError("mesh has no faces; give a triangle mesh (e.g. .ply/.obj/.stl)")
        self.mesh = mesh
        self.smooth = smooth
        lo, hi = mesh.bounds
        self.center = tuple(float(v) for v in 0.5 * (lo + hi))
        self.bounding_radius = float(np.linalg.norm(mesh.vertices - np.asarray(self.center), axis=1).max())
        self._faces = np.asarray(mesh.faces, dtype=np.int64)
        self._face_normals = np.asarray(mesh.face_normals, dtype=np.float64)
        self._vertex_normals = np.asarray(mesh.vertex_normals, dtype=np.float64)

    @classmethod
    def from_file(
        cls,
        path: str,
        *,
        scale: float = 1.0,
        rotation_deg: Sequence[float] = (0.0, 0.0, 0.0),
        translation: Sequence[float] = (0.0, 0.0, 0.0),
        smooth: bool = True,
    ) -> MeshShape:
        """Load a mesh file and place it: ``x_camera = R (scale · x_file) + translation`` with
        ``R = Rz Ry Rx`` from ``rotation_deg``. Raises ValueError naming the file on failure."""
        import trimesh
        try:
            mesh = trimesh.load(path, force="mesh")
        except Exception as exc:  # trimesh raises a variety of exceptions for unreadable files
            raise ValueError(f"cannot load mesh file {path}: {exc}; give a file trimesh reads (.ply, .obj, .stl, .glb)") from exc
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise ValueError(f"mesh file {path} holds no triangles; give a triangle mesh")
        transform = np.eye(4)
        transform[:3, :3] = _orthonormal_from_euler_deg(rotation_deg) * float(scale)
        transform[:3, 3] = _as_vec3(translation, "translation")
        mesh.apply_transform(transform)
        return cls(mesh, smooth=smooth)

    @functools.cached_property
    def _caster(self) -> _Open3DRaycaster:
        # built at the first ray cast, not here: a shape whose rays are never cast (the convex test of
        # polarshape.surface.interreflection) pays neither the scene nor open3d's import
        return _Open3DRaycaster(self.mesh.vertices, self.mesh.faces)

    def _normals_at(self, prim: np.ndarray, uvs: np.ndarray) -> np.ndarray:
        if not self.smooth:
            return self._face_normals[prim]
        tri = self._faces[prim]  # (M, 3)
        w = np.stack([1.0 - uvs[:, 0] - uvs[:, 1], uvs[:, 0], uvs[:, 1]], axis=-1)  # (M, 3)
        n = (self._vertex_normals[tri] * w[..., None]).sum(axis=1)  # (M, 3)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        # keep the interpolated normal on the side of the face normal (meshes with mixed winding)
        flip = (n * self._face_normals[prim]).sum(-1) < 0
        n[flip] *= -1.0
        return n

    def intersect(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        _check_rays(origins, directions)
        out = self._caster.cast(origins, directions)
        hit = np.isfinite(out["t_hit"])
        normals = np.zeros((len(hit), 3))
        normals[hit] = self._normals_at(out["primitive_ids"][hit].astype(np.int64), out["primitive_uvs"][hit].astype(np.float64))
        # a ray that meets a face from behind sees its other side
        face_n = np.zeros_like(normals)
        face_n[hit] = self._face_normals[out["primitive_ids"][hit].astype(np.int64)]
        back = (face_n * to_numpy(directions)).sum(-1) > 0
        normals[back] *= -1.0
        t = torch.as_tensor(out["t_hit"], dtype=origins.dtype, device=origins.device)
        return t, torch.as_tensor(normals, dtype=origins.dtype, device=origins.device)

    def occluded(self, origins: Tensor, directions: Tensor, t_max: Tensor) -> Tensor:
        out = self._caster.cast(origins, directions)
        t = torch.as_tensor(out["t_hit"], dtype=origins.dtype, device=origins.device)
        return t < t_max


class _ImplicitMeshShape(Shape):
    """A surface F(p) = 0 (F < 0 inside) with a tessellation for ray casting.

    open3d finds the hit on the tessellation; Newton steps on F along the ray then move it onto
    the implicit surface, and the normal is ∇F/‖∇F‖ there. Where Newton does not converge (rays
    grazing the silhouette) the tessellation hit is kept, with the normal ∇F/‖∇F‖ at it.
    """

    newton_steps: int = 8
    surface_error_rel = 1e-3

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        self.mesh = mesh
        self._caster = _Open3DRaycaster(mesh.vertices, mesh.faces)

    @abstractmethod
    def implicit(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """F and ∇F at (N, 3) points: returns (N,) and (N, 3)."""

    def intersect(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        _check_rays(origins, directions)
        out = self._caster.cast(origins, directions)
        t_mesh = torch.as_tensor(out["t_hit"], dtype=origins.dtype, device=origins.device)  # (N,)
        hit = torch.isfinite(t_mesh)
        o, d, t0 = origins[hit], directions[hit], t_mesh[hit]
        t = t0.clone()
        for _ in range(self.newton_steps):
            f, grad = self.implicit(o + t[:, None] * d)
            slope = (grad * d).sum(-1)
            step = torch.where(slope.abs() > 1e-12, f / torch.where(slope == 0, 1.0, slope), 0.0)
            t = t - step
        f, _ = self.implicit(o + t[:, None] * d)
        tol = 1e-6 * self.bounding_radius
        ok = (f.abs() < tol) & ((t - t0).abs() < 0.02 * self.bounding_radius) & (t > 0)
        if (~ok).any():
            logger.debug("%d of %d hits kept on the tessellation (Newton did not converge)", int((~ok).sum()), len(ok))
        t = torch.where(ok, t, t0)
        _, grad = self.implicit(o + t[:, None] * d)
        t_all = t_mesh.clone()
        t_all[hit] = t
        normals = torch.zeros_like(origins)
        normals[hit] = torch.nn.functional.normalize(grad, dim=-1)
        return t_all, normals

    def occluded(self, origins: Tensor, directions: Tensor, t_max: Tensor) -> Tensor:
        out = self._caster.cast(origins, directions)
        t = torch.as_tensor(out["t_hit"], dtype=origins.dtype, device=origins.device)
        return t < t_max


class BlobShape(_ImplicitMeshShape):
    """A bumpy blob: a sphere with a smooth radial displacement, non-convex (saddles and dents
    between the bumps, so it casts shadows on itself under grazing light).

    Radius along the unit direction ω from the centre (a sum of Gaussian bumps on the sphere):
    ``r(ω) = R · (1 + Σ_j a_j · exp((ω·d_j − 1) / w²))``.

    Args:
        center: (x, y, z) centre, metres.
        radius: base radius R, metres.
        bumps: number of bumps; directions d_j uniform on the sphere, heights a_j of random sign
            (negative = dent) and magnitude uniform in ``[amplitude/2, amplitude]``, from ``seed``.
        amplitude: largest relative height |a_j| (0 ≤ amplitude < 0.5).
        width: angular width w of a bump, radians.
        seed: seed of the bump layout.
        subdivisions: icosphere subdivisions of the tessellation used for ray casting
            (6: 81 920 triangles).
    """

    def __init__(
        self,
        center: Sequence[float],
        radius: float,
        *,
        bumps: int = 24,
        amplitude: float = 0.25,
        width: float = 0.3,
        seed: int = 2,
        subdivisions: int = 6,
    ) -> None:
        import trimesh
        if not radius > 0:
            raise ValueError(f"blob radius must be > 0 metres, got {radius}")
        if not 0 <= amplitude < 0.5:
            raise ValueError(f"blob amplitude must be in [0, 0.5) (relative to the radius), got {amplitude}")
        if not width > 0:
            raise ValueError(f"blob width must be > 0 radians, got {width}")
        if bumps < 0:
            raise ValueError(f"blob bumps must be >= 0, got {bumps}")
        self.center = _as_vec3(center, "blob center")
        self.radius = float(radius)
        self.width = float(width)
        rng = np.random.default_rng(seed)
        dirs = rng.normal(size=(bumps, 3))
        self.bump_directions = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)  # (B, 3)
        signs = np.where(rng.random(bumps) < 0.5, -1.0, 1.0)
        self.bump_heights = amplitude * signs * rng.uniform(0.5, 1.0, size=bumps)  # (B,)
        sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
        omega = np.asarray(sphere.vertices, dtype=np.float64)
        omega /= np.linalg.norm(omega, axis=1, keepdims=True)
        r = self._radius_np(omega)
        if r.min() < 0.2 * self.radius:
            raise ValueError(
                f"blob dents overlap so deeply that the radius drops to {r.min() / self.radius:.2f} R; "
                "lower amplitude or bumps, or change seed"
            )
        self.bounding_radius = float(r.max()) * 1.01  # margin for the surface between vertices
        vertices = omega * r[:, None] + np.asarray(self.center)
        super().__init__(trimesh.Trimesh(vertices=vertices, faces=sphere.faces, process=False))

    def _radius_np(self, omega: np.ndarray) -> np.ndarray:
        g = np.exp((omega @ self.bump_directions.T - 1.0) / self.width**2)  # (N, B)
        return self.radius * (1.0 + g @ self.bump_heights)

    def implicit(self, points: Tensor) -> tuple[Tensor, Tensor]:
        q = points - _vec(self.center, points)  # (N, 3)
        rho = q.norm(dim=-1).clamp_min(1e-12 * self.radius)  # (N,)
        omega = q / rho[:, None]
        dirs = torch.as_tensor(self.bump_directions, dtype=points.dtype, device=points.device)  # (B, 3)
        heights = torch.as_tensor(self.bump_heights, dtype=points.dtype, device=points.device)  # (B,)
        g = torch.exp((omega @ dirs.T - 1.0) / self.width**2)  # (N, B)
        r = self.radius * (1.0 + g @ heights)  # (N,)
        # ∇_ω r (ambient), then its component tangent to the sphere of directions
        grad_r = self.radius * ((g * heights) @ dirs) / self.width**2  # (N, 3)
        tangential = grad_r - (grad_r * omega).sum(-1, keepdim=True) * omega
        return rho - r, omega - tangential / rho[:, None]


class TorusShape(_ImplicitMeshShape):
    """A torus (non-convex: the inner ring shadows itself under grazing light).

    Args:
        center: (x, y, z) centre, metres.
        major_radius: distance from the centre to the tube's centre line, metres.
        minor_radius: tube radius, metres (< major_radius).
        axis: (x, y, z) symmetry axis (normalised here).
        sections: tessellation resolution (major sections; minor gets half).
    """

    def __init__(
        self,
        center: Sequence[float],
        major_radius: float,
        minor_radius: float,
        *,
        axis: Sequence[float] = (0.0, 0.0, 1.0),
        sections: int = 256,
    ) -> None:
        if not 0 < minor_radius < major_radius:
            raise ValueError(
                f"torus needs 0 < minor_radius < major_radius, got minor {minor_radius}, major {major_radius}"
            )
        self.center = _as_vec3(center, "torus center")
        self.axis = _unit3(axis, "torus axis")
        self.major_radius = float(major_radius)
        self.minor_radius = float(minor_radius)
        self.bounding_radius = self.major_radius + self.minor_radius
        mesh = _torus_mesh(self.major_radius, self.minor_radius, sections, max(sections // 2, 8))
        z = np.asarray(self.axis)
        e1, e2 = plane_axes(self.axis)
        transform = np.eye(4)
        transform[:3, :3] = np.stack([e1, e2, z], axis=1)  # maps local z to the axis
        transform[:3, 3] = self.center
        mesh.apply_transform(transform)
        super().__init__(mesh)

    def implicit(self, points: Tensor) -> tuple[Tensor, Tensor]:
        # signed distance: F = sqrt((ρ − R)² + h²) − r
        q = points - _vec(self.center, points)  # (N, 3)
        a = _vec(self.axis, points)
        h = q @ a  # (N,)
        radial = q - h[:, None] * a  # (N, 3)
        rho = radial.norm(dim=-1).clamp_min(1e-12 * self.major_radius)
        tube = torch.stack([rho - self.major_radius, h], dim=-1)  # (N, 2)
        dist = tube.norm(dim=-1).clamp_min(1e-12 * self.minor_radius)
        grad = ((rho - self.major_radius) / dist)[:, None] * radial / rho[:, None] + (h / dist)[:, None] * a
        return dist - self.minor_radius, grad


def _torus_mesh(major_radius: float, minor_radius: float, major_sections: int, minor_sections: int) -> trimesh.Trimesh:
    """A closed, outward-wound torus about the z axis (a periodic grid: no seam)."""
    import trimesh
    u = np.arange(major_sections) * (2 * np.pi / major_sections)  # around the axis
    v = np.arange(minor_sections) * (2 * np.pi / minor_sections)  # around the tube
    uu, vv = np.meshgrid(u, v, indexing="ij")  # (U, V)
    ring = major_radius + minor_radius * np.cos(vv)
    vertices = np.stack([ring * np.cos(uu), ring * np.sin(uu), minor_radius * np.sin(vv)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(major_sections), np.arange(minor_sections), indexing="ij")
    a = i * minor_sections + j
    b = ((i + 1) % major_sections) * minor_sections + j
    c = ((i + 1) % major_sections) * minor_sections + (j + 1) % minor_sections
    d = i * minor_sections + (j + 1) % minor_sections
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def crater_mesh(center: Sequence[float], radius: float, depth: float, half_width: float, resolution: int) -> trimesh.Trimesh:
    """A square plate facing the camera with a round dish pressed into it (a concave test object).

    The plate is the plane ``z = center_z`` over ``|x − cx|, |y − cy| ≤ half_width``; within
    ``ρ < radius`` of the centre the surface sinks away from the camera to
    ``z = center_z + depth · (1 − (ρ / radius)²)²``, whose slope is zero at the rim and at the bottom
    (a smooth surface, C¹). Vertices on a ``resolution × resolution`` grid, metres, camera frame.
    """
    import trimesh
    cx, cy, cz = _as_vec3(center, "center")
    if not (radius > 0 and depth > 0 and half_width > radius):
        raise ValueError(f"crater needs radius > 0, depth > 0 and half_width > radius; got {radius}, {depth}, {half_width}")
    if resolution < 8:
        raise ValueError(f"crater resolution must be ≥ 8 vertices per side; got {resolution}")
    u = np.linspace(-half_width, half_width, resolution)
    x, y = np.meshgrid(u, u, indexing="xy")  # (R, R)
    rho = np.hypot(x, y)
    z = cz + depth * np.clip(1.0 - (rho / radius) ** 2, 0.0, None) ** 2
    vertices = np.stack([x + cx, y + cy, z], axis=-1).reshape(-1, 3)
    i = np.arange(resolution - 1)
    a = (i[:, None] * resolution + i[None, :]).reshape(-1)  # top-left corner of each grid cell
    b, c, d = a + 1, a + resolution, a + resolution + 1
    # wound so that the face normals point toward the camera (−z)
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)])
    return trimesh.Trimesh(vertices, faces, process=False)


def crater_depth_map(size: int, pixel: float, *, radius: float, depth: float, half_width: float,
                     distance: float) -> tuple[np.ndarray, np.ndarray]:
    """The surface of :func:`crater_mesh` (centred on the optical axis at z = ``distance``) seen by a
    ``size`` × ``size`` orthographic camera of pixel pitch ``pixel`` (metres), as a depth map and its
    analytic normals: ∇z = −4 · depth · q · (x, y) / radius² with q = 1 − (ρ / radius)², N ∝ (∂z/∂x, ∂z/∂y, −1).

    Returns:
        depth (size, size), camera-frame z, NaN off the plate; normals (size, size, 3), unit, facing the
        camera (n_z < 0), NaN off the plate.
    """
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = (xx - (size - 1) / 2) * pixel, (yy - (size - 1) / 2) * pixel
    q = np.clip(1.0 - (np.hypot(x, y) / radius) ** 2, 0.0, None)
    slope = -4.0 * depth * q / radius**2  # (dz/dρ) / ρ
    normals = np.stack([slope * x, slope * y, -np.ones_like(x)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    plate = (np.abs(x) < half_width) & (np.abs(y) < half_width)
    return np.where(plate, distance + depth * q**2, np.nan), np.where(plate[..., None], normals, np.nan)


class CraterShape(MeshShape):
    """:func:`crater_mesh` as a shape: an open surface seen from its front (two-sided)."""

    two_sided = True

    def __init__(self, center: Sequence[float], radius: float, depth: float, *, half_width: float,
                 resolution: int = 257) -> None:
        super().__init__(crater_mesh(center, radius, depth, half_width, resolution), smooth=True)
