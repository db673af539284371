"""Shading and the sensor: Stokes per pixel, the sensor-plane angle rule, the polariser mosaic."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from polarshape.brdf.geometry import sensor_plane_stokes, stokes_frame
from polarshape.cameras import OrthographicCamera, PerspectiveCamera
from polarshape.imaging.mosaic import MosaicLayout, mosaic_from_stokes, split_mosaic
from polarshape.io.capture import load_capture
from polarshape.lights import DirectionalLight, PointLight
from polarshape.scene.render import (
    albedo_scale_map,
    mosaic_radiance,
    polariser_angle_map,
    render_mosaics,
    shade_stokes,
)
from polarshape.scene.geometry import PlaneShape, SphereShape
from polarshape.scene.materials import BaekMaterial, FMBRDFMaterial, LambertianMaterial
from polarshape.scene.objects import Scene, SceneObject
from polarshape.scene.textures import AlbedoTexture

F64 = torch.float64
SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"


@pytest.fixture(scope="module")
def fmbrdf() -> FMBRDFMaterial:
    return FMBRDFMaterial(ior=1.6, k_s=1.0, k_b=0.4, alpha=0.35, beta=2.0, kappa=0.0)


def _superpixel_stokes(mosaic: torch.Tensor, layout: MosaicLayout) -> torch.Tensor:
    """The formula of the brief / spec §1 on the four channel images (0°, 45°, 90°, 135°)."""
    i0, i45, i90, i135 = split_mosaic(mosaic, layout).unbind(-3)
    return torch.stack([0.5 * (i0 + i45 + i90 + i135), i0 - i90, i45 - i135], dim=-3)


def _angle_rule(stokes: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
    """Spec §1 written with angles: e = cos φ e_x + sin φ e_y is seen at atan2(e·ŷ, e·x̂)."""
    s0, s1, s2 = stokes.unbind(-3)
    e_x, e_y = stokes_frame(view)
    phi = 0.5 * torch.atan2(s2, s1)
    e = torch.cos(phi)[..., None] * e_x + torch.sin(phi)[..., None] * e_y
    seen = torch.atan2(e[..., 1], e[..., 0])
    lin = torch.sqrt(s1**2 + s2**2)
    return torch.stack([s0, lin * torch.cos(2 * seen), lin * torch.sin(2 * seen)], dim=-3)


@pytest.mark.parametrize(
    "layout",
    [
        MosaicLayout.imx250mzr(),
        MosaicLayout.from_maker([[90, 45], [135, 0]], "clockwise_on_screen"),
        MosaicLayout.imx250mzr().shifted(1, 0),
    ],
    ids=["imx250mzr", "clockwise", "shifted"],
)
def test_flat_plane_mosaic_inverts_to_the_rendered_stokes(fmbrdf, layout):
    cam = OrthographicCamera(16, 12, 1e-3)
    plane = PlaneShape((0.0, 0.0, 0.5), (0.606, 0.35, -1.0))  # tilted 35° toward azimuth 30°
    # light near the mirror direction of V: a strong, polarised specular lobe at an oblique AoLP
    scene = Scene(cam, (SceneObject(plane, fmbrdf),), (DirectionalLight((0.78, 0.50, -0.37), 1.3),))
    geometry = scene.rasterize()
    stokes = shade_stokes(scene, geometry, scene.lights[0])  # (3, H, W), identical in every pixel
    assert torch.allclose(stokes, stokes[:, :1, :1].expand_as(stokes), rtol=1e-12, atol=0)
    s = stokes[:, 0, 0]
    assert abs(s[1].item()) / s[0].item() > 0.03 and abs(s[2].item()) / s[0].item() > 0.03  # both angles tested
    mosaic = render_mosaics(scene, layout, geometry=geometry)[0]  # (H, W)
    recovered = _superpixel_stokes(mosaic, layout)  # (3, H/2, W/2)
    assert torch.allclose(recovered, s[:, None, None].expand_as(recovered), rtol=1e-12, atol=1e-15)
    # and it agrees with imaging's mosaic of the same Stokes field
    assert torch.allclose(mosaic, mosaic_from_stokes(stokes[:, ::2, ::2], layout), rtol=1e-12, atol=1e-15)


def test_polariser_angle_map_repeats_the_layout():
    layout = MosaicLayout.imx250mzr()  # ours: [[90, 135], [45, 0]]
    angles = polariser_angle_map(layout, 4, 6)
    assert torch.allclose(torch.rad2deg(angles[:2, :2]), torch.tensor([[90.0, 135.0], [45.0, 0.0]], dtype=F64))
    assert torch.equal(angles[2:, 4:], angles[:2, :2])
    with pytest.raises(ValueError, match="even"):
        polariser_angle_map(layout, 3, 4)


def test_mosaic_radiance_is_malus():
    s = torch.tensor([2.0, 0.6, -0.4], dtype=F64)[:, None, None].expand(3, 2, 2)
    theta = torch.tensor([[0.0, math.pi / 4], [math.pi / 2, 3 * math.pi / 4]], dtype=F64)
    assert torch.allclose(mosaic_radiance(s, theta), torch.tensor([[1.3, 0.8], [0.7, 1.2]], dtype=F64))


def test_sensor_plane_rule_matches_the_angle_form():
    g = torch.Generator().manual_seed(0)
    rays = torch.randn(20, 30, 3, generator=g, dtype=F64) * torch.tensor([0.3, 0.3, 1.0], dtype=F64)
    view = -torch.nn.functional.normalize(rays + torch.tensor([0, 0, 1.0], dtype=F64), dim=-1)  # up to ≈30° off-axis
    s0 = torch.rand(20, 30, generator=g, dtype=F64) + 0.5
    rho = torch.rand(20, 30, generator=g, dtype=F64)
    phi = (torch.rand(20, 30, generator=g, dtype=F64) - 0.5) * math.pi
    stokes = torch.stack([s0, s0 * rho * torch.cos(2 * phi), s0 * rho * torch.sin(2 * phi)])
    out = sensor_plane_stokes(stokes, view)
    assert torch.allclose(out, _angle_rule(stokes, view), atol=1e-12)
    assert torch.allclose(out[0], s0) and torch.allclose(out[1:].norm(dim=0), stokes[1:].norm(dim=0))
    assert not torch.allclose(out, stokes, atol=1e-3)  # off-axis the angle does change
    # orthographic / on-axis: unchanged; unpolarised: unchanged
    on_axis = torch.tensor([0.0, 0.0, -1.0], dtype=F64).expand(20, 30, 3)
    assert torch.allclose(sensor_plane_stokes(stokes, on_axis), stokes, atol=1e-15)
    flat = torch.stack([s0, torch.zeros_like(s0), torch.zeros_like(s0)])
    assert torch.equal(sensor_plane_stokes(flat, view), flat)


def test_sensor_plane_angle_shift_is_about_three_degrees_at_19_degrees_off_axis():
    a = math.radians(19.0)
    ray = torch.tensor([math.sin(a) / math.sqrt(2), math.sin(a) / math.sqrt(2), math.cos(a)], dtype=F64)
    phi = torch.linspace(-math.pi / 2, math.pi / 2, 721, dtype=F64)
    stokes = torch.stack([torch.ones_like(phi), torch.cos(2 * phi), torch.sin(2 * phi)])[:, None, :]  # (3, 1, N)
    out = sensor_plane_stokes(stokes, (-ray).expand(1, 721, 3))
    seen = 0.5 * torch.atan2(out[2], out[1])
    shift = torch.remainder(seen - phi + math.pi / 2, math.pi) - math.pi / 2
    assert 2.5 < math.degrees(shift.abs().max()) < 3.5  # spec §1: "≈3° at 19° off-axis"


class _ConstantStokes:
    """Stand-in material: the same Stokes vector in every pixel's own frame (isolates the rule)."""

    def stokes(self, normal, light, view, albedo_scale):
        return torch.tensor([1.0, 0.3, -0.2], dtype=normal.dtype).expand(normal.shape[0], 3)


