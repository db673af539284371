"""Tests of polarshape.imaging.colour: the colour polarisation sensor's block grid, forward model and demosaic."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from polarshape.errors import ShapeError
from polarshape.imaging import (
    BAYER_PATTERNS,
    MosaicLayout,
    block_colours,
    colour_mosaic_from_stokes,
    colour_stokes_from_mosaic,
    pixel_colours,
    stokes_from_mosaic,
)
from polarshape.imaging.colour import select_block_colour, shifted_bayer

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
IMX = MosaicLayout.imx250mzr()
LAYOUTS = [IMX, MosaicLayout(((0.0, 45.0), (135.0, 90.0))), MosaicLayout(((45.0, 90.0), (0.0, 135.0)))]


def _colour_field(h: int, w: int, dtype: torch.dtype = torch.float64, seed: int = 0) -> torch.Tensor:
    """(3, 3, H, W) random per-colour Stokes with DoLP < 1."""
    g = torch.Generator().manual_seed(seed)
    s0 = 0.2 + torch.rand(3, 1, h, w, generator=g, dtype=dtype)
    lin = 0.5 * s0 * (2 * torch.rand(3, 2, h, w, generator=g, dtype=dtype) - 1)
    return torch.cat([s0, lin], dim=1)


def test_block_and_pixel_colours_rggb() -> None:
    assert block_colours("RGGB", 2, 2).tolist() == [[0, 1], [1, 2]]
    assert block_colours("BGGR", 2, 2).tolist() == [[2, 1], [1, 0]]
    assert block_colours("GRBG", 2, 2).tolist() == [[1, 0], [2, 1]]
    assert block_colours("GBRG", 2, 2).tolist() == [[1, 2], [0, 1]]
    px = pixel_colours("RGGB", 8, 8)
    assert px.shape == (8, 8)
    # every 2×2 polariser block is one colour; the 4×4 super-block repeats
    assert torch.equal(px[0::2, 0::2], px[1::2, 1::2]) and torch.equal(px[:4, :4], px[4:, 4:])
    assert px[:4, :4].flatten().bincount().tolist() == [4, 8, 4]


@pytest.mark.parametrize("bayer", BAYER_PATTERNS)
def test_shifted_bayer_matches_cropped_grid(bayer: str) -> None:
    grid = block_colours(bayer, 8, 8)
    for ox, oy in itertools.product((0, 2, 4, 6), repeat=2):
        shifted = block_colours(shifted_bayer(bayer, ox, oy), 4, 4)
        assert torch.equal(shifted, grid[oy // 2 : oy // 2 + 4, ox // 2 : ox // 2 + 4])


def test_shifted_bayer_refuses_odd_offsets() -> None:
    with pytest.raises(ValueError, match="even"):
        shifted_bayer("RGGB", 1, 0)


@pytest.mark.parametrize("bayer", BAYER_PATTERNS)
@pytest.mark.parametrize("layout", LAYOUTS, ids=str)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exact_on_constant_per_colour_stokes(bayer: str, layout: MosaicLayout, dtype: torch.dtype) -> None:
    s = torch.tensor([[0.9, 0.2, -0.1], [0.5, -0.05, 0.1], [0.3, 0.0, 0.06]], dtype=dtype)  # (colour, Stokes)
    field = s[:, :, None, None].expand(2, 3, 3, 5, 7)  # batch of 2, odd block counts
    mosaic = colour_mosaic_from_stokes(field, layout, bayer)
    assert mosaic.shape == (2, 10, 14) and mosaic.dtype == dtype
    out = colour_stokes_from_mosaic(mosaic, layout, bayer)
    assert out.shape == (2, 3, 3, 5, 7) and out.dtype == dtype
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(out, field, atol=tol, rtol=0)


@pytest.mark.parametrize("bayer", BAYER_PATTERNS)
def test_measured_colour_is_the_plain_superpixel_estimate(bayer: str) -> None:
    mosaic = torch.rand(3, 12, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = colour_stokes_from_mosaic(mosaic, IMX, bayer)  # (3, 3, 3, 6, 8)
    own = stokes_from_mosaic(mosaic, IMX, "superpixel")  # (3, 3, 6, 8)
    index = block_colours(bayer, 6, 8)
    picked = out.gather(-4, index.expand(3, 1, 3, 6, 8)).squeeze(-4)  # each block's own colour
    torch.testing.assert_close(picked, own, atol=0, rtol=0)


def test_interior_interpolation_is_textbook_bilinear() -> None:
    field = _colour_field(6, 6)
    mosaic = colour_mosaic_from_stokes(field, IMX, "RGGB")
    out = colour_stokes_from_mosaic(mosaic, IMX, "RGGB")
    r, g, b = 0, 1, 2
    # RGGB blocks: R at (even, even), G at (even, odd) and (odd, even), B at (odd, odd).
    torch.testing.assert_close(out[r, :, 2, 3], 0.5 * (field[r, :, 2, 2] + field[r, :, 2, 4]))  # R on an R row
    torch.testing.assert_close(out[r, :, 3, 2], 0.5 * (field[r, :, 2, 2] + field[r, :, 4, 2]))  # R on an R column
    diag = field[r, :, 2, 2] + field[r, :, 2, 4] + field[r, :, 4, 2] + field[r, :, 4, 4]
    torch.testing.assert_close(out[r, :, 3, 3], 0.25 * diag)  # R at a B block
    cross = field[g, :, 1, 2] + field[g, :, 3, 2] + field[g, :, 2, 1] + field[g, :, 2, 3]
    torch.testing.assert_close(out[g, :, 2, 2], 0.25 * cross)  # G at an R block
    diag_b = field[b, :, 1, 1] + field[b, :, 1, 3] + field[b, :, 3, 1] + field[b, :, 3, 3]
    torch.testing.assert_close(out[b, :, 2, 2], 0.25 * diag_b)  # B at an R block


def test_linear_ramps_exact_in_the_interior() -> None:
    y, x = torch.meshgrid(torch.arange(8.0, dtype=torch.float64), torch.arange(10.0, dtype=torch.float64), indexing="ij")
    field = torch.stack([torch.stack([1 + 0.1 * c + 0.05 * y, 0.01 * x - 0.02 * y, 0.03 * x]) for c in range(3)])
    out = colour_stokes_from_mosaic(colour_mosaic_from_stokes(field, IMX, "GBRG"), IMX, "GBRG")
    torch.testing.assert_close(out[..., 1:-1, 1:-1], field[..., 1:-1, 1:-1], atol=1e-12, rtol=0)


@pytest.mark.parametrize("bayer", BAYER_PATTERNS)
@pytest.mark.parametrize("layout", LAYOUTS, ids=str)
def test_centre_sites_exact_for_fields_linear_in_the_pixel_position(bayer: str, layout: MosaicLayout) -> None:
    """Each pixel sees its own colour's Stokes at its own position (not its block's centre): the
    plain block estimate is off by half a pixel times the gradient, the centred one is exact in the
    interior (three blocks from the border: the border's one-sided interpolation reaches the gradient
    of the next block, which the second interpolation spreads one block further)."""
    h, w = 10, 12
    y, x = torch.meshgrid(torch.arange(2 * h, dtype=torch.float64), torch.arange(2 * w, dtype=torch.float64), indexing="ij")
    def field(yy: torch.Tensor, xx: torch.Tensor) -> torch.Tensor:  # (3 colours, 3, ...)
        return torch.stack([torch.stack([1 + 0.1 * c + 0.05 * yy - 0.03 * xx, 0.02 * xx - 0.01 * c * yy,
                                         0.015 * yy + 0.01 * xx]) for c in range(3)])
    per_pixel = field(y, x)  # (3, 3, 2H, 2W)
    colour = pixel_colours(bayer, 2 * h, 2 * w)  # (2H, 2W)
    own = per_pixel.gather(0, colour.expand(1, 3, 2 * h, 2 * w)).squeeze(0)  # (3, 2H, 2W)
    angle = torch.zeros(2 * h, 2 * w, dtype=torch.float64)
    for i in range(2):
        for j in range(2):
            angle[i::2, j::2] = math.radians(layout.angles_deg[i][j])
    mosaic = 0.5 * (own[0] + own[1] * torch.cos(2 * angle) + own[2] * torch.sin(2 * angle))
    cy, cx = torch.meshgrid(torch.arange(h, dtype=torch.float64) * 2 + 0.5, torch.arange(w, dtype=torch.float64) * 2 + 0.5,
                            indexing="ij")
    truth = field(cy, cx)[..., 3:-3, 3:-3]  # at the block centres
    centred = colour_stokes_from_mosaic(mosaic, layout, bayer, centre_sites=True)[..., 3:-3, 3:-3]
    torch.testing.assert_close(centred, truth, atol=1e-12, rtol=0)
    plain = colour_stokes_from_mosaic(mosaic, layout, bayer)[..., 3:-3, 3:-3]
    assert float((plain - truth).abs().max()) > 1e-3


@pytest.mark.parametrize("bayer", BAYER_PATTERNS)
def test_round_trip_through_the_sensor(bayer: str) -> None:
    field = _colour_field(6, 8)
    mosaic = colour_mosaic_from_stokes(field, IMX, bayer)
    again = colour_mosaic_from_stokes(colour_stokes_from_mosaic(mosaic, IMX, bayer), IMX, bayer)
    torch.testing.assert_close(again, mosaic, atol=1e-12, rtol=0)


def test_select_block_colour_keeps_each_blocks_own_colour() -> None:
    field = _colour_field(4, 4)
    picked = select_block_colour(field, "BGGR")
    assert torch.equal(picked[:, 0, 0], field[2, :, 0, 0]) and torch.equal(picked[:, 1, 1], field[0, :, 1, 1])
    assert torch.equal(picked[:, 0, 1], field[1, :, 0, 1])


@pytest.mark.parametrize("device", DEVICES)
def test_device_and_gradients(device: str) -> None:
    mosaic = torch.rand(8, 8, dtype=torch.float64, device=device, requires_grad=True)
    out = colour_stokes_from_mosaic(mosaic, IMX, "RGGB")
    assert out.device.type == device and torch.isfinite(out).all()
    assert torch.autograd.gradcheck(lambda m: colour_stokes_from_mosaic(m, IMX, "RGGB"), (mosaic,))


def test_float16_input_is_evaluated_in_float32() -> None:
    mosaic = colour_mosaic_from_stokes(_colour_field(4, 4, torch.float32), IMX, "RGGB").half()
    out = colour_stokes_from_mosaic(mosaic, IMX, "RGGB")
    assert out.dtype == torch.float16 and torch.isfinite(out).all()


def test_errors_name_the_problem() -> None:
    with pytest.raises(ValueError, match="bayer must be one of"):
        colour_stokes_from_mosaic(torch.rand(8, 8), IMX, "RGBG")
    with pytest.raises(ShapeError, match="H, W >= 2"):
        colour_stokes_from_mosaic(torch.rand(2, 8), IMX, "RGGB")
    with pytest.raises(ShapeError, match="even"):
        colour_stokes_from_mosaic(torch.rand(8, 7), IMX, "RGGB")
    with pytest.raises(TypeError, match="counts_to_float"):
        colour_stokes_from_mosaic(torch.zeros(8, 8, dtype=torch.uint16), IMX, "RGGB")
    with pytest.raises(TypeError, match="MosaicLayout"):
        colour_stokes_from_mosaic(torch.rand(8, 8), "imx250mzr", "RGGB")  # type: ignore[arg-type]
    with pytest.raises(ShapeError, match=r"\(\*, 3, 3, H, W\)"):
        colour_mosaic_from_stokes(torch.rand(3, 4, 4), IMX, "RGGB")
