"""Tests of polarshape.surface.integrate: signs, analytic surfaces, masks, components, bilateral."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from numpy.typing import NDArray

from polarshape.cameras import OrthographicCamera, PerspectiveCamera
from polarshape.surface.integrate import IntegrationReport, integrate_normals, surface_gradients

Arr = NDArray[np.float64]
SIZE = 128
PIXEL = 1.0 / SIZE  # metres per pixel (orthographic): a 1 m wide image


def _unit(v: Arr) -> Arr:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _grid(size: int = SIZE) -> tuple[Arr, Arr]:
    vv, uu = np.mgrid[0:size, 0:size].astype(np.float64)
    return uu, vv


def _intrinsics(size: int = SIZE, f: float = 150.0) -> Arr:
    c = (size - 1) / 2
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


def _rays(K: Arr, size: int = SIZE) -> Arr:
    uu, vv = _grid(size)
    return np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ np.linalg.inv(K).T  # (H, W, 3), r_z = 1


def _ortho(normals, pixel: float = 1.0) -> OrthographicCamera:
    """The orthographic camera at the grid of a normal map (H, W, 3), ``pixel`` metres per pixel."""
    h, w = normals.shape[:2]
    return OrthographicCamera(w, h, pixel, even=False)


def _persp(K: Arr, size: int = SIZE) -> PerspectiveCamera:
    """The pinhole camera of intrinsics K (3, 3) on a size × size grid."""
    return PerspectiveCamera(size, size, K[0, 0], K[1, 1], K[0, 2], K[1, 2], even=False)


def _circle(size: int = SIZE, radius: float = 0.42, centre: tuple[float, float] = (0.5, 0.5)) -> NDArray[np.bool_]:
    uu, vv = _grid(size)
    return (uu - centre[0] * (size - 1)) ** 2 + (vv - centre[1] * (size - 1)) ** 2 < (radius * size) ** 2


# ---- analytic surfaces: (normals (H, W, 3), mask (H, W), true depth (H, W)) -------------------------


def ortho_sphere(mask: NDArray[np.bool_], centre_uv: tuple[float, float], radius_m: float, centre_z: float = 2.0):
    """Front of a sphere (camera-frame normals (x, y, z − c)/R: outward, so n_z < 0)."""
    uu, vv = _grid(mask.shape[0])
    x = (uu - centre_uv[0]) * PIXEL
    y = (vv - centre_uv[1]) * PIXEL
    z = centre_z - np.sqrt(np.maximum(radius_m**2 - x**2 - y**2, 0.0))
    n = np.stack([x, y, z - centre_z], axis=-1) / radius_m
    return n, mask, z


def ortho_plane(mask: NDArray[np.bool_], dzdx: float = 0.4, dzdy: float = -0.25):
    uu, vv = _grid(mask.shape[0])
    z = 1.5 + dzdx * uu * PIXEL + dzdy * vv * PIXEL
    n = np.broadcast_to(_unit(np.array([dzdx, dzdy, -1.0])), mask.shape + (3,)).copy()
    return n, mask, z


def ortho_bump(mask: NDArray[np.bool_], height: float = 0.15, sigma: float = 0.15):
    uu, vv = _grid(mask.shape[0])
    x = (uu - 60.0) * PIXEL
    y = (vv - 70.0) * PIXEL
    g = height * np.exp(-(x**2 + y**2) / (2 * sigma**2))
    z = 2.0 - g  # bulges towards the camera
    zx, zy = g * x / sigma**2, g * y / sigma**2  # ∂z/∂x, ∂z/∂y
    n = _unit(np.stack([zx, zy, -np.ones_like(z)], axis=-1))
    return n, mask, z


def persp_sphere(mask_extra: NDArray[np.bool_], K: Arr, centre=(0.1, -0.05, 1.6), radius: float = 0.6):
    """Ray-cast sphere, geometric outward normals; mask = hit, facing the camera by > 20°, ∩ mask_extra."""
    r = _rays(K)
    c = np.asarray(centre)
    a = np.sum(r * r, axis=-1)
    b = -2.0 * (r @ c)
    disc = b * b - 4 * a * (c @ c - radius**2)
    z = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
    p = z[..., None] * r
    n = (p - c) / radius
    view = -_unit(p)
    mask = (disc > 0) & (np.sum(n * view, axis=-1) > np.cos(np.radians(70))) & mask_extra
    return n, mask, z


def persp_plane(mask: NDArray[np.bool_], K: Arr, normal=(0.3, -0.2, -1.0), point=(0.0, 0.0, 2.0)):
    n0 = _unit(np.asarray(normal, dtype=np.float64))
    r = _rays(K)
    z = (n0 @ np.asarray(point)) / (r @ n0)  # n·(z r) = n·P0
    return np.broadcast_to(n0, mask.shape + (3,)).copy(), mask, z


def persp_bump(mask: NDArray[np.bool_], K: Arr, height: float = 0.3, sigma: float = 20.0):
    """Depth z(u, v) = 2 − h·exp(−ρ²/2σ²) in pixels; normals from the exact tangents P_u, P_v."""
    uu, vv = _grid(mask.shape[0])
    du, dv = uu - 60.0, vv - 70.0
    g = height * np.exp(-(du**2 + dv**2) / (2 * sigma**2))
    z = 2.0 - g
    z_u, z_v = g * du / sigma**2, g * dv / sigma**2
    k_inv = np.linalg.inv(K)
    r = _rays(K)
    p_u = z_u[..., None] * r + z[..., None] * k_inv[:, 0]
    p_v = z_v[..., None] * r + z[..., None] * k_inv[:, 1]
    n = _unit(np.cross(p_v, p_u))  # camera-facing orientation (n·r < 0)
    return n, mask, z


def _rmse_offset(depth: Arr, true: Arr, mask: NDArray[np.bool_]) -> float:
    """RMSE after the best additive offset, as a fraction of the true depth range."""
    e = depth[mask] - true[mask]
    e = e - e.mean()
    return float(np.sqrt(np.mean(e**2)) / np.ptp(true[mask]))


def _rmse_scale(depth: Arr, true: Arr, mask: NDArray[np.bool_]) -> float:
    """RMSE after the best scale, as a fraction of the true depth range."""
    d, t = depth[mask], true[mask]
    s = float(d @ t / (d @ d))
    return float(np.sqrt(np.mean((s * d - t) ** 2)) / np.ptp(t))


# ---- gradient signs ----------------------------------------------------------------------------------


def test_orthographic_gradient_signs_plane() -> None:
    # z = 0.4 x − 0.25 y (y down): facing normal ∝ (0.4, −0.25, −1), p = −n_x/n_z, q = −n_y/n_z.
    n, mask, _ = ortho_plane(np.ones((4, 4), bool))
    g_u, g_v, clamped = surface_gradients(n, camera=_ortho(n, 0.01))
    np.testing.assert_allclose(g_u, 0.4 * 0.01, rtol=1e-12)
    np.testing.assert_allclose(g_v, -0.25 * 0.01, rtol=1e-12)
    assert not clamped.any()


def test_orthographic_sphere_depth_grows_away_from_centre() -> None:
    # The front of a sphere recedes (z grows) to the right and downwards of its centre.
    n, mask, z = ortho_sphere(_circle(), (63.5, 63.5), 0.45)
    g_u, g_v, _ = surface_gradients(n, camera=_ortho(n, PIXEL))
    right, below = (64, 100), (100, 64)
    assert g_u[right] > 0 and z[64, 101] > z[64, 100]
    assert g_v[below] > 0 and z[101, 64] > z[100, 64]


def test_perspective_gradients_match_finite_differences_of_log_depth() -> None:
    K = _intrinsics()
    n, mask, z = persp_plane(np.ones((SIZE, SIZE), bool), K)
    g_u, g_v, clamped = surface_gradients(n, camera=_persp(K))
    assert not clamped.any()
    logz = np.log(z)
    # A plane has ∂²log z ≠ 0, so compare with central differences at second order.
    np.testing.assert_allclose(g_u[:, 1:-1], (logz[:, 2:] - logz[:, :-2]) / 2, rtol=1e-3, atol=1e-7)
    np.testing.assert_allclose(g_v[1:-1, :], (logz[2:, :] - logz[:-2, :]) / 2, rtol=1e-3, atol=1e-7)


# ---- recovery of analytic surfaces ---------------------------------------------------------------------

ORTHO_CASES = {
    "sphere_cap": lambda: ortho_sphere(_circle(radius=0.40), (63.5, 63.5), 0.45),
    "tilted_plane": lambda: ortho_plane(np.ones((SIZE, SIZE), bool)),
    "smooth_bump": lambda: ortho_bump(_circle(radius=0.45)),
}
PERSP_CASES = {
    "sphere_cap": lambda K: persp_sphere(np.ones((SIZE, SIZE), bool), K),
    "tilted_plane": lambda K: persp_plane(_circle(radius=0.45), K),
    "smooth_bump": lambda K: persp_bump(np.ones((SIZE, SIZE), bool), K),
}


@pytest.mark.parametrize("method", ["smooth", "bilateral"])
@pytest.mark.parametrize("case", sorted(ORTHO_CASES))
def test_orthographic_recovery(case: str, method: str) -> None:
    n, mask, z = ORTHO_CASES[case]()
    depth = integrate_normals(n, mask, camera=_ortho(n, PIXEL), method=method)
    assert np.all(np.isnan(depth[~mask])) and np.all(np.isfinite(depth[mask]))
    err = _rmse_offset(depth, z, mask)
    assert err < 0.01, f"{case}/{method}: RMSE {err:.4f} of the depth range"
    # Gauge: median depth = reference_depth (1.0) by default.
    assert np.median(depth[mask]) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("method", ["smooth", "bilateral"])
@pytest.mark.parametrize("case", sorted(PERSP_CASES))
def test_perspective_recovery(case: str, method: str) -> None:
    K = _intrinsics()
    n, mask, z = PERSP_CASES[case](K)
    assert mask.sum() > 4000
    depth = integrate_normals(n, mask, camera=_persp(K, n.shape[0]), method=method, reference_depth=2.0)
    assert np.all(np.isnan(depth[~mask])) and np.all(depth[mask] > 0)
    err = _rmse_scale(depth, z, mask)
    assert err < 0.01, f"{case}/{method}: RMSE {err:.4f} of the depth range"
    assert np.median(depth[mask]) == pytest.approx(2.0, rel=1e-6)  # median of an even count


def test_smooth_orthographic_is_accurate_well_below_tolerance() -> None:
    # The discretisation is second order: a sphere cap integrates to ~1e-4 of its depth range.
    n, mask, z = ORTHO_CASES["sphere_cap"]()
    assert _rmse_offset(integrate_normals(n, mask, camera=_ortho(n, PIXEL)), z, mask) < 1e-3


def test_circular_mask_ignores_garbage_outside() -> None:
    n, mask, z = ortho_sphere(_circle(radius=0.40), (63.5, 63.5), 0.45)
    garbage = n.copy()
    garbage[~mask] = np.nan
    garbage[~mask & (np.arange(SIZE)[None, :] % 2 == 0)] = (0.0, 0.0, 5.0)  # not unit, facing away
    d1 = integrate_normals(n, mask, camera=_ortho(n, PIXEL))
    d2 = integrate_normals(garbage, mask, camera=_ortho(garbage, PIXEL))
    np.testing.assert_allclose(d1[mask], d2[mask], atol=1e-12)


# ---- components, gauge, warm start --------------------------------------------------------------------


def _two_spheres() -> tuple[Arr, NDArray[np.bool_], Arr, NDArray[np.bool_], NDArray[np.bool_]]:
    left = _circle(radius=0.2, centre=(0.27, 0.5))
    right = _circle(radius=0.15, centre=(0.75, 0.4))
    n1, _, z1 = ortho_sphere(left, (0.27 * 127, 0.5 * 127), 0.3, centre_z=1.5)
    n2, _, z2 = ortho_sphere(right, (0.75 * 127, 0.4 * 127), 0.25, centre_z=3.0)
    n = np.where(left[..., None], n1, n2)
    z = np.where(left, z1, z2)
    return n, left | right, z, left, right


def test_two_components_each_get_their_own_constant() -> None:
    n, mask, z, left, right = _two_spheres()
    depth = integrate_normals(n, mask, camera=_ortho(n, PIXEL), reference_depth=2.5)
    for part in (left, right):
        assert _rmse_offset(depth, z, part) < 0.01
        assert np.median(depth[part]) == pytest.approx(2.5, abs=1e-9)
    # One offset for both would be wrong: the true components sit 1.5 m apart.
    assert _rmse_offset(depth, z, mask) > 0.1


def test_depth_init_fixes_each_component_and_warm_starts() -> None:
    n, mask, z, left, right = _two_spheres()
    depth = integrate_normals(n, mask, camera=_ortho(n, PIXEL), depth_init=z, solver="cg")
    scale = np.ptp(z[mask])
    assert np.sqrt(np.nanmean((depth - z) ** 2)) < 0.01 * scale  # no alignment needed
    cold = integrate_normals(n, mask, camera=_ortho(n, PIXEL), solver="direct")
    np.testing.assert_allclose(depth[left] - np.median(depth[left]), cold[left] - np.median(cold[left]), atol=1e-6)


def test_depth_init_sets_perspective_scale() -> None:
    K = _intrinsics()
    n, mask, z = persp_sphere(np.ones((SIZE, SIZE), bool), K)
    init = np.full_like(z, np.nan)
    init[::7, ::5] = z[::7, ::5]  # sparse prior: only the scale is taken from it
    depth = integrate_normals(n, mask, camera=_persp(K, n.shape[0]), depth_init=init)
    assert np.sqrt(np.mean((depth[mask] - z[mask]) ** 2)) < 0.01 * np.ptp(z[mask])


def test_tiny_components() -> None:
    n, mask, z = ortho_sphere(_circle(radius=0.3), (63.5, 63.5), 0.45)
    mask = mask.copy()
    mask[2, 2] = True  # isolated pixel
    mask[5, 10:12] = True  # two-pixel component
    n = np.where(mask[..., None] & ~np.isfinite(n), np.array([0.0, 0.0, -1.0]), n)
    n[2, 2] = n[5, 10] = n[5, 11] = _unit(np.array([0.1, 0.0, -1.0]))
    depth = integrate_normals(n, mask, camera=_ortho(n, PIXEL), reference_depth=3.0)
    assert depth[2, 2] == pytest.approx(3.0)
    assert depth[5, 11] - depth[5, 10] == pytest.approx(0.1 * PIXEL, rel=1e-9)
    dropped = integrate_normals(n, mask, camera=_ortho(n, PIXEL), min_component_size=3)
    assert np.isnan(dropped[2, 2]) and np.isnan(dropped[5, 10]) and np.isfinite(dropped[64, 64])


@pytest.mark.parametrize("solver", ["cg", "amg"])
def test_iterative_solvers_match_direct(solver: str) -> None:
    if solver == "amg":
        pytest.importorskip("pyamg")
    n, mask, z = ORTHO_CASES["smooth_bump"]()
    ref = integrate_normals(n, mask, camera=_ortho(n, PIXEL), solver="direct")
    report = IntegrationReport()
    got = integrate_normals(n, mask, camera=_ortho(n, PIXEL), solver=solver, report=report)
    assert report.solver == solver and report.cg_steps > 0 and report.iterations == 1
    np.testing.assert_allclose(got[mask], ref[mask], atol=1e-6 * np.ptp(z[mask]))


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_accepts_torch_tensors_of_either_precision(dtype: str) -> None:
    torch = pytest.importorskip("torch")
    n, mask, z = ORTHO_CASES["smooth_bump"]()
    tensor = torch.from_numpy(n).to(getattr(torch, dtype))
    depth = integrate_normals(tensor, torch.from_numpy(mask), camera=_ortho(tensor, PIXEL))
    assert depth.dtype == np.float64
    assert _rmse_offset(depth, z, mask) < (1e-3 if dtype == "float32" else 2e-4)


# ---- discontinuities: bilateral against smooth --------------------------------------------------------


def ortho_tear(size: int = 96, slope: float = 0.6):
    """A fronto-parallel plane (normals (0, 0, −1)) above a cliff; below it the same plane up to
    column 30, then a crease into a plane of slope ``slope`` (pixel units): the cliff's height grows
    from 0 to ~40 px along it, so the normals do determine it (curl along the cliff)."""
    uu, vv = _grid(size)
    top = vv < size // 2
    z = np.where(top, 0.0, slope * np.maximum(uu - 30.0, 0.0))
    zx = np.where(top | (uu < 30), 0.0, slope)
    n = _unit(np.stack([zx, np.zeros_like(zx), -np.ones_like(zx)], axis=-1))
    return n, np.ones((size, size), bool), z


def ortho_occlusion(size: int = 96, slope: float = 0.5):
    """A spherical cap (to 60° from the view axis) in front of a tilted plane (pixel units) that
    touches the cap's left edge: an occluding boundary whose height grows to ~30 px on the right."""
    uu, vv = _grid(size)
    radius, c = 0.3 * size, (size - 1) / 2
    r2 = (uu - c) ** 2 + (vv - c) ** 2
    cap_r = radius * np.sin(np.radians(60))
    cap = r2 < cap_r**2
    z_c = 100.0
    z_cap = z_c - np.sqrt(np.maximum(radius**2 - r2, 0.0))
    rim = z_c - radius * np.cos(np.radians(60))
    z = np.where(cap, z_cap, rim + slope * (uu - (c - cap_r)))
    n_cap = np.stack([uu - c, vv - c, z_cap - z_c], axis=-1) / radius
    n = np.where(cap[..., None], n_cap, _unit(np.array([slope, 0.0, -1.0])))
    return n, np.ones((size, size), bool), z