@pytest.mark.parametrize("material", ["fmbrdf", "constant"])
def test_perspective_render_follows_the_sensor_plane_rule(fmbrdf, material):
    layout = MosaicLayout.imx250mzr()
    # ±19° / ±15° field of view; the finer grid only where the AoLP of super-pixels is compared
    scale = 1 if material == "fmbrdf" else 4
    h, w = 48 * scale, 64 * scale
    cam = PerspectiveCamera(w, h, fx=90.0 * scale, fy=90.0 * scale, cx=(w - 1) / 2, cy=(h - 1) / 2)
    plane = PlaneShape((0.0, 0.0, 1.0), (0.0, 0.7, -1.0))  # tilted 35°, lit near the mirror direction
    mat = fmbrdf if material == "fmbrdf" else _ConstantStokes()
    scene = Scene(cam, (SceneObject(plane, mat),), (DirectionalLight((0.05, 0.93, -0.36)),))
    geometry = scene.rasterize()
    stokes = shade_stokes(scene, geometry, scene.lights[0])  # per-pixel frames
    mosaic = render_mosaics(scene, layout, geometry=geometry)[0]
    expected = mosaic_radiance(_angle_rule(stokes, geometry.view), polariser_angle_map(layout, h, w))
    assert torch.allclose(mosaic, expected, rtol=1e-10, atol=1e-14)
    if material == "fmbrdf":
        return
    # a field that is constant in the per-pixel frames: the super-pixel AoLP follows the
    # sensor-plane angle (up to the tiny view change across a block), not the per-pixel one
    recovered = _superpixel_stokes(mosaic, layout)
    rule = _angle_rule(stokes, geometry.view)[:, ::2, ::2]
    aolp = lambda s: 0.5 * torch.atan2(s[2], s[1])  # noqa: E731
    wrap = lambda d: torch.remainder(d + math.pi / 2, math.pi) - math.pi / 2  # noqa: E731
    err_rule = wrap(aolp(recovered) - aolp(rule)).abs()
    err_frame = wrap(aolp(recovered) - aolp(stokes[:, ::2, ::2])).abs()
    assert math.degrees(err_rule.max()) < 0.05
    assert math.degrees(err_frame.max()) > 1.5  # ≈2–3° toward the corners
    assert math.degrees(err_frame[47:49, 63:65].max()) < 0.05  # ≈0 on the optical axis


