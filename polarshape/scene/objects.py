"""A simulated scene: camera model, objects (shape + material + texture) and lights."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from polarshape.cameras import Camera
from polarshape.lights import Light
from polarshape.scene.geometry import Shape
from polarshape.scene.materials import Material
from polarshape.scene.raycast import GeometryBuffers, rasterize
from polarshape.scene.textures import AlbedoTexture


@dataclass(frozen=True)
class MaterialSplit:
    """A second material on one side of a plane: an object of two parts (a painted mug, a toy with
    a glossy and a matte half).

    Attributes:
        normal: (3,) direction of the plane's normal, camera frame (any length).
        offset: signed distance (metres) of the plane from the shape's ``center`` along ``normal``.
        material: the reflectance model of the points with (p − center)·n̂ > offset.
    """

    normal: tuple[float, float, float]
    offset: float
    material: Material

    def __post_init__(self) -> None:
        if not math.isfinite(math.hypot(*self.normal)) or math.hypot(*self.normal) <= 0:
            raise ValueError(f"split normal must be a non-zero vector, got {self.normal}")

    def side(self, points: Tensor, center: tuple[float, float, float]) -> Tensor:
        """(M,) bool: the points (M, 3) on the split material's side of the plane."""
        n = points.new_tensor(self.normal)
        n = n / n.norm()
        return ((points - points.new_tensor(center)) @ n) > self.offset


@dataclass(frozen=True)
class SceneObject:
    """One object: a shape, its material (or two, split by a plane), an optional albedo texture.

    Attributes:
        shape: the geometry.
        material: reflectance model (of the whole object, or of the side ``split`` does not cover).
        texture: per-point multiplier of the material's diffuse/body albedo; None = 1.
        in_mask: whether the object counts as "the object" in ground-truth masks (False for a
            backdrop or floor).
        split: a second material on one side of a plane; None = one material.
    """

    shape: Shape
    material: Material
    texture: AlbedoTexture | None = None
    in_mask: bool = True
    split: MaterialSplit | None = None

    @property
    def materials(self) -> tuple[Material, ...]:
        """The object's materials, in part order (index 0: ``material``, 1: the split's)."""
        return (self.material,) if self.split is None else (self.material, self.split.material)

    def part_index(self, points: Tensor) -> Tensor:
        """(M,) int64 index into :attr:`materials` of each surface point (M, 3)."""
        if self.split is None:
            return torch.zeros(points.shape[0], dtype=torch.int64, device=points.device)
        return self.split.side(points, self.shape.center).to(torch.int64)


@dataclass(frozen=True)
class Scene:
    """What a simulated camera sees: camera model, objects, lights (camera frame, metres)."""

    camera: Camera
    objects: tuple[SceneObject, ...]
    lights: tuple[Light, ...]

    def __post_init__(self) -> None:
        if len(self.objects) == 0:
            raise ValueError("a scene needs at least one object")
        if len(self.lights) == 0:
            raise ValueError("a scene needs at least one light")

    @property
    def materials(self) -> list[Material]:
        """Every object's materials (:attr:`SceneObject.materials`), in object order: the numbering
        of :meth:`material_index`."""
        return [m for o in self.objects for m in o.materials]

    @property
    def shapes(self) -> list[Shape]:
        """The objects' shapes, in object order (indices of ``GeometryBuffers.object_index``)."""
        return [o.shape for o in self.objects]

    def rasterize(self, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64) -> GeometryBuffers:
        """Per-pixel geometry of the scene (see :func:`polarshape.scene.raycast.rasterize`)."""
        return rasterize(self.shapes, self.camera, device=device, dtype=dtype)

    def material_index(self, geometry: GeometryBuffers) -> Tensor:
        """(H, W) int64: each pixel's material, numbered over the objects' :attr:`SceneObject.materials`
        in object order (object 0's parts first), −1 where nothing is hit."""
        out = torch.full_like(geometry.object_index, -1)
        first = 0
        for k, obj in enumerate(self.objects):
            sel = geometry.object_index == k  # (H, W)
            if bool(sel.any()):
                out[sel] = first + obj.part_index(geometry.points[sel])
            first += len(obj.materials)
        return out

    def object_mask(self, geometry: GeometryBuffers) -> Tensor:
        """(H, W) bool: pixels that see an object with ``in_mask``."""
        in_mask = torch.tensor([o.in_mask for o in self.objects], device=geometry.mask.device)
        return geometry.mask & in_mask[geometry.object_index.clamp_min(0)]
