"""Tests of polarshape.surface.interreflection: one bounce estimated from a recovered surface."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarshape.cameras import OrthographicCamera, PerspectiveCamera
from polarshape.lights import DirectionalLight, Lights
from polarshape.scene.geometry import crater_depth_map
import polarshape.surface.interreflection as interreflection
from polarshape.surface.interreflection import estimate_one_bounce, surface_below_tangent_planes

PARAMS = {"ior": 1.5, "k_s": 1.0, "alpha": 0.3, "beta": 2.0, "kappa": 0.0}
LIGHTS = Lights(tuple(
    DirectionalLight((math.sin(math.radians(z)) * math.cos(math.radians(a)),
                      math.sin(math.radians(z)) * math.sin(math.radians(a)), -math.cos(math.radians(z))))
    for z, a in ((10, 0), (35, 120), (50, 240))
))


def _crater(n: int) -> tuple[np.ndarray, torch.Tensor, OrthographicCamera, np.ndarray]:
    """An n×n orthographic view of a plate with a dish (the crater scene's shape): depth, normals, camera, dish mask."""
    pixel = 0.0256 / n
    camera = OrthographicCamera(n, n, pixel, even=False)
    depth, normals = crater_depth_map(n, pixel, radius=0.008, depth=0.004, half_width=0.0115, distance=0.5)
    return depth, torch.tensor(normals), camera, np.nan_to_num(depth, nan=0.5) > 0.5  # the dish: below the plate


def _bounce(depth: np.ndarray, normals: torch.Tensor, camera, max_pixels: int):  # noqa: ANN001, ANN202
    n = depth.shape[0]
    view = torch.zeros(n, n, 3, dtype=normals.dtype)
    view[..., 2] = -1.0
    return estimate_one_bounce(normals, torch.full((n, n), 0.7, dtype=normals.dtype), depth, camera, view, LIGHTS,
                               PARAMS, samples=32, max_pixels=max_pixels)


def _sphere(n: int) -> tuple[np.ndarray, torch.Tensor, OrthographicCamera]:
    """An n×n orthographic view of a sphere of radius 0.45 (image widths) at z = 2: depth, normals, camera."""
    camera = OrthographicCamera(n, n, 1.0 / n, even=False)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    x, y = (xx - (n - 1) / 2) / n, (yy - (n - 1) / 2) / n
    disc = np.hypot(x, y) < 0.45
    zz = np.sqrt(np.clip(0.45**2 - x**2 - y**2, 0, None))
    depth = np.where(disc, 2.0 - zz, np.nan)
    normals = torch.tensor(np.where(disc[..., None], np.stack([x, y, -zz], -1) / 0.45, np.nan))
    return depth, normals, camera


def test_convex_surface_bounces_nothing() -> None:
    depth, normals, camera = _sphere(64)
    b = _bounce(depth, normals, camera, max_pixels=256)  # a lattice (stride 4) and a mesh of every 2nd pixel
    assert b.stride > 1 and b.rays_hit == 0.0
    assert b.stokes.shape == (3, 3, 64, 64) and torch.all(b.stokes == 0)


def test_convex_surface_casts_no_ray(monkeypatch: pytest.MonkeyPatch) -> None:
    """The convex test decides before any ray is cast (no ray-casting scene, no open3d)."""
    def no_rays(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("rays cast on a convex surface")

    monkeypatch.setattr(interreflection, "hemisphere_hits", no_rays)
    depth, normals, camera = _sphere(64)
    b = _bounce(depth, normals, camera, max_pixels=256)
    assert b.rays_hit == 0.0 and torch.all(b.stokes == 0)
    with pytest.raises(AssertionError, match="rays cast"):  # a concave one still casts its rays
        _bounce(*_crater(48)[:3], max_pixels=256)


def _grid_points(depth: np.ndarray, normals: torch.Tensor, camera, stride: int):  # noqa: ANN001, ANN202
    """The vertex grid (H, W, 3) and the lattice's points and normals (P, 3) of a depth map, as the estimator
    forms them."""
    points = torch.as_tensor(camera.unproject(depth))  # (H, W, 3)
    on = torch.isfinite(points).all(-1) & torch.isfinite(normals).all(-1)
    lattice = (slice(stride // 2, None, stride),) * 2
    return torch.where(on[..., None], points, math.nan), points[lattice][on[lattice]], normals[lattice][on[lattice]]


def _heights(vertices: torch.Tensor, points: torch.Tensor, normals: torch.Tensor) -> float:
    """The largest n̂·(v − p) over every vertex v and point p (brute force)."""
    v = vertices[torch.isfinite(vertices).all(-1)]  # (M, 3)
    n = normals / normals.norm(dim=-1, keepdim=True)
    return float((n @ v.T - (n * points).sum(-1, keepdim=True)).max())


def test_sphere_and_plane_lie_below_their_tangent_planes() -> None:
    depth, normals, camera = _sphere(64)
    vertices, points, lattice_normals = _grid_points(depth, normals, camera, 2)
    assert surface_below_tangent_planes(vertices, normals, points, lattice_normals, offset=1e-3 * 0.45)
    # a tilted plane: every vertex on every tangent plane
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float64) / 64
    plane = 2.0 + 0.3 * xx - 0.2 * yy
    n = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64).expand(64, 64, 3) / math.sqrt(1.13)
    vertices, points, lattice_normals = _grid_points(plane, n, camera, 3)
    assert surface_below_tangent_planes(vertices, n, points, lattice_normals, offset=1e-3)


def test_crater_rises_above_its_tangent_planes() -> None:
    depth, normals, camera, _ = _crater(64)
    vertices, points, lattice_normals = _grid_points(depth, normals, camera, 2)
    assert not surface_below_tangent_planes(vertices, normals, points, lattice_normals, offset=1e-3 * 0.0115)


@pytest.mark.parametrize("stride", [1, 3])
def test_tangent_plane_test_is_exact(stride: int) -> None:
    """On a bumpy sphere the answer flips where the brute-force largest height crosses the start-off."""
    depth, normals, camera = _sphere(50)
    gen = torch.Generator().manual_seed(3)
    bumps = 0.2 * torch.rand(normals.shape, generator=gen, dtype=normals.dtype) - 0.1
    noisy = normals + bumps  # not unit, and off the depth's own normals
    vertices, points, lattice_normals = _grid_points(depth - 1.9, noisy, camera, stride)  # near the origin
    highest = _heights(vertices, points, lattice_normals)
    assert highest > 1e-4  # the bumps lift vertices above their neighbours' planes
    shortest, longest = (float(x) for x in lattice_normals.norm(dim=-1).aminmax())  # rays start offset · |n| above
    assert surface_below_tangent_planes(vertices, noisy, points, lattice_normals, offset=1.05 * highest / shortest)
    assert not surface_below_tangent_planes(vertices, noisy, points, lattice_normals, offset=0.95 * highest / longest)


def test_coarse_mesh_keeps_the_bounce_in_a_dish() -> None:
    """The lattice's mesh (every stride // 2-th pixel) gives the bounce of the mesh of every pixel."""
    depth, normals, camera, dish = _crater(96)
    fine = _bounce(depth, normals, camera, max_pixels=96 * 96)  # every pixel, the mesh of every pixel
    coarse = _bounce(depth, normals, camera, max_pixels=400)  # stride 5: a mesh of every 2nd pixel
    assert fine.stride == 1 and coarse.stride == 5
    assert torch.isfinite(coarse.stokes).all()
    assert coarse.rays_hit == pytest.approx(fine.rays_hit, rel=0.15)
    s_fine, s_coarse = fine.stokes[:, 0][:, torch.as_tensor(dish)], coarse.stokes[:, 0][:, torch.as_tensor(dish)]
    assert float(s_fine.mean()) > 0
    assert float(s_coarse.mean()) == pytest.approx(float(s_fine.mean()), rel=0.1)
    # nothing bounces onto the plate far from the dish, and nothing outside the surface
    far = ~np.isfinite(depth) | (np.hypot(*np.mgrid[0:96, 0:96] - 47.5) > 45)
    assert torch.all(coarse.stokes[..., torch.as_tensor(far)] == 0)


def test_perspective_camera_mesh_grid() -> None:
    depth, normals, _, dish = _crater(96)
    camera = PerspectiveCamera(96, 96, fx=0.5 / (0.0256 / 96), fy=0.5 / (0.0256 / 96), cx=47.5, cy=47.5, even=False)
    b = _bounce(depth, normals, camera, max_pixels=400)
    assert b.stride == 5 and b.rays_hit > 0
    assert float(b.stokes[:, 0][:, torch.as_tensor(dish)].mean()) > 0


def _tilted_rim(tilt: float) -> torch.Tensor:
    """The sphere's normals with the one at the rim pixel (32, 3) turned ``tilt`` radians towards the image centre
    (a recovered rim not quite convex: its neighbours rise above that pixel's tangent plane)."""
    _, normals, _ = _sphere(64)
    n = normals[32, 3].clone()
    towards = torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype)
    towards = towards - (towards @ n) * n
    normals[32, 3] = math.cos(tilt) * n + math.sin(tilt) * towards / towards.norm()
    return normals


def _open_points(normals: torch.Tensor, limit: int = 256) -> torch.Tensor | None:
    depth, _, camera = _sphere(64)
    vertices, points, lattice_normals = _grid_points(depth, normals, camera, 1)
    return interreflection.tangent_plane_open_points(vertices, normals, points, lattice_normals, offset=1e-3 * 0.45,
                                                     limit=limit)


def test_open_points_are_the_pixels_whose_planes_cut_the_surface() -> None:
    depth, normals, camera = _sphere(64)
    assert _open_points(normals).numel() == 0  # a sphere: none
    tilted = _tilted_rim(0.1)
    opened = _open_points(tilted)
    vertices, points, lattice_normals = _grid_points(depth, tilted, camera, 1)
    assert opened.tolist() == [int(np.isfinite(depth).reshape(-1)[: 32 * 64 + 3].sum())]  # the pixel (32, 3)
    assert _heights(vertices, points[opened], lattice_normals[opened]) > 0  # a vertex above its plane
    assert _open_points(tilted, limit=0) is None  # more than the limit: None
    # a crater has hundreds
    depth, normals, camera, _ = _crater(64)
    vertices, points, lattice_normals = _grid_points(depth, normals, camera, 1)
    assert interreflection.tangent_plane_open_points(vertices, normals, points, lattice_normals, offset=1e-3 * 0.0115,
                                                     limit=256) is None


@pytest.mark.parametrize("tilt, cast", [(0.1, False), (0.2, True)])
def test_open_rim_pixel_casts_rays_only_when_they_may_hit(monkeypatch: pytest.MonkeyPatch, tilt: float,
                                                          cast: bool) -> None:
    """A rim pixel whose plane cuts the surface: its own rays decide. At a tilt of 0.1 rad they all miss (the
    rays are not cast, the estimate is the ray caster's: nothing); at 0.2 rad some hit (the rays are cast)."""
    depth, _, camera = _sphere(64)
    normals = _tilted_rim(tilt)
    assert _open_points(normals).numel() == 1
    calls: list[int] = []
    hits = interreflection.hemisphere_hits

    def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.append(1)
        return hits(*args, **kwargs)

    monkeypatch.setattr(interreflection, "hemisphere_hits", counted)
    decided = _bounce(depth, normals, camera, max_pixels=64 * 64)
    assert bool(calls) is cast
    monkeypatch.setattr(interreflection, "_MAX_OPEN_POINTS", -1)  # no point left to the rays' test: always cast
    rays = _bounce(depth, normals, camera, max_pixels=64 * 64)
    assert (rays.rays_hit > 0) is cast
    assert decided.rays_hit == rays.rays_hit and torch.equal(decided.stokes, rays.stokes)


@pytest.mark.parametrize("max_open, max_pairs", [(-1, 1 << 20), (256, 1 << 20), (1 << 30, 1 << 20),
                                                 (1 << 30, 1 << 30)])
def test_crater_gets_the_same_bounce_whatever_decides_to_cast(monkeypatch: pytest.MonkeyPatch, max_open: int,
                                                              max_pairs: int) -> None:
    """A concavity is cast whether the open points are too many (the default), or all go to the rays' test
    (too many (ray, triangle) pairs, or every pair tested: rays that may hit found), or none do."""
    depth, normals, camera, dish = _crater(48)
    reference = _bounce(depth, normals, camera, max_pixels=400)
    monkeypatch.setattr(interreflection, "_MAX_OPEN_POINTS", max_open)
    monkeypatch.setattr(interreflection, "_MAX_RAY_TRIANGLE_PAIRS", max_pairs)
    b = _bounce(depth, normals, camera, max_pixels=400)
    assert reference.rays_hit > 0 and float(reference.stokes[:, 0][:, torch.as_tensor(dish)].mean()) > 0
    assert b.rays_hit == reference.rays_hit and torch.equal(b.stokes, reference.stokes)


def test_ray_triangle_test_widens_by_the_margin() -> None:
    triangle = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]], dtype=torch.float64)
    down = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)

    def meets(origin: list[float], direction: torch.Tensor = down, margin: float = 1e-3) -> bool:
        o = torch.tensor([origin], dtype=torch.float64)
        return bool(interreflection.rays_may_meet_triangles(o, direction / direction.norm(), triangle, margin)[0])

    assert meets([0.2, 0.2, 0.0])  # through the inside
    assert meets([-0.0005, 0.2, 0.0]) and not meets([-0.002, 0.2, 0.0])  # past an edge: within the margin or not
    assert meets([0.5005, 0.5005, 0.0]) and not meets([0.502, 0.502, 0.0])  # the slanted edge
    assert not meets([0.2, 0.2, 1.01])  # behind the ray's start
    assert meets([0.2, 0.2, 1.0005])  # just behind, within the margin
    along = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)  # parallel to the plane
    assert meets([-1.0, 0.2, 1.0005], along) and not meets([-1.0, 0.2, 1.002], along)
    assert not meets([2.0, 0.2, 1.0], along)  # leaving it


