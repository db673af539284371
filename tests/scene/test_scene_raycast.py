"""Ray casting: per-pixel geometry against analytic answers, cast shadows, super-pixel truth."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.cameras import OrthographicCamera, PerspectiveCamera
from polarshape.lights import DirectionalLight, PointLight
from polarshape.scene.geometry import BlobShape, PlaneShape, SphereShape, TorusShape
from polarshape.scene.raycast import cast_shadow_mask, rasterize, superpixel_ground_truth

F64 = torch.float64
CENTER = (0.001, -0.0005, 0.3)
RADIUS = 0.01


def _analytic_sphere(origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Geometric (not algebraic) ray-sphere solution: closest approach, then back off."""
    c = torch.tensor(CENTER, dtype=F64)
    t_ca = ((c - origins) * directions).sum(-1)
    closest = origins + t_ca[..., None] * directions
    d2 = ((closest - c) ** 2).sum(-1)
    hit = d2 <= RADIUS**2
    t = t_ca - torch.sqrt((RADIUS**2 - d2).clamp_min(0))
    p = origins + t[..., None] * directions
    return hit, (p - c) / RADIUS


CAMERAS = {
    "orthographic": OrthographicCamera(96, 80, 2.5e-4),
    "perspective": PerspectiveCamera(96, 80, fx=600.0, fy=640.0, cx=50.3, cy=37.8),
}


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_sphere_normals_depth_and_mask_match_analytic(name):
    cam = CAMERAS[name]
    g = rasterize([SphereShape(CENTER, RADIUS)], cam)
    o, d = cam.rays()
    hit, normals = _analytic_sphere(o, d)
    # pixels within 1e-9 of the silhouette could go either way
    assert torch.equal(g.mask, hit)
    assert 1000 < int(hit.sum()) < 96 * 80
    err = (g.normals[hit] - normals[hit]).norm(dim=-1)
    assert err.max() < 1e-5
    assert torch.all((g.normals[hit] * g.view[hit]).sum(-1) > 0)  # visible side faces the camera
    assert torch.allclose(g.depth[hit], g.points[hit][:, 2])
    assert torch.isnan(g.depth[~hit]).all() and torch.all(g.object_index[~hit] == -1)
    if name == "perspective":
        assert torch.allclose(g.view[hit], torch.nn.functional.normalize(-g.points[hit], dim=-1))
    else:
        assert torch.all(g.view == torch.tensor([0.0, 0.0, -1.0], dtype=F64))


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_superpixel_normals_are_normalised_block_means(name):
    cam = CAMERAS[name]
    g = rasterize([SphereShape(CENTER, RADIUS)], cam)
    normals, depth, mask = superpixel_ground_truth(g)
    assert normals.shape == (40, 48, 3) and depth.shape == mask.shape == (40, 48)
    o, d = cam.rays()
    hit, analytic = _analytic_sphere(o, d)
    block_hit = hit.reshape(40, 2, 48, 2).all(3).all(1)
    assert torch.equal(mask, block_hit)
    expect = torch.nn.functional.normalize(analytic.reshape(40, 2, 48, 2, 3).sum((1, 3)), dim=-1)
    assert (normals[mask] - expect[mask]).norm(dim=-1).max() < 1e-5
    assert torch.isnan(normals[~mask]).all() and torch.isnan(depth[~mask]).all()
    # a block half on the object is not on the object
    partial = hit.reshape(40, 2, 48, 2).any(3).any(1) & ~block_hit
    assert partial.any() and not mask[partial].any()


