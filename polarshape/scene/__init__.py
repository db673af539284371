"""Simulated scenes: shapes, materials, textures, ray casting, scene files.

Camera frame everywhere (OpenCV): x right, y down, z forward; metres. The camera models and lights
are shared with recovery and live in :mod:`polarshape.cameras` and :mod:`polarshape.lights`. See
:mod:`polarshape.scene.render` for shading and :class:`polarshape.acquisition.simulated.SimulatedCamera`
for the camera built on top.
"""

from polarshape.scene.config import SceneConfig, load_scene_config, parse_scene_config
from polarshape.scene.geometry import BlobShape, MeshShape, PlaneShape, Shape, SphereShape, TorusShape
from polarshape.scene.materials import BaekMaterial, FMBRDFMaterial, LambertianMaterial, Material
from polarshape.scene.objects import MaterialSplit, Scene, SceneObject
from polarshape.scene.raycast import GeometryBuffers, cast_shadow_mask, rasterize, superpixel_ground_truth
from polarshape.scene.textures import AlbedoTexture, make_texture

__all__ = [
    "AlbedoTexture",
    "BaekMaterial",
    "BlobShape",
    "FMBRDFMaterial",
    "GeometryBuffers",
    "LambertianMaterial",
    "Material",
    "MaterialSplit",
    "MeshShape",
    "PlaneShape",
    "Scene",
    "SceneConfig",
    "SceneObject",
    "Shape",
    "SphereShape",
    "TorusShape",
    "cast_shadow_mask",
    "load_scene_config",
    "make_texture",
    "parse_scene_config",
    "rasterize",
    "superpixel_ground_truth",
]
