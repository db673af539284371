"""Pack and unpack the raw pixel formats of polarisation cameras (GenICam PFNC).

It is part of ``imaging`` (not ``acquisition``) so that every stage that meets raw bytes uses this
one codec: the camera backends (GigE Vision streams) and the importers (``.raw`` files saved by
Lucid's Arena SDK / ArenaView, :mod:`polarshape.io.importers.arena`).

Every format is converted to and from a ``uint16`` array of shape (H, W) holding sensor counts,
low-bit aligned (values in ``[0, 2**bit_depth - 1]``). The mono sensor's ``PolarizeMono*`` and the
colour sensor's ``BayerRG*`` formats (:data:`~polarshape.imaging.pixels.COLOUR_PIXEL_FORMATS`: the
raw 4×4 super-block mosaic of the IMX250MYR) share the byte layouts, by name suffix:

- ``…8``: one byte per pixel.
- ``…12p`` (PFNC "p" packing, as ``Mono12p``): the image is one LSB-first bit stream;
  two pixels a, b occupy three bytes ``[a & 0xFF, (a >> 8) | (b & 0xF) << 4, b >> 4]``. An odd
  pixel count ends with a half-filled, zero-padded byte pair (the stream is padded to whole bytes).
- ``…12Packed`` (GigE Vision ``Mono12Packed`` / ``BayerRG12Packed``): two pixels a, b in three bytes
  ``[a >> 4, (a & 0xF) | (b & 0xF) << 4, b >> 4]``; an odd pixel count ends with two bytes.
- ``…12`` and ``…16``: two bytes per pixel, little-endian (GigE Vision streams are
  little-endian), 12 or 16 significant bits.

All conversions are vectorised numpy and bit-exact both ways.

Example:
    >>> import numpy as np
    >>> img = np.array([[0x123, 0xABC]], dtype=np.uint16)
    >>> pack_mosaic(img, "PolarizeMono12p").hex()
    '23c1ab'
    >>> unpack_mosaic(bytes.fromhex("23c1ab"), "PolarizeMono12p", width=2, height=1).tolist()
    [[291, 2748]]
"""

from __future__ import annotations

import numpy as np

from polarshape.imaging.pixels import PIXEL_FORMATS, bit_depth_of

__all__ = [
    "format_name_of",
    "pack_mosaic",
    "payload_size",
    "unpack_mosaic",
]

_CODE_TO_NAME: dict[int, str] = {code: name for name, (code, _) in PIXEL_FORMATS.items()}


def _layout_of(pixel_format: str) -> str:
    """Byte layout of a supported format, by its name suffix: ``"8"``, ``"12p"``, ``"12Packed"`` or
    ``"16"`` (two little-endian bytes, 12 or 16 significant bits). Raises ValueError if unsupported."""
    bit_depth_of(pixel_format)  # raises ValueError naming the supported formats
    for suffix in ("12Packed", "12p"):
        if pixel_format.endswith(suffix):
            return suffix
    return "8" if pixel_format.endswith("8") else "16"


def format_name_of(code: int) -> str:
    """PFNC name of a pixel-format code, e.g. ``0x810C0047 -> "PolarizeMono12p"``."""
    try:
        return _CODE_TO_NAME[int(code)]
    except KeyError:
        raise ValueError(
            f"pixel-format code 0x{int(code):08X} is not a raw polarisation mosaic format polarshape reads; "
            f"known codes: { {name: hex(c) for name, (c, _) in PIXEL_FORMATS.items()} }"
        ) from None


def payload_size(pixel_format: str, width: int, height: int) -> int:
    """Number of bytes of one (height, width) image in ``pixel_format``."""
    layout = _layout_of(pixel_format)
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive; got width={width}, height={height}")
    n = width * height
    if layout == "8":
        return n
    if layout in ("12p", "12Packed"):
        return (3 * n + 1) // 2  # 12 bits per pixel, rounded up to whole bytes
    return 2 * n