def test_nearest_object_wins_and_planes_face_the_camera():
    cam = OrthographicCamera(64, 64, 5e-4)
    backdrop = PlaneShape((0.0, 0.0, 0.4), (0.0, 0.3, 1.0))  # normal given away from the camera
    g = rasterize([backdrop, SphereShape(CENTER, RADIUS)], cam)
    assert g.mask.all()
    on_sphere = g.object_index == 1
    assert on_sphere[32, 32] and not on_sphere[0, 0]
    assert torch.all(g.depth[on_sphere] < 0.31) and torch.all(g.depth[~on_sphere] > 0.38)
    plane_n = g.normals[~on_sphere]
    assert torch.all((plane_n * g.view[~on_sphere]).sum(-1) > 0)
    assert torch.allclose(plane_n[0], -torch.nn.functional.normalize(torch.tensor([0.0, 0.3, 1.0], dtype=F64), dim=0))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_sphere_casts_no_shadow_on_itself(dtype):
    cam = OrthographicCamera(64, 64, 4e-4)
    sphere = SphereShape(CENTER, RADIUS)
    g = rasterize([sphere], cam, dtype=dtype)
    for direction in [(1.0, 0.0, -0.05), (0.0, -1.0, -0.2), (0.6, 0.6, -0.5), (0.0, 0.0, -1.0)]:
        assert not cast_shadow_mask([sphere], g, DirectionalLight(direction)).any()
    assert not cast_shadow_mask([sphere], g, PointLight((0.02, 0.0, 0.29))).any()


@pytest.fixture(scope="module")
def blob_view():
    blob = BlobShape((0.0, 0.0, 0.3), 0.008, subdivisions=5)
    return blob, rasterize([blob], OrthographicCamera(96, 96, 2.5e-4))


def test_blob_has_cast_shadows_under_grazing_light(blob_view):
    blob, g = blob_view
    lights = [DirectionalLight((math.cos(a), math.sin(a), -0.3)) for a in torch.linspace(0, 2 * math.pi, 9)[:-1].tolist()]
    counts = [int(cast_shadow_mask([blob], g, light).sum()) for light in lights]
    assert sum(counts) > 50, counts
    # a light at the camera sees no cast shadows on a star-shaped object... but N·L > 0 pixels only
    head_on = cast_shadow_mask([blob], g, DirectionalLight((0.0, 0.0, -1.0)))
    assert head_on.sum() <= 2  # only rounding at the silhouette


def test_shadow_flags_only_lit_facing_pixels(blob_view):
    blob, g = blob_view
    light = DirectionalLight((0.95, 0.0, -0.3))
    shadow = cast_shadow_mask([blob], g, light)
    facing = (g.normals * torch.tensor(light.direction, dtype=F64)).sum(-1) > 0
    assert not (shadow & ~facing).any() and not (shadow & ~g.mask).any()


def test_torus_shadows_itself():
    torus = TorusShape((0.0, 0.0, 0.3), 0.008, 0.003, axis=(0.0, -1.0, -1.5), sections=128)
    g = rasterize([torus], OrthographicCamera(96, 96, 2.5e-4))
    assert cast_shadow_mask([torus], g, DirectionalLight((0.0, 1.0, -0.25))).sum() > 20


def test_sphere_shadows_a_plane_where_geometry_says():
    cam = OrthographicCamera(64, 64, 1e-3)
    sphere = SphereShape((0.0, 0.0, 0.3), 0.01)
    floor = PlaneShape((0.0, 0.0, 0.33), (0.0, 0.0, -1.0))
    g = rasterize([sphere, floor], cam)
    light = DirectionalLight((0.0, 0.0, -1.0))
    shadow = cast_shadow_mask([sphere, floor], g, light)
    # head-on light: the shadow hides exactly behind the sphere, invisible
    assert not shadow.any()
    tilted = DirectionalLight((0.5, 0.0, -1.0))  # the shadow falls at +x... on the floor it moves to −x
    shadow = cast_shadow_mask([sphere, floor], g, tilted)
    on_floor = shadow & (g.object_index == 1)
    assert on_floor.any()
    x = g.points[on_floor][:, 0]
    assert torch.all(x < 0)
    # the shadow centre: ray from (x, 0, 0.33) toward L passes the sphere centre -> x = -0.03 * 0.5
    assert x.mean().item() == pytest.approx(-0.015, abs=2e-3)
    # a point light between the floor and the sphere does not put the sphere's shadow on it
    lamp = PointLight((-0.015, 0.0, 0.325))
    near = cast_shadow_mask([sphere, floor], g, lamp) & (g.object_index == 1)
    assert not near[(g.points[..., 0] + 0.015).abs() < 0.002].any()


def test_empty_scene_is_refused():
    with pytest.raises(ValueError, match="no objects"):
        rasterize([], OrthographicCamera(8, 8, 1.0))