def persp_tear(size: int = 96, slope: float = 0.6, f: float = 120.0):
    """``ortho_tear`` seen by a perspective camera: plane A z = 2 m; below the cliff and right of
    column 30 a plane B through A's line X = X₀ with ∂z/∂X = slope (ray-cast depths)."""
    K = _intrinsics(size, f)
    r = _rays(K, size)
    uu, vv = _grid(size)
    x0 = 2.0 * r[0, 30, 0]
    z_b = (2.0 - slope * x0) / (1.0 - slope * r[..., 0])
    in_b = (vv >= size // 2) & (uu >= 30)
    z = np.where(in_b, z_b, 2.0)
    n = np.where(in_b[..., None], _unit(np.array([slope, 0.0, -1.0])), np.array([0.0, 0.0, -1.0]))
    return n, np.ones((size, size), bool), z, K


@pytest.mark.parametrize(("case", "ratio"), [("tear", 0.1), ("occlusion", 0.4)])
def test_bilateral_preserves_orthographic_discontinuities(case: str, ratio: float) -> None:
    # Measured (96², defaults): tear smooth 0.199 / bilateral 0.0054; occlusion 0.129 / 0.036.
    n, mask, z = ortho_tear() if case == "tear" else ortho_occlusion()
    smooth = _rmse_offset(integrate_normals(n, mask, camera=_ortho(n), method="smooth"), z, mask)
    bilateral = _rmse_offset(integrate_normals(n, mask, camera=_ortho(n), method="bilateral"), z, mask)
    assert smooth > 0.1, f"{case}: smooth integration should smear the cliff (error {smooth:.4f})"
    assert bilateral < ratio * smooth, f"{case}: bilateral {bilateral:.4f} vs smooth {smooth:.4f}"


def test_bilateral_warm_start_from_its_own_result_converges_at_once() -> None:
    n, mask, z = ortho_tear()
    first, again = IntegrationReport(), IntegrationReport()
    depth = integrate_normals(n, mask, camera=_ortho(n), method="bilateral", report=first)
    redo = integrate_normals(n, mask, camera=_ortho(n), method="bilateral", depth_init=depth, report=again)
    assert first.iterations > 5 and again.iterations < first.iterations / 3
    assert first.solver == "direct" and first.cg_steps == 0 and first.pixels == mask.size
    np.testing.assert_allclose(redo, depth, atol=0.01 * np.ptp(z))


def test_bilateral_preserves_perspective_discontinuity() -> None:
    n, mask, z, K = persp_tear()
    smooth = _rmse_scale(integrate_normals(n, mask, camera=_persp(K, n.shape[0])), z, mask)
    bilateral = _rmse_scale(integrate_normals(n, mask, camera=_persp(K, n.shape[0]), method="bilateral"), z, mask)
    # Measured: smooth 0.177, bilateral 0.0049.
    assert smooth > 0.1
    assert bilateral < 0.1 * smooth, f"bilateral {bilateral:.4f} vs smooth {smooth:.4f}"


def test_normals_that_do_not_encode_a_step_cannot_recover_it() -> None:
    # Two fronto-parallel plateaus at different heights have identical normals (0, 0, −1): the step
    # is invisible to any integrator (documented limit), and both methods return one flat plane.
    n = np.zeros((32, 32, 3))
    n[..., 2] = -1.0
    for method in ("smooth", "bilateral"):
        depth = integrate_normals(n, None, camera=_ortho(n), method=method)
        assert np.ptp(depth) < 1e-9


# ---- validation ----------------------------------------------------------------------------------------


def _plane(size: int = 8) -> tuple[Arr, NDArray[np.bool_]]:
    n, mask, _ = ortho_plane(np.ones((size, size), bool))
    return n, mask


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda n, m: (n[..., :2], m), r"shape \(H, W, 3\)"),
        (lambda n, m: (n, m[:-1]), "mask must have shape"),
        (lambda n, m: (n, np.zeros_like(m)), "mask is empty"),
        (lambda n, m: (n * 1.1, m), "unit vectors"),
        (lambda n, m: (np.where(np.eye(8, dtype=bool)[..., None], np.nan, n), m), "NaN"),
        (lambda n, m: (-n, m), "face away from the camera"),
    ],
)
def test_bad_inputs_raise_clear_errors(mutate, message: str) -> None:
    n, mask = mutate(*_plane())
    with pytest.raises(ValueError, match=message):
        integrate_normals(n, mask, camera=_ortho(n))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"camera": OrthographicCamera(4, 4, even=False)}, "the camera's grid"),
        ({"camera": PerspectiveCamera(8, 6, 10.0, 10.0, 4.0, 3.0)}, "the camera's grid"),
        ({"camera": np.eye(3)}, "camera must be"),
        ({"method": "poisson"}, "method must be"),
        ({"solver": "magic"}, "solver must be"),
        ({"reference_depth": -1.0}, "reference_depth"),
        ({"depth_init": np.zeros((3, 3))}, "depth_init must have shape"),
        ({"k": 0.0}, "bilateral options"),
    ],
)
def test_bad_options_raise_clear_errors(kwargs: dict, message: str) -> None:
    n, mask = _plane()
    with pytest.raises(ValueError, match=message):
        integrate_normals(n, mask, **{"camera": _ortho(n), **kwargs})


