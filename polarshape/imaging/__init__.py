"""Polarisation imaging: Stokes vectors, the 2×2 polariser mosaic, demosaicing, pixel formats.

Angles follow spec fmbrdf.md §1: in the image plane, from image x (right) toward image y (down).
"""

from polarshape.imaging.colour import (
    BAYER_PATTERNS,
    block_colours,
    colour_mosaic_from_stokes,
    colour_stokes_from_mosaic,
    pixel_colours,
)
from polarshape.imaging.demosaic import DEMOSAIC_METHODS, intensities_from_mosaic, stokes_from_mosaic
from polarshape.imaging.mosaic import (
    CHANNEL_ANGLES_DEG,
    MosaicLayout,
    channel_angles_rad,
    mosaic_from_intensities,
    mosaic_from_stokes,
    split_mosaic,
)
from polarshape.imaging.stokes import aolp, dolp, intensities_from_stokes, stokes_from_intensities

__all__ = [
    "BAYER_PATTERNS",
    "CHANNEL_ANGLES_DEG",
    "DEMOSAIC_METHODS",
    "MosaicLayout",
    "aolp",
    "block_colours",
    "channel_angles_rad",
    "colour_mosaic_from_stokes",
    "colour_stokes_from_mosaic",
    "dolp",
    "intensities_from_mosaic",
    "intensities_from_stokes",
    "mosaic_from_intensities",
    "mosaic_from_stokes",
    "pixel_colours",
    "split_mosaic",
    "stokes_from_intensities",
    "stokes_from_mosaic",
]
