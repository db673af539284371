"""Scene containers: validation, rasterisation and the object mask."""

from __future__ import annotations

import pytest
import torch

from polarshape.cameras import OrthographicCamera
from polarshape.lights import DirectionalLight
from polarshape.scene.geometry import PlaneShape, SphereShape
from polarshape.scene.materials import LambertianMaterial
from polarshape.scene.objects import Scene, SceneObject


def test_object_mask_leaves_out_backdrops():
    mat = LambertianMaterial()
    scene = Scene(
        OrthographicCamera(32, 32, 1e-3),
        (SceneObject(SphereShape((0, 0, 0.5), 0.008), mat), SceneObject(PlaneShape((0, 0, 0.6), (0, 0, -1)), mat, in_mask=False)),
        (DirectionalLight((0, 0, -1)),),
    )
    assert [type(s) for s in scene.shapes] == [SphereShape, PlaneShape]
    g = scene.rasterize(dtype=torch.float32)
    assert g.points.dtype == torch.float32
    mask = scene.object_mask(g)
    assert g.mask.all() and torch.equal(mask, g.object_index == 0) and 0 < int(mask.sum()) < 32 * 32


def test_empty_scenes_are_refused():
    cam = OrthographicCamera(8, 8, 1e-3)
    with pytest.raises(ValueError, match="object"):
        Scene(cam, (), (DirectionalLight((0, 0, -1)),))
    with pytest.raises(ValueError, match="light"):
        Scene(cam, (SceneObject(SphereShape((0, 0, 1), 0.1), LambertianMaterial()),), ())


def test_a_split_object_has_two_materials_either_side_of_its_plane():
    from polarshape.scene.materials import FMBRDFMaterial
    from polarshape.scene.objects import MaterialSplit

    rough, glossy = FMBRDFMaterial(alpha=0.45), FMBRDFMaterial(alpha=0.08)
    obj = SceneObject(SphereShape((0, 0, 0.5), 0.008), rough, split=MaterialSplit((2.0, 0.0, 0.0), 0.001, glossy))
    scene = Scene(OrthographicCamera(32, 32, 1e-3), (obj,), (DirectionalLight((0, 0, -1)),))
    assert scene.materials == [rough, glossy]
    g = scene.rasterize(dtype=torch.float64)
    index = scene.material_index(g)
    hit = g.object_index == 0
    assert bool((index[~hit] == -1).all())
    side = g.points[..., 0] > 0.001  # beyond the plane x = 1 mm (offset from the centre along +x)
    assert torch.equal(index[hit], side[hit].long()) and 0 < int((index == 1).sum()) < int(hit.sum())
    assert int((SceneObject(SphereShape((0, 0, 0.5), 0.008), rough).part_index(g.points[hit])).sum()) == 0
    with pytest.raises(ValueError, match="non-zero"):
        MaterialSplit((0.0, 0.0, 0.0), 0.0, glossy)
