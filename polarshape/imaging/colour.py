"""The colour polarisation sensor (Sony IMX250MYR, Lucid TRI050S-QC): Bayer over the 2×2 polariser blocks.

Each 2×2 polariser block (super-pixel; its four sites at 0/45/90/135°, the same
:class:`~polarshape.imaging.mosaic.MosaicLayout` as the mono IMX250MZR) sits behind ONE colour
filter, and the blocks form a Bayer pattern, so the sensor repeats a 4×4 super-block. For the
IMX250MYR the pattern is RGGB on the block grid: block (0, 0) red, (0, 1) and (1, 0) green,
(1, 1) blue (Sony's IMX250MYR flyer; Lucid names the raw formats ``PolarizedBayerRG*`` /
``BayerRGPolarized*``).

Grids: a raw mosaic is (2H, 2W) pixels; block (y, x) covers pixels (2y..2y+1, 2x..2x+1); the
Bayer pattern names the colours of blocks (0, 0), (0, 1), (1, 0), (1, 1) of the mosaic as stored
(for an ROI use :func:`shifted_bayer`). Colour indices are 0 R, 1 G, 2 B.

Example:
    >>> layout = MosaicLayout.imx250mzr()
    >>> stokes = torch.rand(3, 3, 4, 4)                     # (colour, Stokes, H, W)
    >>> mosaic = colour_mosaic_from_stokes(stokes, layout, "RGGB")   # (8, 8)
    >>> colour_stokes_from_mosaic(mosaic, layout, "RGGB").shape
    torch.Size([3, 3, 4, 4])
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.checks import check_dtype_floating, check_shape, format_shape
from polarshape.errors import ShapeError
from polarshape.imaging.mosaic import (
    MosaicLayout,
    channel_angles_rad,
    check_layout,
    check_mosaic_shape,
    mosaic_from_stokes,
    split_mosaic,
)
from polarshape.imaging.stokes import intensities_from_stokes, stokes_from_intensities

__all__ = [
    "BAYER_PATTERNS",
    "COLOUR_NAMES",
    "BayerPattern",
    "bayer_reach",
    "block_colours",
    "check_bayer",
    "colour_mosaic_from_stokes",
    "colour_stokes_from_mosaic",
    "pixel_colours",
    "select_block_colour",
    "shifted_bayer",
]

BayerPattern = Literal["RGGB", "BGGR", "GRBG", "GBRG"]
#: Bayer patterns of the block grid: colours of blocks (0, 0), (0, 1), (1, 0), (1, 1).
BAYER_PATTERNS: tuple[str, ...] = ("RGGB", "BGGR", "GRBG", "GBRG")
#: Colour channel names in index order (the colour axis of every colour tensor here).
COLOUR_NAMES: tuple[str, str, str] = ("R", "G", "B")

_COLOUR_INDEX = {"R": 0, "G": 1, "B": 2}

# Bilinear Bayer interpolation as a normalised convolution: with this tent kernel the samples of
# one colour weighted by it and divided by the summed weights of the samples present give, in
# the interior, the 2-neighbour (R/B on a G row or column), 4-diagonal (R at B, B at R) and
# 4-cross (G at R/B) means of the textbook bilinear demosaic, and at the borders the mean of the
# neighbours that exist; where the colour was measured the sample itself is kept.
_TENT = ((1.0, 2.0, 1.0), (2.0, 4.0, 2.0), (1.0, 2.0, 1.0))


def check_bayer(bayer: object) -> str:
    """Return ``bayer`` if it is one of :data:`BAYER_PATTERNS`, else raise a ValueError naming the fix."""
    if not isinstance(bayer, str) or bayer not in BAYER_PATTERNS:
        raise ValueError(
            f"bayer must be one of {BAYER_PATTERNS} (colours of the top-left 2×2 polariser blocks, "
            f"row by row; the IMX250MYR / TRI050S-QC is 'RGGB'); got {bayer!r}"
        )
    return bayer


def shifted_bayer(bayer: str, offset_x: int, offset_y: int) -> str:
    """The Bayer pattern seen in a region of interest whose top-left pixel is sensor pixel (offset_x, offset_y).

    Offsets are in raw pixels and must be even (an odd offset would cut the 2×2 polariser blocks
    across two colour filters); an offset of 2 (mod 4) moves the pattern by one block.

    Example:
        >>> shifted_bayer("RGGB", 2, 0), shifted_bayer("RGGB", 0, 2), shifted_bayer("RGGB", 2, 2)
        ('GRBG', 'GBRG', 'BGGR')
    """
    bayer = check_bayer(bayer)
    for name, v in (("offset_x", offset_x), ("offset_y", offset_y)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 0 or v % 2:
            raise ValueError(
                f"{name} must be a non-negative even integer (pixels) for a colour polarisation sensor: an odd "
                f"offset splits the 2×2 polariser blocks across colour filters; got {v!r}"
            )
    bx, by = (offset_x // 2) % 2, (offset_y // 2) % 2
    return "".join(bayer[2 * ((i + by) % 2) + (j + bx) % 2] for i in range(2) for j in range(2))


def block_colours(bayer: str, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """(H, W) int64 colour index (0 R, 1 G, 2 B) of every 2×2 polariser block (super-pixel).

    Example:
        >>> block_colours("RGGB", 2, 3)
        tensor([[0, 1, 0],
                [1, 2, 1]])
    """
    bayer = check_bayer(bayer)
    for name, v in (("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name} must be a positive integer (super-pixels); got {v!r}")
    tile = torch.tensor([[_COLOUR_INDEX[bayer[2 * i + j]] for j in range(2)] for i in range(2)], device=device)
    return tile.repeat((height + 1) // 2, (width + 1) // 2)[:height, :width]


def pixel_colours(bayer: str, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """(2H, 2W) int64 colour index of every raw pixel; ``height``, ``width`` are the raw sizes (even).

    Example:
        >>> pixel_colours("RGGB", 4, 4)
        tensor([[0, 0, 1, 1],
                [0, 0, 1, 1],
                [1, 1, 2, 2],
                [1, 1, 2, 2]])
    """
    for name, v in (("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 2 or v % 2:
            raise ValueError(f"{name} must be a positive even integer (raw pixels, whole 2×2 blocks); got {v!r}")
    blocks = block_colours(bayer, height // 2, width // 2, device)
    return blocks.repeat_interleave(2, dim=0).repeat_interleave(2, dim=1)


def _check_colour_stokes(stokes: object, name: str = "stokes") -> Tensor:
    stokes = check_dtype_floating(stokes, name)
    check_shape(stokes, ["*", "3", "3", "H", "W"], name, "(colour R, G, B; Stokes s0, s1, s2; H; W)")
    return stokes


def select_block_colour(stokes: Tensor, bayer: str) -> Tensor:
    """The Stokes vector of each block's own colour: what reaches that block's polarisers.

    Args:
        stokes: (*, 3, 3, H, W) per-colour Stokes at super-pixel resolution (colour R, G, B;
            s0, s1, s2; rows; columns).
        bayer: Bayer pattern of the block grid (:data:`BAYER_PATTERNS`).

    Returns:
        (*, 3, H, W) Stokes behind each block's colour filter, same dtype/device as ``stokes``.
    """
    stokes = _check_colour_stokes(stokes)
    h, w = stokes.shape[-2:]
    index = block_colours(bayer, h, w, stokes.device)  # (H, W)
    one_hot = F.one_hot(index, 3).permute(2, 0, 1).to(stokes.dtype)  # (3, H, W)
    return (stokes * one_hot[:, None]).sum(dim=-4)


def colour_mosaic_from_stokes(stokes: Tensor, layout: MosaicLayout, bayer: str) -> Tensor:
    """Raw mosaic an ideal colour polarisation sensor records from per-colour Stokes images.

    Forward model of :func:`colour_stokes_from_mosaic`: each block keeps its own colour
    (:func:`select_block_colour`), then ideal polarisers at the layout's angles
    (:func:`~polarshape.imaging.mosaic.mosaic_from_stokes`, spec §1).

    Args:
        stokes: (*, 3, 3, H, W) per-colour Stokes (colour R, G, B; s0, s1, s2; super-pixel rows; cols).
        layout: polariser layout of each 2×2 block (our convention).
        bayer: Bayer pattern of the block grid.

    Returns:
        (*, 2H, 2W) raw mosaic, same dtype/device as ``stokes``.
    """
    layout = check_layout(layout)
    return mosaic_from_stokes(select_block_colour(stokes, bayer), layout)


def bayer_reach(flags: Tensor, bayer: str) -> Tensor:
    """Which colour estimates of :func:`colour_stokes_from_mosaic` were interpolated from a flagged block.

    Args:
        flags: (*, H, W) bool blocks (e.g. dark: background or shadow, whose colour would be
            interpolated into their neighbours').
        bayer: Bayer pattern of the block grid.

    Returns:
        (*, 3, H, W) bool: colour c at block p came from a flagged neighbour of colour c (a block's
        own colour is measured, never interpolated: False).

    Example:
        >>> dark = torch.zeros(4, 4, dtype=torch.bool); dark[0, 0] = True   # a red block (RGGB)
        >>> bayer_reach(dark, "RGGB")[0, :2, :2]
        tensor([[False,  True],
                [ True,  True]])
    """
    bayer = check_bayer(bayer)
    *lead, h, w = flags.shape
    masks = F.one_hot(block_colours(bayer, h, w, flags.device), 3).permute(2, 0, 1).to(torch.float32)  # (3, H, W)
    flagged = masks * flags.reshape(-1, 1, h, w).to(torch.float32)  # (N, 3, H, W)
    reach = F.conv2d(flagged, torch.ones(3, 1, 3, 3, device=flags.device), padding=1, groups=3) > 0
    return (reach & ~masks.bool()).reshape(*lead, 3, h, w)


def _bilinear_bayer(stokes: Tensor, bayer: str) -> Tensor:
    """(N, 3, H, W) block Stokes (each block its own colour) -> (N, 3 colours, 3 Stokes, H, W).

    A small torch convolution rather than OpenCV's ``cvtColor(COLOR_Bayer…)``: that works on
    uint8/uint16 only, and s1, s2 are signed floats; the convolution also runs batched on CUDA
    and is differentiable.
    """
    n, _, h, w = stokes.shape
    index = block_colours(bayer, h, w, stokes.device)  # (H, W)
    masks = F.one_hot(index, 3).permute(2, 0, 1).to(stokes.dtype)  # (3, H, W)
    tent = stokes.new_tensor(_TENT)[None, None]  # (1, 1, 3, 3)
    samples = (stokes[:, None] * masks[None, :, None]).reshape(n, 9, h, w)  # (N, colour·Stokes, H, W)
    num = F.conv2d(samples, tent.repeat(9, 1, 1, 1), padding=1, groups=9).reshape(n, 3, 3, h, w)
    den = F.conv2d(masks[None], tent.repeat(3, 1, 1, 1), padding=1, groups=3)  # (1, 3, H, W); > 0 as H, W >= 2
    interpolated = num / den[:, :, None]  # (N, 3, 3, H, W)
    # The tent reaches a green block's diagonal green neighbours: keep every measured sample as is.
    measured = masks[None, :, None].bool()  # (1, 3, 1, H, W)
    return torch.where(measured, stokes[:, None], interpolated)


def _site_corrected(block_stokes: Tensor, colour_stokes: Tensor, layout: MosaicLayout, bayer: str,
                    angles: Tensor) -> Tensor:
    """Block Stokes (N, 3, H, W) with each site's intensity moved to the block centre, to first order.

    The four sites of a block lie ±½ pixel (±¼ block) from its centre, so under an intensity
    gradient the plain 2×2 estimate sees a spurious s1, s2 (the mono pipeline's reason for its
    bilinear demosaic). Here each site's I_θ is moved to the centre with the gradient of I_θ of the
    block's own colour, ∇I_θ = ½(∇s0 + cos 2θ ∇s1 + sin 2θ ∇s2), taken by central differences of
    that colour's interpolated Stokes field ``colour_stokes`` (N, 3, 3, H, W) on the block grid
    (one-sided at the borders): I_θ(centre) = I_θ(site) − (site − centre) · ∇I_θ.
    """
    grad_y, grad_x = torch.gradient(colour_stokes, dim=(-2, -1))  # per block, (N, 3, 3, H, W) each
    own_y, own_x = select_block_colour(grad_y, bayer), select_block_colour(grad_x, bayer)  # (N, 3, H, W)
    di_y = intensities_from_stokes(own_y, angles)  # (N, 4, H, W): ∂I_θ/∂row per block
    di_x = intensities_from_stokes(own_x, angles)
    sites = torch.tensor([layout.site_of_channel(c) for c in range(4)], dtype=block_stokes.dtype,
                         device=block_stokes.device)  # (4, 2) row, column parity
    offset = (sites - 0.5) / 2.0  # (4, 2) site − centre, in blocks (a pixel is ½ block)
    shift = offset[:, 0, None, None] * di_y + offset[:, 1, None, None] * di_x  # (N, 4, H, W)
    return block_stokes - stokes_from_intensities(shift, angles)


def colour_stokes_from_mosaic(mosaic: Tensor, layout: MosaicLayout, bayer: str, *, centre_sites: bool = False) -> Tensor:
    """Per-colour Stokes images from a raw colour polarisation mosaic (IMX250MYR-style).

    Each 2×2 block gives its own colour's Stokes vector by the plain super-pixel estimate
    (``s0 = ½ ΣI, s1 = I0 − I90, s2 = I45 − I135``, spec §1); the two colours a block did not see
    are interpolated bilinearly from the neighbouring blocks of those colours on the (H, W) block
    grid, per Stokes component (at the borders, from the neighbours that exist). Exact for
    spatially constant per-colour Stokes fields.

    ``centre_sites``: first move each site's intensity to its block's centre with the gradient of
    its colour's interpolated field, then interpolate again (:func:`_site_corrected`): exact in the
    interior for per-colour Stokes fields linear in the pixel position (the plain estimate sees a
    spurious s1, s2 there, half a pixel times the gradient), at the cost of a second interpolation.
    What :func:`polarshape.recover.preprocess.colour_superpixel_stokes` uses.

    Args:
        mosaic: (*, 2H, 2W) raw mosaic, floating point (e.g. fraction of full scale); H, W >= 2
            (every colour must occur).
        layout: polariser layout of each block as stored (our convention; for an ROI with even
            offsets the polariser layout is unchanged and the Bayer pattern is :func:`shifted_bayer`).
        bayer: Bayer pattern of the block grid (:data:`BAYER_PATTERNS`; IMX250MYR: ``"RGGB"``).
        centre_sites: correct each site to its block's centre to first order (above).

    Returns:
        (*, 3, 3, H, W): colour (R, G, B), Stokes (s0, s1, s2), super-pixel rows, columns; same
        dtype and device as ``mosaic``. Angles from image x toward image y (down).

    Example:
        >>> m = torch.rand(2, 8, 12)
        >>> colour_stokes_from_mosaic(m, MosaicLayout.imx250mzr(), "RGGB").shape
        torch.Size([2, 3, 3, 4, 6])
    """
    check_dtype_floating(mosaic, "mosaic", "convert sensor counts with polarshape.imaging.pixels.counts_to_float")
    layout = check_layout(layout)
    bayer = check_bayer(bayer)
    check_mosaic_shape(mosaic)
    *batch, hh, ww = mosaic.shape
    if hh < 4 or ww < 4:
        raise ShapeError(
            f"mosaic must have shape (*, 2H, 2W) with H, W >= 2 super-pixels for a colour sensor (at least one "
            f"4×4 Bayer super-block, so that every colour occurs); got {format_shape(mosaic.shape)}"
        )
    work_dtype = mosaic.dtype if mosaic.dtype in (torch.float32, torch.float64) else torch.float32
    m = mosaic.reshape(-1, hh, ww).to(work_dtype)  # (N, 2H, 2W)
    angles = channel_angles_rad(device=m.device, dtype=m.dtype)
    block_stokes = stokes_from_intensities(split_mosaic(m, layout), angles)  # (N, 3, H, W)
    out = _bilinear_bayer(block_stokes, bayer)  # (N, 3, 3, H, W)
    if centre_sites:
        out = _bilinear_bayer(_site_corrected(block_stokes, out, layout, bayer, angles), bayer)
    return out.to(mosaic.dtype).reshape(*batch, 3, 3, hh // 2, ww // 2)
