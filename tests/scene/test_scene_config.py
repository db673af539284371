"""Scene files: the shipped examples load, bad fields are named, relative paths resolve."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import trimesh

from polarshape.cameras import OrthographicCamera, PerspectiveCamera
from polarshape.io.capture import LightSpec
from polarshape.lights import DirectionalLight, PointLight
from polarshape.scene.config import load_scene_config, parse_scene_config
from polarshape.scene.geometry import BlobShape, MeshShape, PlaneShape, SphereShape, TorusShape
from polarshape.scene.materials import BaekMaterial, FMBRDFMaterial, LambertianMaterial

SCENES = Path(__file__).resolve().parents[2] / "configs" / "scenes"

UNIT_SPHERE = {"type": "sphere", "center": [0, 0, 1], "radius": 1}
BASE = {
    "camera": {"projection": "orthographic", "width": 16, "height": 16, "pixel_size_m": 1e-3},
    "objects": [{"shape": {"type": "sphere", "center": [0, 0, 1], "radius": 0.004}}],
    "lights": [{"direction": [0, 0, -1]}],
}


def _with(**changes):
    data = {k: v for k, v in BASE.items()}
    data.update(changes)
    return data


@pytest.mark.parametrize("name", ["sphere", "blob", "textured"])
def test_shipped_scenes_load_and_build(name):
    config = load_scene_config(SCENES / f"{name}.yaml")
    assert config.camera.width % 2 == 0 and len(config.lights) >= 4
    if name == "blob":
        # building the blob tessellation is the costly part; check the description only
        assert config.objects[0].shape.type == "blob" and config.camera.projection == "perspective"
        return
    scene = config.build_scene()
    assert len(scene.objects) == len(config.objects)
    if name == "textured":
        assert all(o.texture is not None for o in scene.objects)
        assert all(isinstance(light, PointLight) for light in scene.lights)
        assert scene.objects[1].in_mask is False


def test_defaults_build_the_expected_objects():
    scene = parse_scene_config(BASE).build_scene()
    assert isinstance(scene.camera, OrthographicCamera)
    assert isinstance(scene.objects[0].shape, SphereShape)
    assert isinstance(scene.objects[0].material, FMBRDFMaterial)
    assert scene.lights == (DirectionalLight((0.0, 0.0, -1.0), 1.0),)


def test_angles_give_directions_in_the_camera_frame():
    config = parse_scene_config(_with(lights=[{"zenith_deg": 30, "azimuth_deg": 90, "intensity": 2.0}]))
    light = config.lights[0].to_light()
    assert light.direction == pytest.approx((0.0, 0.5, -math.sqrt(3) / 2))  # +y = image down
    assert light.intensity == 2.0


def test_lights_are_capture_light_entries_of_any_length():
    config = parse_scene_config(_with(lights=[{"direction": [0, 0, -2], "intensity": 0.5}, {"position": [0, 0.1, 0]}]))
    assert all(isinstance(light, LightSpec) for light in config.lights)
    assert [light.to_light() for light in config.lights] == [DirectionalLight((0.0, 0.0, -1.0), 0.5),
                                                             PointLight((0.0, 0.1, 0.0), 1.0)]


def test_every_shape_and_material_kind(tmp_path):
    trimesh.creation.box(extents=(0.01, 0.01, 0.01)).export(tmp_path / "box.stl")
    objects = [
        {
            "shape": {"type": "plane", "point": [0, 0, 2], "normal": [0, 0, -1], "size": [1, 1]},
            "material": {"model": "lambertian"},
        },
        {"shape": {"type": "torus", "center": [0, 0, 1], "major_radius": 0.01, "minor_radius": 0.003, "sections": 32}},
        {
            "shape": {"type": "mesh", "path": "box.stl", "translation": [0, 0, 0.5]},
            "material": {"model": "baek", "distribution": "beckmann"},
        },
        {"shape": {"type": "blob", "center": [0, 0, 1], "radius": 0.01, "subdivisions": 2}},
    ]
    config = parse_scene_config(_with(objects=objects), base_dir=tmp_path)  # the mesh path is relative
    scene = config.build_scene()
    kinds = [type(o.shape) for o in scene.objects]
    assert kinds == [PlaneShape, TorusShape, MeshShape, BlobShape]
    assert isinstance(scene.objects[0].material, LambertianMaterial)
    baek = scene.objects[2].material
    assert isinstance(baek, BaekMaterial) and baek.distribution == "beckmann"
    intrinsics = {"fx": 100, "fy": 100, "cx": 7.5, "cy": 7.5}
    camera = {"projection": "perspective", "intrinsics": intrinsics, "width": 16, "height": 16}
    perspective = parse_scene_config(_with(camera=camera))
    assert isinstance(perspective.build_scene().camera, PerspectiveCamera)


@pytest.mark.parametrize(
    "change,fragment",
    [
        (dict(camera={"projection": "orthographic"}), "pixel_size_m"),
        (dict(camera={"projection": "perspective"}), "intrinsics"),
        (dict(camera={"projection": "orthographic", "pixel_size_m": 1e-3, "width": 15}), "even"),
        (dict(camera={"projection": "orthographic", "pixel_size_m": 1e-3, "pixel_format": "Mono8"}), "pixel_format"),
        (dict(camera={"projection": "orthographic", "pixel_size_m": 1e-3, "pixel_format": "BayerRG12"}),
         "colour sensor's raw format .* set mosaic.bayer: RGGB"),
        (dict(objects=[{"shape": {"type": "cube", "size": 1}}]), "objects.0.shape"),
        (dict(objects=[{"shape": {"type": "sphere", "center": [0, 0, 1], "radius": -1}}]), "radius"),
        (dict(objects=[{"shape": {**UNIT_SPHERE, "colour": 3}}]), "colour"),
        (dict(objects=[{"shape": UNIT_SPHERE, "material": {"model": "fmbrdf", "alpha": -0.1}}]), "alpha"),
        (dict(objects=[{"shape": UNIT_SPHERE, "texture": {"kind": "image"}}]), "path"),
        (dict(lights=[{"direction": [0, 0, 1]}]), "z < 0"),
        (dict(lights=[{"direction": [0, 0, -1], "position": [0, 0, 0]}]), "exactly one"),
        (dict(lights=[{"zenith_deg": 10}]), "azimuth_deg"),
        (dict(lights=[]), "lights"),
    ],
)
def test_invalid_fields_are_named(change, fragment):
    with pytest.raises(ValueError, match=fragment):
        parse_scene_config(_with(**change))


def test_missing_files_are_named(tmp_path):
    with pytest.raises(ValueError, match="nothing.yaml"):
        load_scene_config(tmp_path / "nothing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera: [unclosed\n")
    with pytest.raises(ValueError, match="bad.yaml"):
        load_scene_config(bad)
    config = parse_scene_config(_with(objects=[{"shape": {"type": "mesh", "path": "gone.ply"}}]), base_dir=tmp_path)
    with pytest.raises(ValueError, match="gone.ply"):
        config.build_scene()


def test_a_point_light_behind_the_object_is_refused():
    """z is forward, away from the camera: a point light at or beyond the nearest object's centre
    lights the side the camera does not see."""
    with pytest.raises(ValueError, match=r"lights\[1\]\.position z = 1\.2 m is at or beyond the centre of the nearest "
                                         r"object \(objects\[0\], z = 1 m\): behind the object seen from the camera: "
                                         r"z is forward, away from the camera"):
        parse_scene_config(_with(lights=[{"position": [0, 0, 0.5]}, {"position": [0.1, 0, 1.2]}]))
    parse_scene_config(_with(lights=[{"position": [0, 0, 0.5]}, {"position": [0.1, 0, -0.2]}]))  # camera side


def test_a_backdrop_behind_the_object_does_not_excuse_a_light_behind_it():
    backdrop = {"shape": {"type": "plane", "point": [0, 0, 2], "normal": [0, 0, -1]}, "in_mask": False}
    objects = [*BASE["objects"], backdrop]
    with pytest.raises(ValueError, match=r"lights\[0\]\.position .*objects\[0\], z = 1 m"):
        parse_scene_config(_with(objects=objects, lights=[{"position": [0, 0, 1.5]}]))


def test_the_colour_scene_records_in_a_colour_raw_format():
    config = load_scene_config(SCENES / "colour.yaml")
    assert config.camera.mosaic.bayer == "RGGB" and config.camera.pixel_format.startswith("BayerRG")


def test_a_split_gives_an_object_a_second_material():
    split = {"normal": [1, 0, 0], "offset": 0.0, "material": {"model": "fmbrdf", "alpha": 0.08, "ior": 1.6}}
    config = parse_scene_config(_with(objects=[{**BASE["objects"][0], "material": {"model": "fmbrdf", "alpha": 0.45},
                                                "split": split}]))
    obj = config.build_scene().objects[0]
    assert [m.alpha for m in obj.materials] == [0.45, 0.08]
    with pytest.raises(ValueError, match="split.normal"):
        parse_scene_config(_with(objects=[{**BASE["objects"][0], "split": {**split, "normal": [0, 0, 0]}}]))
    two = load_scene_config(SCENES / "two_materials_blob.yaml")
    assert two.objects[0].split is not None and two.objects[0].split.material.alpha == 0.08