def test_ray_triangle_test_keeps_every_hit_of_the_ray_caster() -> None:
    """Against open3d (float32, the estimator's ray caster): every hit is kept, and a ray that misses the whole
    mesh is proven to miss every triangle."""
    o3d = pytest.importorskip("open3d")
    from polarshape.surface.mesh import depth_to_mesh

    depth, normals, camera, _ = _crater(24)
    mesh = depth_to_mesh(depth, camera=camera)
    vertices = torch.as_tensor(np.asarray(mesh.vertices, dtype=np.float64))
    faces = torch.as_tensor(np.asarray(mesh.faces, dtype=np.int64))
    gen = torch.Generator().manual_seed(5)
    origins = vertices[torch.randint(len(vertices), (4000,), generator=gen)] - torch.tensor([0.0, 0.0, 2e-3],
                                                                                            dtype=torch.float64)
    directions = torch.nn.functional.normalize(torch.randn(4000, 3, generator=gen, dtype=torch.float64), dim=-1)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.numpy().astype(np.float32)),
                        o3d.core.Tensor(faces.numpy().astype(np.uint32)))
    out = scene.cast_rays(o3d.core.Tensor(torch.cat([origins, directions], -1).numpy().astype(np.float32)))
    hit = torch.as_tensor(np.isfinite(out["t_hit"].numpy()))
    assert 0.2 < float(hit.double().mean()) < 0.8
    margin = interreflection._FLOAT32_MARGIN * float(vertices.abs().max())
    prim = torch.as_tensor(out["primitive_ids"].numpy().astype(np.int64))[hit]
    assert interreflection.rays_may_meet_triangles(origins[hit], directions[hit], vertices[faces[prim]], margin).all()
    missed = (~hit).nonzero().squeeze(1)[:60]  # (M,) each against every triangle
    pairs = torch.cartesian_prod(missed, torch.arange(len(faces)))  # (M·F, 2)
    assert not interreflection.rays_may_meet_triangles(origins[pairs[:, 0]], directions[pairs[:, 0]],
                                                       vertices[faces[pairs[:, 1]]], margin).any()