def test_cast_shadow_darkens_and_can_be_switched_off():
    cam = OrthographicCamera(32, 32, 2e-3)
    mat = LambertianMaterial(0.5)
    sphere = SceneObject(SphereShape((0.0, 0.0, 0.3), 0.01), mat)
    floor = SceneObject(PlaneShape((0.0, 0.0, 0.33), (0.0, 0.0, -1.0)), mat, in_mask=False)
    scene = Scene(cam, (sphere, floor), (DirectionalLight((0.5, 0.0, -1.0)),))
    g = scene.rasterize()
    lit = shade_stokes(scene, g, scene.lights[0], shadows=False)
    shaded = shade_stokes(scene, g, scene.lights[0])
    dark = (shaded[0] == 0) & (lit[0] > 0)
    assert dark.any() and torch.all(g.object_index[dark] == 1)
    assert torch.equal(shaded[:, ~dark], lit[:, ~dark])
    assert torch.equal(scene.object_mask(g), g.object_index == 0)


def test_texture_scales_the_diffuse_albedo_and_point_lights_fall_off():
    cam = OrthographicCamera(32, 32, 1e-3)
    tex = AlbedoTexture("stripes", "planar", (0.0, 0.0, 0.5), cells=2.0, low=0.25, high=1.0, size_m=0.032)
    obj = SceneObject(PlaneShape((0.0, 0.0, 0.5), (0.0, 0.0, -1.0)), LambertianMaterial(0.8), tex)
    near = PointLight((0.0, 0.0, 0.4), 0.02)
    scene = Scene(cam, (obj,), (near, PointLight((0.0, 0.0, 0.3), 0.02)))
    g = scene.rasterize()
    scale = albedo_scale_map(scene, g)
    assert set(scale.unique().tolist()) == {0.25, 1.0}
    s_near = shade_stokes(scene, g, scene.lights[0])
    s_far = shade_stokes(scene, g, scene.lights[1])
    # pixels (15, 15) and (15, 16) straddle x = 0: one on each stripe
    for v, u in [(15, 15), (15, 16), (3, 28)]:
        r = math.dist(g.points[v, u].tolist(), [0.0, 0.0, 0.4])
        cos_l, irradiance = 0.1 / r, 0.02 / r**2  # N = (0, 0, −1), the lamp 0.1 m in front
        expect = 0.8 * scale[v, u].item() / math.pi * cos_l * irradiance
        assert s_near[0, v, u].item() == pytest.approx(expect, rel=1e-9)
    ratio = s_near[0][g.mask] / s_far[0][g.mask]
    assert ratio[0].item() > 3.5  # 1/r²: r = 0.1 vs 0.2 (and a little cosine)
    assert torch.all(s_near[1:] == 0)  # Lambertian is unpolarised


