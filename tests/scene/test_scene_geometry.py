"""Shapes: analytic intersections, implicit refinement of tessellated shapes, mesh loading."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from polarshape.scene.geometry import BlobShape, MeshShape, PlaneShape, SphereShape, TorusShape, crater_depth_map, crater_mesh, plane_axes

F64 = torch.float64


def _rays(origins, directions):
    o = torch.tensor(origins, dtype=F64).reshape(-1, 3)
    d = torch.nn.functional.normalize(torch.tensor(directions, dtype=F64).reshape(-1, 3), dim=-1)
    return o, d


@pytest.fixture(scope="module")
def blob() -> BlobShape:
    return BlobShape((0.0, 0.0, 0.5), 0.01, subdivisions=5)


@pytest.fixture(scope="module")
def torus() -> TorusShape:
    return TorusShape((0.0, 0.0, 0.5), 0.008, 0.003, axis=(0.0, -1.0, -1.0), sections=128)


def test_sphere_hit_distance_and_normal():
    s = SphereShape((0.0, 0.0, 1.0), 0.5)
    o, d = _rays([[0, 0, 0], [0.3, 0, 0], [0.6, 0, 0]], [[0, 0, 1]] * 3)
    t, n = s.intersect(o, d)
    assert t[0].item() == pytest.approx(0.5, abs=1e-15)
    assert t[1].item() == pytest.approx(1.0 - math.sqrt(0.25 - 0.09), abs=1e-15)
    assert math.isinf(t[2].item()) and torch.all(n[2] == 0)
    p = o[1] + t[1] * d[1]
    assert torch.allclose(n[1], (p - torch.tensor([0, 0, 1.0], dtype=F64)) / 0.5, atol=1e-14)


def test_sphere_ray_from_inside_hits_far_side_and_behind_misses():
    s = SphereShape((0.0, 0.0, 1.0), 0.5)
    o, d = _rays([[0, 0, 1.0], [0, 0, 2.0]], [[0, 0, 1], [0, 0, 1]])
    t, _ = s.intersect(o, d)
    assert t[0].item() == pytest.approx(0.5)
    assert math.isinf(t[1].item())


def test_sphere_never_occludes_itself_from_its_lit_side():
    s = SphereShape((0.0, 0.0, 1.0), 0.5)
    g = torch.Generator().manual_seed(0)
    normals = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g, dtype=F64), dim=-1)
    light = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g, dtype=F64), dim=-1)
    light = torch.where(((normals * light).sum(-1) < 0)[:, None], -light, light)  # N·L > 0
    origins = torch.tensor([0, 0, 1.0], dtype=F64) + 0.5 * normals * (1 + 1e-6)
    assert not s.occluded(origins, light, torch.full((2000,), math.inf, dtype=F64)).any()
    # but a ray aimed through the centre is blocked
    o, d = _rays([[0, 0, 0]], [[0, 0, 1]])
    assert s.occluded(o, d, torch.tensor([10.0], dtype=F64)).all()
    assert not s.occluded(o, d, torch.tensor([0.4], dtype=F64)).any()  # stops before the sphere


def test_plane_infinite_and_finite():
    p = PlaneShape((0.0, 0.0, 2.0), (0.0, 0.0, -1.0))
    o, d = _rays([[0, 0, 0], [0, 0, 0], [0, 0, 0]], [[0, 0, 1], [1, 0, 1], [1, 0, 0]])
    t, n = p.intersect(o, d)
    assert t[0].item() == pytest.approx(2.0)
    assert t[1].item() == pytest.approx(2.0 * math.sqrt(2))
    assert math.isinf(t[2].item())  # parallel
    assert torch.allclose(n[0], torch.tensor([0, 0, -1.0], dtype=F64))
    finite = PlaneShape((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), size=(1.0, 0.5))
    o, d = _rays([[0.49, 0, 0], [0.51, 0, 0], [0, 0.24, 0], [0, 0.26, 0]], [[0, 0, 1]] * 4)
    t, _ = finite.intersect(o, d)
    assert torch.isfinite(t).tolist() == [True, False, True, False]


def test_plane_axes_are_orthonormal_and_in_plane():
    n = np.array([0.2, -0.5, -0.8])
    n /= np.linalg.norm(n)
    e1, e2 = (np.array(a) for a in plane_axes(n))
    assert abs(e1 @ n) < 1e-12 and abs(e2 @ n) < 1e-12 and abs(e1 @ e2) < 1e-12
    assert np.allclose(np.cross(e1, e2), n)


@pytest.mark.parametrize("bad", [dict(radius=0.0), dict(radius=-1.0)])
def test_sphere_rejects_bad_radius(bad):
    with pytest.raises(ValueError, match="radius"):
        SphereShape((0, 0, 1), **bad)


def test_blob_implicit_gradient_matches_finite_differences(blob):
    g = torch.Generator().manual_seed(1)
    directions = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=F64), dim=-1)
    p = torch.tensor(blob.center, dtype=F64) + 0.012 * directions
    f, grad = blob.implicit(p)
    h = 1e-7
    fd = torch.stack([(blob.implicit(p + h * e)[0] - blob.implicit(p - h * e)[0]) / (2 * h) for e in torch.eye(3, dtype=F64)], -1)
    assert torch.allclose(grad, fd, atol=1e-6)


def test_blob_hits_lie_on_the_implicit_surface_with_analytic_normals(blob):
    xs = torch.linspace(-0.012, 0.012, 41, dtype=F64)
    yy, xx = torch.meshgrid(xs, xs, indexing="ij")
    o = torch.stack([xx, yy, torch.zeros_like(xx)], -1).reshape(-1, 3)
    d = torch.zeros_like(o)
    d[:, 2] = 1.0
    t, n = blob.intersect(o, d)
    hit = torch.isfinite(t)
    assert hit.sum() > 500
    p = o[hit] + t[hit, None] * d[hit]
    f, grad = blob.implicit(p)
    converged = f.abs() < 1e-12
    assert converged.float().mean() > 0.99  # only silhouette-grazing rays may stay on the facets
    assert torch.allclose(n[hit][converged], torch.nn.functional.normalize(grad[converged], dim=-1), atol=1e-12)
    # the blob is not a sphere: hit radii vary by tens of percent
    r = (p - torch.tensor(blob.center, dtype=F64)).norm(dim=-1)
    assert r.max() / r.min() > 1.3


def test_blob_rejects_overlapping_dents():
    with pytest.raises(ValueError, match="amplitude|radius"):
        BlobShape((0, 0, 1), 0.01, amplitude=0.6)


def test_torus_signed_distance_and_tessellation(torus):
    a = torch.tensor(torus.axis, dtype=F64)
    e1 = torch.tensor(plane_axes(torus.axis)[0], dtype=F64)
    c = torch.tensor(torus.center, dtype=F64)
    pts = torch.stack([c, c + 0.008 * e1, c + 0.011 * e1, c + 0.008 * e1 + 0.001 * a])
    f, _ = torus.implicit(pts)
    assert torch.allclose(f, torch.tensor([0.008 - 0.003, -0.003, 0.0, -0.002], dtype=F64), atol=1e-15)
    assert torus.mesh.is_watertight
    assert torus.mesh.volume == pytest.approx(2 * math.pi**2 * 0.008 * 0.003**2, rel=5e-3)  # facets cut ≈0.2 %


def test_torus_ray_through_hole_misses_and_ray_on_tube_hits(torus):
    c = torch.tensor(torus.center, dtype=F64)
    a = torch.tensor(torus.axis, dtype=F64)
    e1 = torch.tensor(plane_axes(torus.axis)[0], dtype=F64)
    o = torch.stack([c - 0.05 * a, c + 0.008 * e1 - 0.05 * a])
    d = a.expand(2, 3).clone()
    t, n = torus.intersect(o, d)
    assert math.isinf(t[0].item())
    assert t[1].item() == pytest.approx(0.05 - 0.003, abs=1e-12)
    assert torch.allclose(n[1], -a, atol=1e-9)


def test_mesh_shape_smooth_normals_approach_the_sphere(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    path = tmp_path / "ball.ply"
    mesh.export(path)
    shape = MeshShape.from_file(str(path), scale=2.0, translation=(0.0, 0.0, 3.0))
    assert shape.bounding_radius == pytest.approx(1.0, rel=1e-6)
    o, d = _rays([[0.3, -0.2, 0], [0.0, 0.7, 0], [2.0, 0, 0]], [[0, 0, 1]] * 3)
    t, n = shape.intersect(o, d)
    assert math.isinf(t[2].item())
    p = o[:2] + t[:2, None] * d[:2]
    analytic = torch.nn.functional.normalize(p - torch.tensor([0, 0, 3.0], dtype=F64), dim=-1)
    assert torch.allclose(n[:2], analytic, atol=2e-3)
    flat = MeshShape(trimesh.creation.icosphere(subdivisions=1), smooth=False)
    o, d = _rays([[0.1, 0.05, -5]], [[0, 0, 1]])
    t, n = flat.intersect(o, d)
    faces = torch.tensor(flat.mesh.face_normals, dtype=F64)  # flat shading: the normal of the face hit
    assert float((faces - n[0]).norm(dim=-1).min()) < 1e-12


def test_mesh_rotation_is_applied(tmp_path):
    box = trimesh.creation.box(extents=(2.0, 0.2, 0.2))
    path = tmp_path / "bar.obj"
    box.export(path)
    rotated = MeshShape.from_file(str(path), rotation_deg=(0.0, 0.0, 90.0), translation=(0.0, 0.0, 5.0))
    o, d = _rays([[0.0, 0.8, 0.0], [0.8, 0.0, 0.0]], [[0, 0, 1]] * 2)
    t, _ = rotated.intersect(o, d)
    assert torch.isfinite(t).tolist() == [True, False]  # the bar now lies along y


def test_mesh_from_missing_or_broken_file_names_the_file(tmp_path):
    bad = tmp_path / "broken.ply"
    bad.write_text("not a mesh")
    with pytest.raises(ValueError, match="broken.ply"):
        MeshShape.from_file(str(bad))


def test_crater_depth_map_matches_the_crater_mesh_and_its_normals_its_depth() -> None:
    """The depth map lies on crater_mesh's surface (same grid, same z), and its analytic normals are
    those of the depth's own finite-difference gradient (a sign or factor slip would show)."""
    n, pixel = 257, 0.0256 / 256
    depth, normals = crater_depth_map(n, pixel, radius=0.008, depth=0.004, half_width=0.0128, distance=0.5)
    mesh = crater_mesh((0.0, 0.0, 0.5), 0.008, 0.004, 0.0128, n)  # vertices on the same n × n grid
    inside = np.isfinite(depth)
    assert inside[1:-1, 1:-1].all()
    np.testing.assert_allclose(depth[inside], mesh.vertices[:, 2].reshape(n, n)[inside], atol=1e-12)
    dzdy, dzdx = np.gradient(depth, pixel)
    fd = np.stack([dzdx, dzdy, -np.ones_like(depth)], -1)
    fd /= np.linalg.norm(fd, axis=-1, keepdims=True)
    cos = (fd[2:-2, 2:-2] * normals[2:-2, 2:-2]).sum(-1)
    assert float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max()) < 1.0
    assert (normals[inside][:, 2] < 0).all() and np.allclose(np.linalg.norm(normals[inside], axis=-1), 1.0)