def pack_mosaic(image: np.ndarray, pixel_format: str) -> bytes:
    """Encode a mosaic into the byte layout of ``pixel_format``.

    Args:
        image: (H, W) integer array of sensor counts in ``[0, 2**bit_depth - 1]``.
        pixel_format: a key of :data:`polarshape.imaging.pixels.PIXEL_FORMATS`.

    Returns:
        ``payload_size(pixel_format, W, H)`` bytes, rows concatenated top to bottom.
    """
    layout = _layout_of(pixel_format)
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"image must have shape (H, W); got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.integer):
        raise ValueError(f"image must hold integer sensor counts; got dtype {image.dtype}")
    bits = bit_depth_of(pixel_format)
    if image.size and (int(image.min()) < 0 or int(image.max()) > (1 << bits) - 1):
        raise ValueError(
            f"image values must lie in [0, {(1 << bits) - 1}] for {pixel_format}; got "
            f"[{int(image.min())}, {int(image.max())}] (scale or clip the counts first)"
        )
    flat = image.astype(np.uint16, copy=False).ravel()  # (N,)
    if layout == "8":
        return flat.astype(np.uint8).tobytes()
    if layout == "16":
        return flat.astype("<u2").tobytes()
    n = flat.size
    if n % 2:
        flat = np.concatenate([flat, np.zeros(1, dtype=np.uint16)])
    a = flat[0::2]  # (N/2,) first pixel of each pair
    b = flat[1::2]  # (N/2,) second pixel
    out = np.empty((a.size, 3), dtype=np.uint8)
    if layout == "12p":
        out[:, 0] = a & 0xFF
        out[:, 1] = (a >> 8) | ((b & 0xF) << 4)
        out[:, 2] = b >> 4
    else:  # 12Packed
        out[:, 0] = a >> 4
        out[:, 1] = (a & 0xF) | ((b & 0xF) << 4)
        out[:, 2] = b >> 4
    return out.tobytes()[: payload_size(pixel_format, n, 1)]


def unpack_mosaic(
    data: bytes | bytearray | memoryview | np.ndarray,
    pixel_format: str,
    *,
    width: int,
    height: int,
) -> np.ndarray:
    """Decode ``pixel_format`` bytes into a (height, width) ``uint16`` mosaic of sensor counts.

    Args:
        data: the image payload; at least ``payload_size(pixel_format, width, height)`` bytes
            (trailing bytes, e.g. padding of a GigE Vision buffer, are ignored).
        pixel_format: a key of :data:`polarshape.imaging.pixels.PIXEL_FORMATS`.
        width, height: image size in pixels.

    Returns:
        (height, width) ``uint16`` array, low-bit aligned.
    """
    need = payload_size(pixel_format, width, height)
    layout = _layout_of(pixel_format)
    raw = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    raw = raw.reshape(-1).view(np.uint8) if raw.dtype != np.uint8 else raw.reshape(-1)
    if raw.size < need:
        raise ValueError(
            f"{pixel_format} image of {width}x{height} needs {need} bytes; got {raw.size} "
            "(wrong width/height/pixel_format, or a truncated buffer)"
        )
    raw = raw[:need]
    n = width * height
    if layout == "8":
        return raw.astype(np.uint16).reshape(height, width)
    if layout == "16":
        img = raw.view("<u2").astype(np.uint16)
        if bit_depth_of(pixel_format) == 12 and img.size and int(img.max()) > 0xFFF:
            raise ValueError(
                f"{pixel_format} data has values above 4095: the payload is not low-bit aligned "
                f"12-bit (is the camera sending {pixel_format[:-2]}16?)"
            )
        return img.reshape(height, width)
    if raw.size % 3:
        raw = np.concatenate([raw, np.zeros(3 - raw.size % 3, dtype=np.uint8)])
    triples = raw.reshape(-1, 3).astype(np.uint16)  # (ceil(N/2), 3)
    pixels = np.empty((triples.shape[0], 2), dtype=np.uint16)
    if layout == "12p":
        pixels[:, 0] = triples[:, 0] | ((triples[:, 1] & 0xF) << 8)
        pixels[:, 1] = (triples[:, 1] >> 4) | (triples[:, 2] << 4)
    else:  # 12Packed
        pixels[:, 0] = (triples[:, 0] << 4) | (triples[:, 1] & 0xF)
        pixels[:, 1] = (triples[:, 2] << 4) | (triples[:, 1] >> 4)
    return pixels.reshape(-1)[:n].reshape(height, width)
