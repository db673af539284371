"""Tests of polarshape.imaging.demosaic: exactness, the rotating-polariser convention check, edges,
and the layout convention on independent data (Mitsuba sphere)."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from polarshape.errors import ShapeError
from polarshape.imaging.demosaic import DEMOSAIC_METHODS, block_mean_bilinear_stokes, intensities_from_mosaic, stokes_from_mosaic
from polarshape.imaging.mosaic import MosaicLayout, channel_angles_rad, mosaic_from_stokes
from polarshape.imaging.stokes import aolp, dolp, intensities_from_stokes

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"
PERMUTATIONS = list(itertools.permutations((0.0, 45.0, 90.0, 135.0)))


def _angle_diff(a: torch.Tensor, b: float | torch.Tensor) -> torch.Tensor:
    """|a − b| modulo π, in [0, π/2]."""
    return (torch.remainder(a - b + math.pi / 2, math.pi) - math.pi / 2).abs()


@pytest.mark.parametrize("method", DEMOSAIC_METHODS)
def test_exact_on_constant_stokes_every_layout_and_offset(method: str) -> None:
    s = torch.tensor([0.8, 0.25, -0.3], dtype=torch.float64).view(3, 1, 1)
    # All 24 layouts through the counter-clockwise reading (negation permutes the set), and both
    # readings of a few maker blocks.
    cases = [(p, "counterclockwise_on_screen") for p in PERMUTATIONS]
    cases += [(p, "clockwise_on_screen") for p in PERMUTATIONS[::6]]
    for perm, angles in cases:
        maker = ((perm[0], perm[1]), (perm[2], perm[3]))
        sensor_layout = MosaicLayout.from_maker(maker, angles)  # type: ignore[arg-type]
        sensor = mosaic_from_stokes(s.expand(3, 6, 7), sensor_layout)  # (12, 14)
        for ox, oy in itertools.product((0, 1), (0, 1)):
            roi = sensor[oy : oy + 10, ox : ox + 12]
            out = stokes_from_mosaic(roi, sensor_layout.shifted(ox, oy), method)  # type: ignore[arg-type]
            expected_hw = (5, 6) if method == "superpixel" else (10, 12)
            assert out.shape == (3, *expected_hw)
            torch.testing.assert_close(out, s.expand_as(out), rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", DEMOSAIC_METHODS)
@pytest.mark.parametrize("hw", [(1, 1), (1, 3), (3, 1)])
def test_exact_on_the_smallest_mosaics(method: str, hw: tuple[int, int]) -> None:
    s = torch.tensor([0.5, -0.1, 0.2], dtype=torch.float64).view(3, 1, 1)
    out = stokes_from_mosaic(mosaic_from_stokes(s.expand(3, *hw), MosaicLayout.imx250mzr()), method=method)  # type: ignore[arg-type]
    torch.testing.assert_close(out, s.expand_as(out), rtol=0, atol=1e-12)


@pytest.mark.parametrize("layout", [MosaicLayout.imx250mzr(), MosaicLayout(((0.0, 90.0), (45.0, 135.0)))])
def test_bilinear_is_normalised_tent_interpolation(layout: MosaicLayout) -> None:
    m = torch.rand(2, 6, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    tent = torch.tensor([0.5, 1.0, 0.5], dtype=torch.float64)
    kernel = (tent[:, None] * tent[None, :]).expand(4, 1, 3, 3)
    sites = torch.zeros(1, 4, 6, 8, dtype=torch.float64)
    for c in range(4):
        i, j = layout.site_of_channel(c)
        sites[0, c, i::2, j::2] = 1.0
    expected = F.conv2d(m[:, None] * sites, kernel, padding=1, groups=4) / F.conv2d(sites, kernel, padding=1, groups=4)
    torch.testing.assert_close(intensities_from_mosaic(m, layout, "bilinear"), expected)


def test_wrong_offset_is_not_exact() -> None:
    s = torch.tensor([0.8, 0.3, 0.0], dtype=torch.float64).view(3, 1, 1)
    layout = MosaicLayout.imx250mzr()
    roi = mosaic_from_stokes(s.expand(3, 4, 4), layout)[1:7, 0:6]  # cropped at an odd row
    out = stokes_from_mosaic(roi, layout, "superpixel")  # layout not shifted: wrong on purpose
    assert (out - s).abs().max() > 0.1


def _rotating_polariser_mosaic(phi_rad: float, maker: tuple[tuple[float, float], ...], angles: str) -> torch.Tensor:
    """Physically built (8, 8) mosaic of a fully polarised beam at φ (from x toward y-down) behind
    wire grids labelled ``maker``: Malus cos² of the angle between the beam and each filter axis."""
    sign = -1.0 if angles == "counterclockwise_on_screen" else 1.0
    m = torch.empty(8, 8, dtype=torch.float64)
    for i, j in itertools.product(range(2), range(2)):
        # Filter axis in image coordinates (x right, y down); counter-clockwise on screen = toward -y.
        a = math.radians(maker[i][j])
        axis = (math.cos(a), sign * math.sin(a))
        beam = (math.cos(phi_rad), math.sin(phi_rad))
        m[i::2, j::2] = 0.7 * (axis[0] * beam[0] + axis[1] * beam[1]) ** 2
    return m


@pytest.mark.parametrize("method", DEMOSAIC_METHODS)
@pytest.mark.parametrize("angles", ["counterclockwise_on_screen", "clockwise_on_screen"])
@pytest.mark.parametrize("maker", [((90.0, 45.0), (135.0, 0.0)), ((0.0, 45.0), (135.0, 90.0))])
def test_rotating_linear_polariser(method: str, angles: str, maker: tuple[tuple[float, float], ...]) -> None:
    layout = MosaicLayout.from_maker(maker, angles)  # type: ignore[arg-type]
    for deg in np.arange(0.0, 360.0, 15.0):
        phi = math.radians(float(deg))
        out = stokes_from_mosaic(_rotating_polariser_mosaic(phi, maker, angles), layout, method)  # type: ignore[arg-type]
        assert float(_angle_diff(aolp(out), phi).max()) < 1e-9, f"phi = {deg}°"
        torch.testing.assert_close(dolp(out), torch.ones_like(dolp(out)))
        torch.testing.assert_close(out[0], torch.full_like(out[0], 0.7))


def test_rotating_polariser_detects_a_wrong_direction() -> None:
    maker = ((90.0, 45.0), (135.0, 0.0))
    wrong = MosaicLayout.from_maker(maker, "clockwise_on_screen")
    out = stokes_from_mosaic(_rotating_polariser_mosaic(math.radians(30.0), maker, "counterclockwise_on_screen"), wrong)
    assert float(_angle_diff(aolp(out), math.radians(30.0)).min()) > math.radians(50)


def _step_scene(method: str, tau_rel: float = 0.03) -> torch.Tensor:
    """False DoLP at a vertical intensity step (s0 1 -> 0.2) under constant polarisation (ρ 0.2, 30°)."""
    w = 32
    x = torch.arange(w, dtype=torch.float64)
    s0 = torch.where(x < 15, 1.0, 0.2).view(1, w).expand(16, w)
    rho, phi = 0.2, math.radians(30)
    s = torch.stack([s0, s0 * rho * math.cos(2 * phi), s0 * rho * math.sin(2 * phi)])  # (3, 16, 32)
    layout = MosaicLayout.imx250mzr()
    # Each mosaic pixel takes its own site's channel from the full-resolution field.
    ints = intensities_from_stokes(s, channel_angles_rad(dtype=torch.float64))  # (4, 16, 32)
    mosaic = torch.empty(16, w, dtype=torch.float64)
    for c in range(4):
        i, j = layout.site_of_channel(c)
        mosaic[i::2, j::2] = ints[c, i::2, j::2]
    out = stokes_from_mosaic(mosaic, layout, method, tau_rel=tau_rel)  # type: ignore[arg-type]
    return (dolp(out) - rho).abs().max()


def test_edge_aware_removes_false_polarisation_at_intensity_edges() -> None:
    err_bilinear = float(_step_scene("bilinear"))
    err_edge_aware = float(_step_scene("edge_aware"))
    assert err_bilinear > 0.2  # per-channel interpolation invents strong polarisation at the step
    assert err_edge_aware < 0.02
    assert float(_step_scene("edge_aware", tau_rel=1e6)) > 0.1  # no edge weighting ≈ bilinear


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("method", DEMOSAIC_METHODS)
def test_shapes_dtype_device_batch(method: str, dtype: torch.dtype, device: str) -> None:
    m = torch.rand(2, 3, 8, 12, dtype=dtype, device=device)
    out = stokes_from_mosaic(m, method=method)  # type: ignore[arg-type]
    hw = (4, 6) if method == "superpixel" else (8, 12)
    assert out.shape == (2, 3, 3, *hw) and out.dtype == dtype and out.device.type == device
    assert torch.isfinite(out).all()
    ints = intensities_from_mosaic(m, method=method)  # type: ignore[arg-type]
    assert ints.shape == (2, 3, 4, *hw)
    # The batch is processed image by image.
    torch.testing.assert_close(stokes_from_mosaic(m[1, 2], method=method), out[1, 2])  # type: ignore[arg-type]


@pytest.mark.parametrize("method", DEMOSAIC_METHODS)
def test_differentiable(method: str) -> None:
    m = torch.rand(6, 8, dtype=torch.float64, requires_grad=True)
    stokes_from_mosaic(m, method=method).sum().backward()  # type: ignore[arg-type]
    assert m.grad is not None and torch.isfinite(m.grad).all()


def test_zero_mosaic_is_finite() -> None:
    out = stokes_from_mosaic(torch.zeros(4, 6), method="edge_aware")
    assert torch.equal(out, torch.zeros_like(out))


def test_invalid_inputs() -> None:
    with pytest.raises(ValueError, match="method must be one of"):
        stokes_from_mosaic(torch.zeros(4, 4), method="bicubic")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="counts_to_float"):
        stokes_from_mosaic(torch.zeros(4, 4, dtype=torch.int32))
    with pytest.raises(ShapeError, match="even"):
        stokes_from_mosaic(torch.zeros(4, 5), method="bilinear")
    with pytest.raises(ValueError, match="tau_rel"):
        stokes_from_mosaic(torch.zeros(4, 4), method="edge_aware", tau_rel=0.0)
    with pytest.raises(TypeError, match="MosaicLayout"):
        stokes_from_mosaic(torch.zeros(4, 4), [[90, 45], [135, 0]])  # type: ignore[arg-type]


def test_mitsuba_sphere_aolp_follows_normal_azimuth() -> None:
    """Independent renderer (Mitsuba 3, maker layout [[90, 45], [135, 0]] counter-clockwise on
    screen): the AoLP must be parallel (diffuse) or perpendicular (specular) to the azimuth
    atan2(n_y, n_x) of the true normals, and the opposite angle direction must not be."""
    folder = SHARED / "data" / "mitsuba_sphere_a020"
    if not (folder / "capture.yaml").is_file():
        pytest.skip(f"shared data not found at {folder}")
    from polarshape.imaging.pixels import counts_to_float
    from polarshape.io.capture import load_capture

    capture = load_capture(folder)
    m = counts_to_float(capture.frames, capture.bit_depth, dtype=torch.float64)  # (K, 512, 512)
    n = torch.from_numpy(capture.ground_truth["normals"]).double()  # (256, 256, 3)
    azimuth = torch.atan2(n[..., 1], n[..., 0])
    on_sphere = torch.from_numpy(capture.mask) & torch.isfinite(azimuth)
    fractions = {}
    for name, layout in (
        ("ours", capture.layout),
        ("flipped", MosaicLayout.from_maker(capture.spec.camera.mosaic.layout, "clockwise_on_screen")),
    ):
        s = stokes_from_mosaic(m, layout, "superpixel").sum(0)  # all lights: (3, 256, 256)
        sel = on_sphere & (dolp(s) > 0.02)
        d = _angle_diff(aolp(s), azimuth)[sel].rad2deg()
        fractions[name] = float(((d < 10) | (d > 80)).double().mean())
    assert capture.layout == MosaicLayout.imx250mzr()
    assert fractions["ours"] > 0.85, fractions
    assert fractions["flipped"] < 0.4, fractions


@pytest.mark.parametrize(("dx", "dy"), [(0, 0), (1, 0), (0, 1), (1, 1)])
def test_block_mean_bilinear_equals_the_pooled_full_resolution_estimate(dx: int, dy: int) -> None:
    from polarshape.imaging.mosaic import MosaicLayout

    layout = MosaicLayout.imx250mzr().shifted(dx, dy)
    m = torch.rand(2, 3, 10, 14, dtype=torch.float64, generator=torch.Generator().manual_seed(dx + 2 * dy))
    pooled = F.avg_pool2d(stokes_from_mosaic(m, layout, "bilinear").reshape(-1, 10, 14), 2).reshape(2, 3, 3, 5, 7)
    assert torch.allclose(block_mean_bilinear_stokes(m, layout), pooled, atol=1e-14)


def test_block_mean_bilinear_sites_is_exact_on_counts_in_float32() -> None:
    """Weights in 1/16: 12-bit counts give the float64 result exactly in float32 (preprocessing relies on it)."""
    from polarshape.imaging.demosaic import block_mean_bilinear_sites
    from polarshape.imaging.mosaic import MosaicLayout, split_mosaic

    layout = MosaicLayout.imx250mzr().shifted(1, 0)
    counts = torch.randint(0, 4096, (12, 16), generator=torch.Generator().manual_seed(2)).double()
    sites = split_mosaic(counts, layout).float().contiguous()
    result = block_mean_bilinear_sites(sites, layout)
    reference = block_mean_bilinear_sites(split_mosaic(counts, layout), layout)
    assert torch.equal(result.double(), reference)
    assert block_mean_bilinear_sites(sites, layout, inplace=True) is sites and torch.equal(sites, result)
