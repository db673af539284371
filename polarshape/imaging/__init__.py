"""Polarisation imaging: Stokes vectors, the 2×2 polariser mosaic, demosaicing, pixel formats.

Angles follow spec fmbrdf.md §1: in the image plane, from image x (right) toward image y (down).
"""

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
    "CHANNEL_ANGLES_DEG",
    "DEMOSAIC_METHODS",
    "MosaicLayout",
    "aolp",
    "channel_angles_rad",
    "dolp",
    "intensities_from_mosaic",
    "intensities_from_stokes",
    "mosaic_from_intensities",
    "mosaic_from_stokes",
    "split_mosaic",
    "stokes_from_intensities",
    "stokes_from_mosaic",
]