def test_matches_an_independent_renderer_on_the_shared_mitsuba_sphere():
    """Conventions end to end (mosaic layout, angle direction, Stokes frame, light directions)
    against Mitsuba 3's polarised renderer (``pplastic`` = Baek et al., Beckmann α = 0.2)."""
    folder = SHARED / "data" / "mitsuba_sphere_a020"
    if not folder.is_dir():
        pytest.skip(f"shared data not found at {folder}")
    capture = load_capture(folder)
    # a 128×128 crop toward the left limb (strong diffuse polarisation); even offsets keep the layout
    y0, x0, size = 192, 48, 128
    cam = OrthographicCamera(size, size, 2.3 / 512, cx=255.5 - x0, cy=255.5 - y0)  # Mitsuba: 2.3 units over 512 px
    pplastic = BaekMaterial(ior=1.5, k_s=1.0, k_d=0.3, alpha=0.2, distribution="beckmann")
    sphere = SceneObject(SphereShape((0.0, 0.0, 5.0), 1.0), pplastic)
    picked = (0, 10)
    lights = tuple(DirectionalLight(capture.spec.lights[k].direction, capture.spec.lights[k].intensity) for k in picked)
    ours = render_mosaics(Scene(cam, (sphere,), lights), capture.layout)
    mask = torch.as_tensor(capture.mask)[y0 // 2 : (y0 + size) // 2, x0 // 2 : (x0 + size) // 2]
    scales = []
    for k, light_index in enumerate(picked):
        crop = capture.frames[light_index, y0 : y0 + size, x0 : x0 + size].astype(np.float64)
        theirs = _superpixel_stokes(torch.as_tensor(crop), capture.layout)
        mine = _superpixel_stokes(ours[k], capture.layout)
        sel = mask & (theirs[0] > 200) & (mine[0] > 0)
        assert sel.sum() > 2000
        scale = (theirs[0][sel] / mine[0][sel]).median()
        scales.append(scale.item())
        assert ((theirs[0][sel] - scale * mine[0][sel]).abs() / theirs[0][sel]).median() < 0.02
        aolp_theirs = 0.5 * torch.atan2(theirs[2], theirs[1])
        aolp_mine = 0.5 * torch.atan2(mine[2], mine[1])
        polarised = sel & (mine[1:].norm(dim=0) / mine[0] > 0.1)
        assert polarised.sum() > 300
        wrap = lambda d: (torch.remainder(d + math.pi / 2, math.pi) - math.pi / 2).abs()  # noqa: E731
        err = math.degrees(wrap(aolp_theirs - aolp_mine)[polarised].median())
        mirrored = math.degrees(wrap(aolp_theirs + aolp_mine)[polarised].median())  # the other angle direction
        assert err < 4.0 and mirrored > 2 * err, (err, mirrored)
    assert scales[0] == pytest.approx(scales[1], rel=5e-3)  # one exposure for all lights: intensities agree
