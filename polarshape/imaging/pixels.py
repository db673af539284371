"""Sensor pixel formats (GenICam names, bit depths): counts <-> floats, saturation and dark masks,
super-pixel mask reduction.

Raw counts are low-bit aligned integers in [0, 2**bit_depth - 1] (capture-format.md), stored in
``uint8`` (8-bit) or ``uint16`` (10, 12, 16-bit). Floats are fractions of full scale after black
level subtraction: ``(counts - black_level) / (2**bit_depth - 1 - black_level)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, TypeVar

import numpy as np
import torch
from torch import Tensor

from polarshape.checks import check_shape, to_numpy

__all__ = [
    "saturation_count",
    "BIT_DEPTHS",
    "COLOUR_PIXEL_FORMATS",
    "MONO_PIXEL_FORMATS",
    "left_shift_of",
    "PIXEL_FORMATS",
    "bayer_of",
    "bit_depth_of",
    "check_bit_depth",
    "check_count_range",
    "counts_to_float",
    "dark_mask",
    "float_to_counts",
    "max_count",
    "reduce_mask_to_superpixels",
    "saturation_mask",
]

#: Bit depths polarshape understands.
BIT_DEPTHS: tuple[int, ...] = (8, 10, 12, 16)

#: Raw mosaic formats of the mono polarisation sensor (IMX250MZR, Lucid TRI050S-PC): Lucid's custom
#: codes (bit 31 set), as in Arena SDK's PFNC.h (``LUCID_PolarizeMono*``).
MONO_PIXEL_FORMATS: dict[str, tuple[int, int]] = {
    "PolarizeMono8": (0x81080001, 8),
    "PolarizeMono12p": (0x810C0047, 12),
    "PolarizeMono12Packed": (0x810C0006, 12),
    "PolarizeMono12": (0x81100008, 12),
    "PolarizeMono16": (0x81100007, 16),
}

#: Raw mosaic formats of the colour polarisation sensor (IMX250MYR, Lucid TRI050S-QC): the 4×4
#: super-block mosaic (a Bayer filter over the 2×2 polariser blocks) travels in the standard PFNC
#: Bayer formats, whose name gives the colours of the top-left blocks (``BayerRG`` = RGGB on the
#: block grid). Codes as in PFNC (Arena SDK's PFNC.h ``PFNC_BayerRG*``, ``GVSP_BayerRG12Packed``;
#: Aravis' ``ARV_PIXEL_FORMAT_BAYER_RG_*``). Same byte layouts as the PolarizeMono format of the
#: same suffix (:mod:`polarshape.imaging.pixel_formats`).
COLOUR_PIXEL_FORMATS: dict[str, tuple[int, int]] = {
    "BayerRG8": (0x01080009, 8),
    "BayerRG12p": (0x010C0059, 12),
    "BayerRG12Packed": (0x010C002B, 12),
    "BayerRG12": (0x01100011, 12),
    "BayerRG16": (0x0110002F, 16),
}

#: Pixel formats polarshape understands, by GenICam PFNC name -> (code, bit depth): the raw mosaic
#: formats of the mono and the colour polarisation sensors. Lucid's processed polarisation formats
#: (``PolarizedAngles_*``, ``PolarizedStokes_*``, ``PolarizedDolpAolp_*``, …) are not among them:
#: capture the raw mosaic.
PIXEL_FORMATS: dict[str, tuple[int, int]] = {**MONO_PIXEL_FORMATS, **COLOUR_PIXEL_FORMATS}

# PFNC Bayer name prefix -> colours of blocks (0, 0), (0, 1), (1, 0), (1, 1) (polarshape.imaging.colour)
_BAYER_PREFIXES = {"BayerRG": "RGGB", "BayerGR": "GRBG", "BayerGB": "GBRG", "BayerBG": "BGGR"}

ArrayOrTensor = TypeVar("ArrayOrTensor", np.ndarray, Tensor)


def check_bit_depth(bit_depth: object) -> int:
    """Return ``bit_depth`` as an int if it is one of 8, 10, 12, 16; else raise ValueError naming the fix."""
    if isinstance(bit_depth, bool) or not isinstance(bit_depth, (int, np.integer)) or int(bit_depth) not in BIT_DEPTHS:
        raise ValueError(
            f"bit_depth must be one of {BIT_DEPTHS} (significant bits per pixel of the sensor's pixel "
            f"format, e.g. 12 for PolarizeMono12p); got {bit_depth!r}"
        )
    return int(bit_depth)


def bit_depth_of(pixel_format: str) -> int:
    """Significant bits per pixel of a raw polarisation mosaic format (a key of :data:`PIXEL_FORMATS`: 8, 12 or 16)."""
    if pixel_format not in PIXEL_FORMATS:
        raise ValueError(f"pixel_format {pixel_format!r} is not supported; use one of {sorted(PIXEL_FORMATS)}")
    return PIXEL_FORMATS[pixel_format][1]


def bayer_of(pixel_format: str) -> str | None:
    """Bayer pattern of the 2×2 polariser blocks of a frame in ``pixel_format`` (a key of
    :data:`PIXEL_FORMATS`): ``"RGGB"`` for ``BayerRG*`` (the IMX250MYR / TRI050S-QC), None for the mono
    ``PolarizeMono*`` formats. It is what ``camera.mosaic.bayer`` of a capture.yaml records.

    Example:
        >>> bayer_of("BayerRG12p"), bayer_of("PolarizeMono12p")
        ('RGGB', None)
    """
    bit_depth_of(pixel_format)  # raises ValueError naming the supported formats
    return next((bayer for prefix, bayer in _BAYER_PREFIXES.items() if pixel_format.startswith(prefix)), None)


def max_count(bit_depth: int) -> int:
    """Largest count of a ``bit_depth``-bit pixel: ``2**bit_depth - 1``."""
    return (1 << check_bit_depth(bit_depth)) - 1


def saturation_count(bit_depth: int) -> int:
    """The count at which a site is clipped: :func:`max_count`, except that a 16-bit format
    carrying a 12-bit ADC (the IMX250MZR's PolarizeMono16) tops out at 4095 · 16 = 65520, not
    65535, so the last 12-bit step counts as saturated."""
    return max_count(bit_depth) if bit_depth < 16 else 65520


def left_shift_of(frames: np.ndarray | Sequence[np.ndarray]) -> int:
    """Bits by which 16-bit counts look stored **high-bit aligned**: 4 for 12-bit counts (as the
    IMX250MZR's PolarizeMono16 and 16-bit saves of PolarizeMono12 hold them), 6 for 10-bit, 8 for
    8-bit; 0 when they are not.

    Counts are taken as shifted by ``s`` when the largest is above 4095 (low-bit aligned 12-bit
    counts never are), every count is a multiple of ``2**s`` and they are not all equal (a flat
    frame cannot tell). Judged over all ``frames`` together; an evenly spread sample of 4096 counts
    is looked at first, so ordinary 16-bit data cost almost nothing.

    Args:
        frames: ``uint16`` counts of any shape, or a sequence of such arrays (e.g. K frames (H, W)).

    Returns:
        0, 4, 6 or 8.
    """
    arrays = [np.asarray(frames)] if isinstance(frames, np.ndarray) else [np.asarray(f) for f in frames]
    arrays = [a.reshape(-1) for a in arrays if a.size]
    if not arrays:
        return 0
    if any(int(np.bitwise_or.reduce(a[:: max(1, a.size // 4096)])) & 0xF for a in arrays):
        return 0
    hi = max(int(a.max()) for a in arrays)
    if hi <= 4095 or min(int(a.min()) for a in arrays) == hi:
        return 0
    bits_set = 0
    for a in arrays:
        bits_set |= int(np.bitwise_or.reduce(a))
    zeros = (bits_set & -bits_set).bit_length() - 1  # low zero bits common to every count
    return next((s for s in (8, 6, 4) if zeros >= s), 0)


def _check_black_level(black_level: float, bit_depth: int) -> float:
    top = max_count(bit_depth)
    if not np.isfinite(black_level) or not 0 <= black_level < top:
        raise ValueError(f"black_level must be in [0, {top}) counts for bit_depth {bit_depth}; got {black_level!r}")
    return float(black_level)


def _check_integer_counts(raw: object, name: str = "raw") -> None:
    """Raise TypeError unless ``raw`` is a numpy array or torch tensor of an integer dtype."""
    if isinstance(raw, np.ndarray):
        if not np.issubdtype(raw.dtype, np.integer):
            raise TypeError(f"{name} must hold integer sensor counts (uint8/uint16); got dtype {raw.dtype}")
        return
    if isinstance(raw, Tensor):
        if raw.is_floating_point() or raw.is_complex() or raw.dtype == torch.bool:
            raise TypeError(f"{name} must hold integer sensor counts (uint8/uint16); got dtype {raw.dtype}")
        return
    raise TypeError(f"{name} must be a numpy array or torch tensor of sensor counts; got {type(raw).__name__}")


def _counts_as_int64(raw: np.ndarray | Tensor, name: str = "raw") -> Tensor:
    """Integer counts (any integer dtype, numpy or torch) as an int64 tensor on the input's device."""
    _check_integer_counts(raw, name)
    if isinstance(raw, np.ndarray):
        return torch.from_numpy(raw.astype(np.int64, copy=False))
    return raw.to(torch.int64)


def counts_to_float(
    raw: np.ndarray | Tensor,
    bit_depth: int,
    black_level: float = 0,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """Sensor counts -> fraction of full scale after black level subtraction.

    Args:
        raw: (*) integer counts, low-bit aligned, in [0, 2**bit_depth - 1] (numpy or torch).
        bit_depth: 8, 10, 12 or 16.
        black_level: counts of a dark pixel, subtracted first; in [0, 2**bit_depth - 1).
        dtype: float dtype of the result.
        device: device of the result (default: the input's device; CPU for numpy input).

    Returns:
        (*) ``(raw - black_level) / (2**bit_depth - 1 - black_level)``: 1 at full scale. Counts
        below the black level give small negative values (kept, so noise stays unbiased). Equal to
        the float64 result rounded to ``dtype``; float32 is computed in float32 when that is exact
        (a black level in 1/256 counts), so the memory is one array of the result (no int64 copy).

    Raises:
        ValueError: bad bit depth or black level, or a count above ``2**bit_depth - 1`` (the data
            are not what ``bit_depth`` says, e.g. high-bit aligned).
    """
    bit_depth = check_bit_depth(bit_depth)
    black = _check_black_level(black_level, bit_depth)
    _check_integer_counts(raw)
    if not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating-point torch dtype; got {dtype}")
    top = max_count(bit_depth)
    # float32 gives the float64 result rounded once when counts - black and top - black are exact in
    # float32 (black a multiple of 1/256: < 24 significant bits) and the division is IEEE: the float64
    # quotient is then never within its own rounding of a float32 midpoint. Else float64 first.
    exact32 = dtype == torch.float32 and (black * 256.0).is_integer()
    work = torch.float32 if exact32 else torch.float64
    if isinstance(raw, np.ndarray):  # no int64 copy: counts of up to 16 bits are exact in float32
        x = torch.from_numpy(raw.astype(np.float32 if exact32 else np.float64))
        x = x if device is None else x.to(device)
    else:
        x = raw.to(device=raw.device if device is None else device, dtype=torch.float64 if raw.element_size() > 2 else work)
    if x.numel():
        check_count_range(int(x.min()), int(x.max()), bit_depth)
    x = x.to(work).sub_(black).div_(top - black)  # (*) in place: one array of the working dtype
    return x.to(dtype)


def check_count_range(lo: int, hi: int, bit_depth: int) -> None:
    """Raise ValueError when counts spanning [lo, hi] do not fit a ``bit_depth``-bit pixel (e.g. high-bit
    aligned data), naming the fix."""
    top = max_count(bit_depth)
    if lo < 0 or hi > top:
        raise ValueError(
            f"raw counts span [{lo}, {hi}] but a {bit_depth}-bit pixel holds [0, {top}]: check bit_depth "
            f"(if the data are high-bit aligned in 16 bits, shift right by {16 - bit_depth})"
        )


def float_to_counts(x: np.ndarray | Tensor, bit_depth: int, black_level: float = 0) -> np.ndarray:
    """Fraction of full scale -> integer counts (inverse of :func:`counts_to_float`), rounded and clipped.

    Args:
        x: (*) floats, 1 = full scale above the black level (numpy or torch, any device).
        bit_depth: 8, 10, 12 or 16.
        black_level: counts added back after scaling.

    Returns:
        (*) ``uint8`` array for bit_depth 8, else ``uint16``, values in [0, 2**bit_depth - 1].
        NaN maps to 0.
    """
    bit_depth = check_bit_depth(bit_depth)
    black = _check_black_level(black_level, bit_depth)
    top = max_count(bit_depth)
    arr = to_numpy(x, np.float64)
    counts = np.rint(np.nan_to_num(arr * (top - black) + black, nan=0.0, posinf=top, neginf=0.0))
    return np.clip(counts, 0, top).astype(np.uint8 if bit_depth == 8 else np.uint16)


def _like_input(mask: Tensor, raw: ArrayOrTensor) -> ArrayOrTensor:
    return mask.cpu().numpy() if isinstance(raw, np.ndarray) else mask  # type: ignore[return-value]


def saturation_mask(raw: ArrayOrTensor, bit_depth: int, margin: int = 0) -> ArrayOrTensor:
    """Pixels at (or within ``margin`` counts of) the top of the range.

    Args:
        raw: (*) integer counts (numpy or torch).
        bit_depth: 8, 10, 12 or 16.
        margin: counts below ``2**bit_depth - 1`` still treated as saturated (>= 0).

    Returns:
        (*) bool mask, True where ``raw >= 2**bit_depth - 1 - margin``; numpy in, numpy out.
        Reduce to super-pixels with :func:`reduce_mask_to_superpixels` (``mode="any"``).
    """
    top = max_count(bit_depth)
    if isinstance(margin, bool) or not isinstance(margin, (int, np.integer)) or not 0 <= margin < top:
        raise ValueError(f"margin must be an integer number of counts in [0, {top}); got {margin!r}")
    return _like_input(_counts_as_int64(raw) >= top - int(margin), raw)


def dark_mask(raw: ArrayOrTensor, bit_depth: int, black_level: float = 0, threshold: float = 0.02) -> ArrayOrTensor:
    """Pixels too dark to carry polarisation (signal below ``threshold`` of full scale).

    Args:
        raw: (*) integer counts (numpy or torch).
        bit_depth: 8, 10, 12 or 16.
        black_level: counts of a dark pixel.
        threshold: fraction of full scale (after black level subtraction), in [0, 1).

    Returns:
        (*) bool mask, True where ``counts_to_float(raw) < threshold``; numpy in, numpy out.
    """
    if not 0 <= threshold < 1:
        raise ValueError(f"threshold must be a fraction of full scale in [0, 1); got {threshold!r}")
    x = counts_to_float(raw, bit_depth, black_level, dtype=torch.float64)
    return _like_input(x < threshold, raw)


def reduce_mask_to_superpixels(mask: ArrayOrTensor, mode: Literal["any", "all"] = "any") -> ArrayOrTensor:
    """Reduce a mosaic-resolution mask to super-pixels.

    Args:
        mask: (*, 2H, 2W) bool (or 0/non-zero) mask at mosaic resolution, numpy or torch.
        mode: ``"any"``: a super-pixel is set if any of its four sites is (use for saturation and
            darkness: one bad site spoils the Stokes vector); ``"all"``: only if all four are (use
            for object masks).

    Returns:
        (*, H, W) bool mask, numpy in, numpy out.
    """
    if mode not in ("any", "all"):
        raise ValueError(f"mode must be 'any' or 'all'; got {mode!r}")
    check_shape(mask, ["*", "2H", "2W"], "mask", "with even sizes")
    sites = [mask[..., i::2, j::2] != 0 for i in (0, 1) for j in (0, 1)]
    if isinstance(mask, np.ndarray):
        stacked = np.stack(sites, axis=0)
        return np.asarray(stacked.any(axis=0) if mode == "any" else stacked.all(axis=0))
    stacked_t = torch.stack(sites, dim=0)
    return stacked_t.any(dim=0) if mode == "any" else stacked_t.all(dim=0)
