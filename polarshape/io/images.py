"""Lossless single-channel 8/16-bit PNG and TIFF images (raw mosaics, masks), written atomically.

Images are read unchanged (``cv2.IMREAD_UNCHANGED``: no colour conversion, no bit-depth scaling)
and written with the dtype they have, so a ``uint16`` array of 12-bit counts round-trips exactly.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np

from polarshape.errors import ImageError
from polarshape.io.atomic import atomic_path

logger = logging.getLogger(__name__)

__all__ = ["IMAGE_SUFFIXES", "ImageError", "decode_image", "read_image", "write_image"]

#: File suffixes (lower case) of the image formats polarshape reads and writes.
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".tif", ".tiff")


def _check_suffix(path: Path) -> None:
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise ImageError(f"{path}: unsupported image type {path.suffix!r}; use one of {IMAGE_SUFFIXES} (lossless)")


def decode_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Decode an image file exactly as stored (``cv2.IMREAD_UNCHANGED``), a single channel as (H, W).

    Callers check channels and dtype with their own message (:func:`read_image`, the importers).

    Returns:
        (H, W) or (H, W, C) array of the file's dtype.

    Raises:
        ImageError: the file cannot be decoded.
    """
    path = Path(path)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageError(f"{path}: cannot be decoded as an image (corrupt or not a {path.suffix} file)")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    return image


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a single-channel 8- or 16-bit PNG/TIFF exactly as stored.

    Args:
        path: image file (.png, .tif, .tiff).

    Returns:
        (H, W) ``uint8`` or ``uint16`` array (sensor counts or mask values, unscaled).

    Raises:
        ImageError: missing or unreadable file, colour or multi-page content, other dtypes.
    """
    path = Path(path)
    _check_suffix(path)
    if not path.is_file():
        raise ImageError(f"{path}: file not found")
    image = decode_image(path)
    if image.ndim != 2:
        raise ImageError(
            f"{path}: has {image.shape[2] if image.ndim == 3 else '?'} channels; a raw mosaic or mask must be a "
            "single-channel (grayscale) image: save the sensor counts as one channel, not RGB"
        )
    if image.dtype not in (np.uint8, np.uint16):
        raise ImageError(
            f"{path}: pixel type {image.dtype} is not supported; store sensor counts as 8-bit or 16-bit unsigned "
            "integers (low-bit aligned)"
        )
    return image


def write_image(path: str | os.PathLike[str], image: np.ndarray, *, overwrite: bool = False) -> Path:
    """Write a single-channel ``uint8``/``uint16`` image losslessly and atomically.

    Args:
        path: destination (.png, .tif or .tiff; the suffix picks the format).
        image: (H, W) ``uint8`` or ``uint16`` array, written unscaled.
        overwrite: replace an existing file (otherwise :class:`OutputExistsError`).

    Returns:
        The path written.
    """
    path = Path(path)
    _check_suffix(path)
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        desc = f"{image.dtype} array of shape {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ImageError(
            f"{path}: can only write (H, W) uint8 or uint16 arrays; got {desc} "
            "(convert counts with polarshape.imaging.pixels.float_to_counts)"
        )
    params = [cv2.IMWRITE_PNG_COMPRESSION, 3] if path.suffix.lower() == ".png" else []
    with atomic_path(path, overwrite=overwrite) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(image), params):
            raise ImageError(f"{path}: OpenCV could not write the image (check the folder is writable)")
    logger.debug("wrote %s (%s, %dx%d)", path, image.dtype, image.shape[1], image.shape[0])
    return path