def test_grazing_normals_are_capped_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    n, mask = _plane()
    n[0, 0] = (1.0, 0.0, 0.0)  # grazing: infinite slope
    with caplog.at_level(logging.WARNING, logger="polarshape.surface.integrate"):
        depth = integrate_normals(n, mask, camera=_ortho(n))
    assert np.all(np.isfinite(depth))
    assert "grazing" in caplog.text


def test_a_few_near_grazing_outliers_do_not_wreck_the_depth() -> None:
    """Four wrong, nearly grazing normals (n_z = −0.002: slope 500) inside a sphere: with the default
    cap (n·r̂ ≤ −0.05: slope ≤ 20) the depth stays close to the truth; with a cap at 0.001 they
    dominate the least-squares integration."""
    from polarshape.surface.integrate import GRAZING_EPS

    n, mask, z = ortho_sphere(_circle(), (63.5, 63.5), 0.45)
    bad = n.copy()
    for r, c in ((40, 50), (41, 50), (80, 70), (64, 90)):
        bad[r, c] = _unit(np.array([1.0, 0.3, -0.002]))
    clean = _rmse_offset(integrate_normals(n, mask, camera=_ortho(n, PIXEL)), z, mask)
    capped = _rmse_offset(integrate_normals(bad, mask, camera=_ortho(bad, PIXEL)), z, mask)
    loose = _rmse_offset(integrate_normals(bad, mask, camera=_ortho(bad, PIXEL), grazing_eps=1e-3), z, mask)
    assert GRAZING_EPS == 0.05
    # measured: 0.014 %, 1.1 % and 28 % of the depth range
    assert capped < 0.02 and loose > 10 * capped, (clean, capped, loose)
    # a true sphere's own limb normals are not changed by the cap (none tilts beyond 87° here)
    assert clean < 0.005, clean
