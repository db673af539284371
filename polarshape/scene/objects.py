"""A simulated scene: camera model, objects (shape + material + texture) and lights."""

from __future__ import annotations

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
class SceneObject:
    """One object: a shape, its material, an optional albedo texture.

    Attributes:
        shape: the geometry.
        material: reflectance model.
        texture: per-point multiplier of the material's diffuse/body albedo; None = 1.
        in_mask: whether the object counts as "the object" in ground-truth masks (False for a
            backdrop or floor).
    """

    shape: Shape
    material: Material
    texture: AlbedoTexture | None = None
    in_mask: bool = True


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
    def shapes(self) -> list[Shape]:
        """The objects' shapes, in object order (indices of ``GeometryBuffers.object_index``)."""
        return [o.shape for o in self.objects]

    def rasterize(self, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64) -> GeometryBuffers:
        """Per-pixel geometry of the scene (see :func:`polarshape.scene.raycast.rasterize`)."""
        return rasterize(self.shapes, self.camera, device=device, dtype=dtype)

    def object_mask(self, geometry: GeometryBuffers) -> Tensor:
        """(H, W) bool: pixels that see an object with ``in_mask``."""
        in_mask = torch.tensor([o.in_mask for o in self.objects], device=geometry.mask.device)
        return geometry.mask & in_mask[geometry.object_index.clamp_min(0)]
