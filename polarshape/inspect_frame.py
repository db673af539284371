"""`polarshape inspect FRAME`: polarisation statistics of one raw mosaic (e.g. to check the
polariser angle convention of a camera with a rotating linear polariser)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch

from polarshape.checks import check_shape
from polarshape.imaging.demosaic import stokes_from_mosaic
from polarshape.imaging.mosaic import MosaicLayout
from polarshape.imaging.pixels import counts_to_float, saturation_mask
from polarshape.imaging.stokes import aolp, dolp
from polarshape.io.images import read_image


@dataclass(frozen=True)
class FrameStats:
    """Mean Stokes statistics over the evaluated super-pixels."""

    mean_s0: float  # fraction of full scale
    mean_dolp: float  # DoLP of the mean Stokes vector
    aolp_deg: float  # AoLP of the mean Stokes vector, our convention (from image x toward y), (−90, 90]
    saturated_fraction: float
    n_superpixels: int


def frame_stats(
    path: str | Path,
    *,
    bit_depth: int = 12,
    black_level: float = 0.0,
    layout: MosaicLayout | None = None,
    roi: tuple[int, int, int, int] | None = None,
) -> FrameStats:
    """Stokes statistics of a raw mosaic file over an optional ROI (x, y, w, h in mosaic pixels).

    The ROI is snapped to even offsets so the 2×2 pattern of ``layout`` (default IMX250MZR) holds.
    """
    raw = read_image(path)  # (H, W) sensor counts
    check_shape(raw, ["H", "W"], str(path), "(a single-channel raw mosaic)")
    if roi is not None:
        full_wh = raw.shape[::-1]
        x, y, w, h = roi
        x, y = x - x % 2, y - y % 2
        raw = raw[y : y + h - h % 2, x : x + w - w % 2]
        if raw.size == 0:
            raise ValueError(f"ROI {roi} is empty for a {full_wh} frame")
    sat = saturation_mask(raw, bit_depth)
    img = counts_to_float(raw, bit_depth, black_level, dtype=torch.float64)
    s = stokes_from_mosaic(img, layout or MosaicLayout.imx250mzr(), method="superpixel")  # (3, H/2, W/2)
    mean = s.reshape(3, -1).mean(-1)  # (3,) the mean Stokes vector
    s0 = float(mean[0])
    return FrameStats(
        mean_s0=s0,
        mean_dolp=float(dolp(mean, dim=0, eps=0.0)) if s0 > 0 else 0.0,
        aolp_deg=math.degrees(float(aolp(mean, dim=0))),
        saturated_fraction=float(sat.mean()),
        n_superpixels=int(s.shape[-1] * s.shape[-2]),
    )
