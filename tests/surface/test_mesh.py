"""Tests of polarshape.surface.mesh: depth → mesh, Poisson meshing, PLY/OBJ export."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from polarshape.cameras import OrthographicCamera, PerspectiveCamera
from polarshape.io.atomic import OutputExistsError
from polarshape.surface.mesh import (
    depth_to_mesh,
    mesh_file_checks,
    mesh_in_frame,
    poisson_mesh,
    self_intersecting_triangles,
    write_mesh,
)

SIZE = 48
ORTHO = OrthographicCamera(SIZE, SIZE, 0.02, even=False)  # 0.02 m per pixel, principal point at the centre


def _sphere_depth(size: int = SIZE, pixel: float = 0.02, radius: float = 0.4, centre_z: float = 2.0):
    """Orthographic depth/normals of the front of a sphere, circular mask; plus a stray pixel."""
    vv, uu = np.mgrid[0:size, 0:size].astype(np.float64)
    x = (uu - (size - 1) / 2) * pixel
    y = (vv - (size - 1) / 2) * pixel
    mask = x**2 + y**2 < (0.9 * radius) ** 2
    z = np.where(mask, centre_z - np.sqrt(np.maximum(radius**2 - x**2 - y**2, 0.0)), np.nan)
    n = np.stack([x, y, z - centre_z], axis=-1) / radius
    mask[0, 0] = True  # an isolated valid pixel: a vertex without faces
    z[0, 0] = 2.5
    n[0, 0] = (0.0, 0.0, -1.0)
    return z, mask, n


def _perspective_plane(size: int = SIZE):
    K = np.array([[60.0, 0.0, (size - 1) / 2], [0.0, 60.0, (size - 1) / 2], [0.0, 0.0, 1.0]])
    vv, uu = np.mgrid[0:size, 0:size].astype(np.float64)
    rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ np.linalg.inv(K).T
    n0 = np.array([0.5, -0.3, -1.0]) / np.linalg.norm([0.5, -0.3, -1.0])
    z = (n0 @ np.array([0.0, 0.0, 1.5])) / (rays @ n0)
    return z, K, n0


def _face_view_dots(mesh: trimesh.Trimesh, orthographic: bool) -> np.ndarray:
    centroids = mesh.triangles_center
    view = np.array([0.0, 0.0, -1.0]) if orthographic else -centroids / np.linalg.norm(centroids, axis=1, keepdims=True)
    return np.sum(mesh.face_normals * view, axis=1)


def test_one_vertex_per_valid_pixel_and_faces_face_the_camera() -> None:
    z, mask, n = _sphere_depth()
    mesh = depth_to_mesh(z, mask, camera=ORTHO, normals=n)
    valid = mask & np.isfinite(z)
    assert len(mesh.vertices) == int(valid.sum())
    full_blocks = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    assert len(mesh.faces) == 2 * int(full_blocks.sum())
    assert np.all(_face_view_dots(mesh, orthographic=True) > 0)
    # vertex i is the i-th valid pixel in raster order, at the camera-frame point of that pixel
    np.testing.assert_allclose(mesh.vertices, ORTHO.unproject(z)[valid])
    np.testing.assert_allclose(mesh.vertex_normals, n[valid], atol=1e-12)


def test_perspective_mesh_faces_the_camera_and_lies_on_the_rays() -> None:
    z, K, n0 = _perspective_plane()
    camera = PerspectiveCamera(SIZE, SIZE, K[0, 0], K[1, 1], K[0, 2], K[1, 2], even=False)
    mesh = depth_to_mesh(z, camera=camera)
    assert len(mesh.vertices) == SIZE * SIZE and len(mesh.faces) == 2 * (SIZE - 1) ** 2
    assert np.all(_face_view_dots(mesh, orthographic=False) > 0)
    # reprojection of the vertices gives the pixel grid back
    proj = mesh.vertices @ K.T
    uv = proj[:, :2] / proj[:, 2:]
    vv, uu = np.mgrid[0:SIZE, 0:SIZE]
    np.testing.assert_allclose(uv, np.stack([uu.ravel(), vv.ravel()], axis=1), atol=1e-9)
    # computed vertex normals (no normals given) equal the plane's normal
    np.testing.assert_allclose(mesh.vertex_normals, np.broadcast_to(n0, mesh.vertex_normals.shape), atol=1e-9)


def test_vertices_are_the_documented_camera_frame_points() -> None:
    # orthographic: ((u − (W−1)/2)·s, (v − (H−1)/2)·s, z); perspective: z·K⁻¹(u, v, 1)
    z, mask, _ = _sphere_depth()
    vv, uu = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    expected = np.stack([(uu - (SIZE - 1) / 2) * 0.02, (vv - (SIZE - 1) / 2) * 0.02, z], axis=-1)
    np.testing.assert_array_equal(ORTHO.unproject(z), expected)
    zp, K, _ = _perspective_plane()
    camera = PerspectiveCamera(SIZE, SIZE, K[0, 0], K[1, 1], K[0, 2], K[1, 2], even=False)
    rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ np.linalg.inv(K).T
    np.testing.assert_array_equal(camera.unproject(zp), zp[..., None] * rays)
    np.testing.assert_array_equal(depth_to_mesh(zp, camera=camera).vertices, (zp[..., None] * rays).reshape(-1, 3))


def test_computed_normals_face_the_camera_and_isolated_vertices_get_the_view_direction() -> None:
    z, mask, n = _sphere_depth()
    mesh = depth_to_mesh(z, mask, camera=ORTHO)
    valid = mask & np.isfinite(z)
    computed = mesh.vertex_normals
    assert np.all(computed[:, 2] < 0)
    np.testing.assert_allclose(computed[0], (0.0, 0.0, -1.0))  # the isolated pixel (0, 0)
    inner = np.abs(np.sum(computed * n[valid], axis=1))
    assert np.median(inner) > 0.999


def test_vertex_colors_from_an_albedo_map() -> None:
    z, mask, _ = _sphere_depth()
    albedo = np.zeros((SIZE, SIZE, 3))
    albedo[..., 0] = 1.0
    albedo[..., 2] = 0.5
    mesh = depth_to_mesh(z, mask, camera=ORTHO, colors=albedo)
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], np.broadcast_to([255, 0, 128], (len(mesh.vertices), 3)))


def test_depth_to_mesh_rejects_bad_input() -> None:
    z, mask, n = _sphere_depth()
    with pytest.raises(ValueError, match="mask must have shape"):
        depth_to_mesh(z, mask[:-1], camera=ORTHO)
    with pytest.raises(ValueError, match="no valid pixel"):
        depth_to_mesh(np.full((4, 4), np.nan), camera=OrthographicCamera(4, 4))
    with pytest.raises(ValueError, match="camera's grid"):
        depth_to_mesh(z, camera=OrthographicCamera(4, 4))
    with pytest.raises(ValueError, match="normals must have shape"):
        depth_to_mesh(z, mask, camera=ORTHO, normals=n[..., :2])
    with pytest.raises(ValueError, match="colors must have shape"):
        depth_to_mesh(z, mask, camera=ORTHO, colors=np.zeros((3, 3)))
    behind = np.full((SIZE, SIZE), -1.0)  # a perspective camera sees nothing at z < 0
    with pytest.raises(ValueError, match="no valid pixel"):
        depth_to_mesh(behind, camera=PerspectiveCamera(SIZE, SIZE, 60.0, 60.0, 23.5, 23.5))


def _sphere_cloud(count: int = 3000, radius: float = 0.3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(count, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.array([0.0, 0.0, 2.0]) + radius * n, n


def test_watertight_poisson_of_a_closed_sphere() -> None:
    points, normals = _sphere_cloud()
    mesh = poisson_mesh(points, normals, depth=6, watertight=True)
    assert mesh.is_watertight
    radii = np.linalg.norm(mesh.vertices - [0.0, 0.0, 2.0], axis=1)
    assert np.all(np.abs(radii - 0.3) < 0.02)
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 0.3**3, rel=0.05)


def test_poisson_density_trimming_removes_the_extrapolated_back() -> None:
    points, normals = _sphere_cloud()
    front = points[:, 2] < 2.0  # only the camera-facing half was seen
    closed = poisson_mesh(points[front], normals[front], depth=6, watertight=True)
    trimmed = poisson_mesh(points[front], normals[front], depth=6, density_quantile=0.3)
    assert len(trimmed.vertices) < 0.8 * len(closed.vertices)
    assert trimmed.vertices[:, 2].max() < closed.vertices[:, 2].max()


def test_poisson_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        poisson_mesh(np.zeros((10, 3)), np.zeros((10, 2)))
    with pytest.raises(ValueError, match="at least 4"):
        poisson_mesh(np.full((10, 3), np.nan), np.ones((10, 3)))


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_write_mesh_round_trip_with_normals(tmp_path: Path, suffix: str) -> None:
    z, mask, n = _sphere_depth()
    mask[0, 0] = False  # OBJ readers drop unreferenced vertices: keep only meshed pixels
    albedo = np.full((SIZE, SIZE, 3), 0.25)
    mesh = depth_to_mesh(z, mask, camera=ORTHO, normals=n, colors=albedo)
    path = write_mesh(mesh, tmp_path / f"mesh{suffix}")
    back = trimesh.load(path, process=False)
    assert len(back.faces) == len(mesh.faces)
    assert len(back.vertices) == len(mesh.vertices)
    # match vertices by position (OBJ readers may reorder), then compare normals
    dist, nearest = cKDTree(mesh.vertices).query(back.vertices)
    assert dist.max() < 1e-6 and len(np.unique(nearest)) == len(nearest)
    np.testing.assert_allclose(back.vertex_normals, mesh.vertex_normals[nearest], atol=1e-4)
    if suffix == ".ply":
        np.testing.assert_array_equal(back.visual.vertex_colors[:, :3], 64)
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_write_mesh_refuses_to_overwrite(tmp_path: Path) -> None:
    z, mask, n = _sphere_depth()
    mesh = depth_to_mesh(z, mask, camera=ORTHO)
    path = tmp_path / "mesh.ply"
    write_mesh(mesh, path)
    before = path.read_bytes()
    with pytest.raises(OutputExistsError):
        write_mesh(mesh, path)
    assert path.read_bytes() == before
    write_mesh(depth_to_mesh(z * 2, mask, camera=ORTHO), path, overwrite=True)
    assert path.read_bytes() != before
    with pytest.raises(ValueError, match=r"\.ply or \.obj"):
        write_mesh(mesh, tmp_path / "mesh.stl")


# --- frames, headers, checks, Poisson colours and repair -----------------------------------------

OPENGL = np.diag([1.0, -1.0, -1.0])


def _ply_header(path: Path) -> str:
    data = path.read_bytes()
    return data[: data.index(b"end_header")].decode("ascii")


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_opengl_frame_is_a_half_turn_and_faces_still_face_the_viewer(tmp_path: Path, suffix: str) -> None:
    z, mask, n = _sphere_depth()
    mask[0, 0] = False  # OBJ readers drop unreferenced vertices
    mesh = depth_to_mesh(z, mask, camera=ORTHO, normals=n)
    gl = trimesh.load(write_mesh(mesh, tmp_path / f"gl{suffix}", frame="opengl"), process=False)
    cv = trimesh.load(write_mesh(mesh, tmp_path / f"cv{suffix}", frame="opencv"), process=False)
    dist, nearest = cKDTree(mesh.vertices @ OPENGL).query(gl.vertices)  # OBJ readers may reorder
    assert dist.max() < 1e-6
    np.testing.assert_allclose(gl.vertex_normals, mesh.vertex_normals[nearest] @ OPENGL, atol=1e-4)
    # orthographic: the viewer is at +z in opengl (the camera looks along −z), at −z in opencv
    assert np.all(gl.face_normals[:, 2] > 0) and np.all(gl.vertex_normals[:, 2] > 0)
    assert np.all(cv.face_normals[:, 2] < 0)
    assert gl.vertices[:, 1].max() == pytest.approx(-mesh.vertices[:, 1].min(), abs=1e-6)  # image top is +y


def test_perspective_mesh_in_opengl_faces_the_camera_at_the_origin(tmp_path: Path) -> None:
    z, K, _ = _perspective_plane()
    camera = PerspectiveCamera(SIZE, SIZE, K[0, 0], K[1, 1], K[0, 2], K[1, 2], even=False)
    gl = trimesh.load(write_mesh(depth_to_mesh(z, camera=camera), tmp_path / "gl.ply", frame="opengl"), process=False)
    assert np.all(gl.vertices[:, 2] < 0)  # in front of an OpenGL camera: z < 0
    assert np.all(np.sum(gl.face_normals * -gl.triangles_center, axis=1) > 0)
    assert mesh_in_frame(depth_to_mesh(z, camera=camera), "opengl").is_winding_consistent


def test_file_headers_state_units_and_frame(tmp_path: Path) -> None:
    z, mask, _ = _sphere_depth()
    mesh = depth_to_mesh(z, mask, camera=ORTHO)
    header = _ply_header(write_mesh(mesh, tmp_path / "m.ply", frame="opengl"))
    assert "comment polarshape units: metres\n" in header
    assert "comment polarshape frame: opengl: x right, y up, z toward the viewer" in header
    assert "diag(1, -1, -1)" in header and header.startswith("ply\nformat binary_little_endian 1.0\n")
    obj = write_mesh(mesh, tmp_path / "m.obj", frame="opencv", units="superpixels").read_text()
    assert obj.startswith("# polarshape units: super-pixels")
    assert "# polarshape frame: opencv: x right, y down, z into the scene" in obj
    plain = write_mesh(mesh, tmp_path / "s.ply", units="superpixels")
    assert "comment polarshape units: super-pixels" in _ply_header(plain)
    with pytest.raises(ValueError, match="frame must be"):
        write_mesh(mesh, tmp_path / "x.ply", frame="directx")
    with pytest.raises(ValueError, match="units must be"):
        write_mesh(mesh, tmp_path / "x.ply", units="mm")


def _overlapping_spheres() -> trimesh.Trimesh:
    """Two icospheres that cut each other (one mesh): a closed, manifold, self-intersecting surface."""
    a = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    b = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    b.apply_translation([1.2, 0.1, 0.05])
    return trimesh.util.concatenate([a, b])


def test_self_intersecting_triangles_are_open3d_pairs() -> None:
    import open3d as o3d

    mesh = _overlapping_spheres()
    reference = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                          o3d.utility.Vector3iVector(mesh.faces))
    expected = np.unique(np.sort(np.asarray(reference.get_self_intersecting_triangles()), axis=1), axis=0)
    assert len(expected) > 20
    for cell in (10, 100, 100000):  # many cells, some, one
        found = self_intersecting_triangles(mesh.vertices, mesh.faces, cell_triangles=cell)
        np.testing.assert_array_equal(found, expected)
    single = trimesh.creation.icosphere(subdivisions=2)
    assert self_intersecting_triangles(single.vertices, single.faces).shape == (0, 2)


def test_mesh_file_checks_are_open3d_verdicts_on_the_file(tmp_path: Path) -> None:
    import open3d as o3d

    z, mask, _ = _sphere_depth()
    cases = {
        "closed": trimesh.creation.icosphere(subdivisions=2),
        "crossing": _overlapping_spheres(),
        "open": depth_to_mesh(z, mask, camera=ORTHO),
    }
    verdicts = {}
    for name, mesh in cases.items():
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(tmp_path / f"{name}.ply")
        checks = mesh_file_checks(tmp_path / f"{name}.ply")
        reference = o3d.io.read_triangle_mesh(str(tmp_path / f"{name}.ply"))
        assert checks["watertight"] == reference.is_watertight()
        assert checks["self_intersecting"] == reference.is_self_intersecting()
        assert checks["edge_manifold"] == reference.is_edge_manifold(allow_boundary_edges=True)
        assert checks["vertex_manifold"] == reference.is_vertex_manifold()
        assert checks["triangles"] == len(mesh.faces)
        verdicts[name] = (checks["watertight"], checks["self_intersecting"], checks["boundary_edges"] > 0)
    assert verdicts == {"closed": (True, False, False), "crossing": (False, True, False), "open": (False, False, True)}
    with pytest.raises(FileNotFoundError, match="no such mesh"):
        mesh_file_checks(tmp_path / "missing.ply")


def test_poisson_interpolates_point_colours(tmp_path: Path) -> None:
    points, normals = _sphere_cloud()
    red = points[:, 0] > 0  # right half red, left half blue
    colours = np.where(red[:, None], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    mesh = poisson_mesh(points, normals, depth=6, colors=colours, watertight=True)
    rgba = mesh.visual.vertex_colors
    assert rgba.shape == (len(mesh.vertices), 4) and np.all(rgba[:, 3] == 255)
    right, left = mesh.vertices[:, 0] > 0.1, mesh.vertices[:, 0] < -0.1
    assert np.all(rgba[right, 0] > 200) and np.all(rgba[right, 2] < 55)
    assert np.all(rgba[left, 2] > 200) and np.all(rgba[left, 0] < 55)
    back = trimesh.load(write_mesh(mesh, tmp_path / "p.ply", frame="opengl"), process=False)
    np.testing.assert_array_equal(back.visual.vertex_colors, rgba)
    grey = poisson_mesh(points, normals, depth=5, colors=np.full(len(points), 0.5), watertight=True)
    assert np.all(np.abs(grey.visual.vertex_colors[:, :3].astype(int) - 127.5) < 1)  # 0.5 · 255
    assert poisson_mesh(points, normals, depth=5).visual.kind is None
    with pytest.raises(ValueError, match="colors must have shape"):
        poisson_mesh(points, normals, colors=colours[:10])


def _mirror_closed_hemisphere(size: int = 128, radius: float = 0.4) -> tuple[np.ndarray, np.ndarray]:
    """The front of a sphere seen by a size×size orthographic camera and its mirror image behind
    (as the pipeline closes a one-view surface)."""
    pixel = 2 * radius / size
    vv, uu = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = (uu - (size - 1) / 2) * pixel, (vv - (size - 1) / 2) * pixel
    inside = x**2 + y**2 < (0.999 * radius) ** 2
    z = 2.0 - np.sqrt(np.maximum(radius**2 - x**2 - y**2, 0.0))
    front = np.stack([x, y, z], axis=-1)[inside]
    normals = (front - [0.0, 0.0, 2.0]) / radius
    back, back_normals = front * [1, 1, -1] + [0, 0, 2 * front[:, 2].max()], normals * [1, 1, -1]
    return np.concatenate([front, back]), np.concatenate([normals, back_normals])


@pytest.mark.slow
def test_repair_removes_poisson_self_intersections(tmp_path: Path) -> None:
    points, normals = _mirror_closed_hemisphere()
    raw = poisson_mesh(points, normals, depth=8, watertight=True, repair=False)
    repaired = poisson_mesh(points, normals, depth=8, watertight=True)
    assert raw.metadata["repair"] is None
    assert len(self_intersecting_triangles(raw.vertices, raw.faces)) > 0  # marching-cubes slivers
    checks = mesh_file_checks(write_mesh(repaired, tmp_path / "p.ply"))
    assert checks["self_intersecting_pairs"] == 0 and checks["watertight"]
    removed = repaired.metadata["repair"]["triangles_removed"]
    assert 0 < removed < 0.02 * len(repaired.faces)  # slivers only: the surface is kept


@pytest.mark.parametrize("coloured", [True, False])
@pytest.mark.parametrize("frame", ["opencv", "opengl"])
def test_obj_is_trimesh_export_byte_for_byte(tmp_path: Path, coloured: bool, frame: str) -> None:
    """mesh.obj is written with numpy (polarshape.io.tables): the bytes of trimesh's exporter after the header."""
    z, mask, n = _sphere_depth()
    colours = np.random.default_rng(0).random(z.shape) if coloured else None
    mesh = depth_to_mesh(z, mask, camera=ORTHO, normals=n, colors=colours)
    text = write_mesh(mesh, tmp_path / "m.obj", frame=frame).read_bytes()
    reference = trimesh.exchange.obj.export_obj(mesh_in_frame(mesh, frame), include_normals=True, include_color=True,
                                                include_texture=False).encode()
    assert text.endswith(reference)
    assert text[: len(text) - len(reference)].decode().startswith("# polarshape units: metres")
