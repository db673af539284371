"""Frames saved by Lucid's Arena SDK / ArenaView → polarshape capture folders.

A polarisation camera on Arena (the Lucid TRI050S-PC, Sony IMX250MZR) is saved one frame per
file. What each kind of file holds, and what the import makes of it:

- ``.raw`` — the image buffer as the camera sent it, no header. Width, height and pixel format are
  not in the file, so they must be given (ArenaView shows them as the camera's ``Width``,
  ``Height`` and ``PixelFormat``; a full TRI050S-PC frame is 2448×2048). The byte layouts are
  those of :mod:`polarshape.imaging.pixel_formats` (the same codec as the Aravis backend):
  ``PolarizeMono8`` (a byte per pixel), ``PolarizeMono12`` and ``PolarizeMono16`` (two bytes,
  little-endian, low-bit aligned), ``PolarizeMono12p`` (PFNC: one LSB-first bit stream, two pixels
  in three bytes) and ``PolarizeMono12Packed`` (GigE Vision: two pixels in three bytes, the shared
  middle byte holding both low nibbles). The file size must be exactly one frame. A colour
  polarisation camera (TRI050S-QC, Sony IMX250MYR) saves its raw 4×4 super-block mosaic in the
  ``BayerRG8`` / ``BayerRG12`` / ``BayerRG12p`` / ``BayerRG12Packed`` / ``BayerRG16`` formats, with the
  same byte layouts; the capture then records ``camera.mosaic.bayer: RGGB``.
- ``.tif`` / ``.tiff`` / ``.png``, one channel, 16-bit — counts in a 16-bit container. 12-bit
  counts are often stored **high-bit aligned** (left-shifted by 4: every count a multiple of 16,
  full scale 65520), as Arena does when it saves PolarizeMono12 data in 16 bits, and the IMX250MZR's
  own PolarizeMono16 is its 12-bit counts shifted the same way. When every count of every frame is a
  multiple of 16 and the largest is above 4095, the import says so (``logging.info`` and the notes
  it returns), shifts the counts right and records the shift in ``camera.model`` and
  ``ground_truth/source.json``. 10-bit (multiples of 64) and 8-bit (of 256) counts in 16 bits are
  found the same way. Counts that never exceed 4095 are kept as 16-bit unless ``pixel_format``
  says they are 12-bit (``PolarizeMono12``); the notes point that out.
- 8-bit single-channel PNG/TIFF — refused unless ``pixel_format="PolarizeMono8"`` (or ``BayerRG8``)
  says it is a real 8-bit save of the sensor counts: an 8-bit PNG from ArenaView is usually a
  display image. A colour camera's 16-bit saves need ``pixel_format`` (a ``BayerRG*`` one) to be
  imported as colour mosaics; without it they are taken for a mono sensor's.
- ``.bmp``, ``.jpg`` / ``.jpeg`` and any colour image — always refused: a display image
  (tone-mapped, 8-bit, possibly demosaiced or false-coloured), not the sensor's counts.

The frame of the light file is never guessed (``light_frame``); the lights go to the frames by
:func:`~polarshape.io.importers.lightfiles.match_light_order` (an ``.lp`` file naming every frame
goes by name, else file order). The camera is orthographic unless pinhole intrinsics are given;
the mosaic is the IMX250MZR's (``camera.mosaic`` default: a ROI whose offset is odd shifts it, so
edit ``camera.mosaic.layout`` then). Import writes through
:func:`polarshape.io.capture.write_capture` (atomic) and never over a source file.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from polarshape.errors import CaptureError
from polarshape.imaging.pixel_formats import payload_size, unpack_mosaic
from polarshape.imaging.pixels import COLOUR_PIXEL_FORMATS, bayer_of, bit_depth_of, left_shift_of, max_count
from polarshape.io.images import ImageError, decode_image
from polarshape.io.capture import CAPTURE_FORMAT, Capture, parse_capture_spec, write_capture
from polarshape.io.importers.destination import check_import_destination
from polarshape.io.importers.diligent import read_diligent_intensities
from polarshape.io.importers.lightfiles import (
    LightFileFormat,
    LightFrame,
    check_camera_side,
    match_light_order,
    read_light_file,
)

logger = logging.getLogger(__name__)

__all__ = [
    "ARENA_FRAME_SUFFIXES",
    "ARENA_PIXEL_FORMATS",
    "ArenaFrame",
    "import_arena",
    "read_arena_frame",
]

#: Pixel formats a ``.raw`` save may hold: the TRI050S-PC's raw polarisation formats, then the colour
#: TRI050S-QC's raw ``BayerRG*`` ones.
ARENA_PIXEL_FORMATS: tuple[str, ...] = ("PolarizeMono8", "PolarizeMono12", "PolarizeMono12p",
                                        "PolarizeMono12Packed", "PolarizeMono16", *COLOUR_PIXEL_FORMATS)
RAW_SUFFIXES: tuple[str, ...] = (".raw",)
PICTURE_SUFFIXES: tuple[str, ...] = (".tif", ".tiff", ".png")
#: Suffixes of the files the import reads.
ARENA_FRAME_SUFFIXES: tuple[str, ...] = RAW_SUFFIXES + PICTURE_SUFFIXES
#: Display formats, always refused.
PREVIEW_SUFFIXES: tuple[str, ...] = (".bmp", ".jpg", ".jpeg")

#: A full TRI050S-PC (IMX250MZR) frame, width × height (for the size hints of a .raw file).
FULL_FRAME: tuple[int, int] = (2448, 2048)
#: Largest count of 12-bit data: above it, a 16-bit container holds more than 12 bits.
MAX_12BIT = 4095

_PREVIEW_REASON = ("a display image (ArenaView/Arena previews are 8-bit, tone-mapped and possibly demosaiced or "
                   "false-coloured), not the sensor's counts")
_SAVE_FIX = ("save the frames as .raw (the buffer as the camera sent it) or as single-channel 16-bit TIFF/PNG of a "
             "PolarizeMono12/PolarizeMono16 image")


class ArenaFrame(NamedTuple):
    """One Arena save, read as sensor counts.

    Attributes:
        counts: (H, W) ``uint16`` counts, low-bit aligned (in ``[0, 2**bit_depth - 1]``).
        bit_depth: significant bits of ``counts`` (8, 10, 12 or 16).
        notes: what was found and done (e.g. a left shift undone), one sentence each.
        shift: bits the stored values were shifted right by (0: stored low-bit aligned).
    """

    counts: np.ndarray
    bit_depth: int
    notes: tuple[str, ...]
    shift: int


@dataclass(frozen=True)
class _Stored:
    """A file's values before any shift: (H, W) ``uint16`` (8-bit widened), what the file is, the
    container's bits (8 or 16), and the bits the pixel format fixes (None: to be found)."""

    values: np.ndarray
    kind: str
    container_bits: int
    declared_bits: int | None


# --- reading one file ----------------------------------------------------------------------------


def _pixels_in(size: int, pixel_format: str) -> int | None:
    """The pixel count whose ``pixel_format`` payload is ``size`` bytes, or None."""
    if pixel_format.endswith(("12p", "12Packed")):
        for n in (2 * size // 3, (2 * size - 1) // 3):
            if n > 0 and payload_size(pixel_format, n, 1) == size:
                return n
        return None
    per_pixel = 1 if bit_depth_of(pixel_format) == 8 else 2
    return size // per_pixel if size % per_pixel == 0 and size else None


def _sizes_that_fit(size: int, pixel_format: str, width: int, height: int) -> list[str]:
    """Pixel formats and sizes a ``size``-byte .raw file would be (for the error message); formats of the
    same camera only (mono or colour: their byte layouts are the same)."""
    family = [f for f in ARENA_PIXEL_FORMATS if bayer_of(f) == bayer_of(pixel_format)]
    fits = [f"{f} at {width}x{height}" for f in family if payload_size(f, width, height) == size]
    n = _pixels_in(size, pixel_format)
    if n is not None:
        if n % width == 0 and n // width != height:
            fits.append(f"{pixel_format} at {width}x{n // width}")
        if n % height == 0 and n // height != width:
            fits.append(f"{pixel_format} at {n // height}x{height}")
    if (width, height) != FULL_FRAME:
        fits += [f"{f} at {FULL_FRAME[0]}x{FULL_FRAME[1]} (a full TRI050S-PC/QC frame)" for f in family
                 if payload_size(f, *FULL_FRAME) == size]
    return fits


def _check_raw_options(path: Path, pixel_format: str | None, width: int | None, height: int | None) -> None:
    missing = [flag for flag, v in (("--pixel-format", pixel_format), ("--width", width), ("--height", height))
               if v is None]
    if missing:
        raise CaptureError(
            f"{path}: a .raw save has no header, so its pixel format and size must be given; missing "
            f"{', '.join(missing)} (e.g. --pixel-format PolarizeMono12p --width {FULL_FRAME[0]} --height "
            f"{FULL_FRAME[1]}: the camera's PixelFormat, Width and Height as ArenaView shows them)")
    if pixel_format not in ARENA_PIXEL_FORMATS:
        raise CaptureError(f"{path}: pixel format {pixel_format!r} is not one of {list(ARENA_PIXEL_FORMATS)}")
    for flag, v in (("--width", width), ("--height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
            raise CaptureError(f"{path}: {flag} must be a positive number of pixels; got {v!r}")


def _read_raw(path: Path, pixel_format: str | None, width: int | None, height: int | None) -> _Stored:
    """A headerless .raw save, decoded by the shared PFNC codec."""
    _check_raw_options(path, pixel_format, width, height)
    assert pixel_format is not None and width is not None and height is not None
    size = path.stat().st_size
    need = payload_size(pixel_format, width, height)
    if size != need:
        fits = _sizes_that_fit(size, pixel_format, width, height)
        raise CaptureError(
            f"{path}: is {size} bytes, but one {pixel_format} frame of {width}x{height} is {need} bytes (a .raw "
            f"save holds exactly one frame); {size} bytes would fit "
            f"{' or '.join(fits) if fits else 'none of the pixel formats at this width or height'}: check "
            "--pixel-format, --width and --height against the camera's PixelFormat, Width and Height")
    try:
        values = unpack_mosaic(path.read_bytes(), pixel_format, width=width, height=height)  # (H, W) uint16
    except ValueError as err:  # PolarizeMono12 holding counts above 4095
        raise CaptureError(f"{path}: {err}; if the counts are high-bit aligned, read it with --pixel-format "
                           "PolarizeMono16 (the import then finds and undoes the shift)") from None
    bits = bit_depth_of(pixel_format)
    return _Stored(values=values, kind=f"{pixel_format} .raw", container_bits=8 if bits == 8 else 16,
                   declared_bits=None if bits == 16 else bits)


def _read_picture(path: Path, pixel_format: str | None) -> _Stored:
    """A single-channel 8/16-bit TIFF or PNG."""
    try:
        image = decode_image(path)
    except ImageError as err:
        raise CaptureError(str(err)) from None
    if image.ndim != 2:
        channels = image.shape[2] if image.ndim == 3 else "?"
        raise CaptureError(f"{path}: has {channels} channels: {_PREVIEW_REASON}; a polarisation mosaic is one "
                           f"channel of counts: {_SAVE_FIX}")
    if image.dtype not in (np.uint8, np.uint16):
        raise CaptureError(f"{path}: pixel type {image.dtype}; sensor counts are 8- or 16-bit unsigned integers: "
                           f"{_SAVE_FIX}")
    name = "TIFF" if path.suffix.lower() in (".tif", ".tiff") else "PNG"
    if pixel_format is not None and pixel_format not in ARENA_PIXEL_FORMATS:
        raise CaptureError(f"{path}: pixel format {pixel_format!r} is not one of {list(ARENA_PIXEL_FORMATS)}")
    eight_bit = pixel_format is not None and bit_depth_of(pixel_format) == 8
    if image.dtype == np.uint8:
        if pixel_format is None:
            raise CaptureError(f"{path}: an 8-bit {name} is usually {_PREVIEW_REASON}; {_SAVE_FIX}. If it really is "
                               "an 8-bit save of the counts (PixelFormat PolarizeMono8, nothing adjusted for "
                               "display), pass --pixel-format PolarizeMono8")
        if not eight_bit:
            raise CaptureError(f"{path}: an 8-bit {name} cannot hold {pixel_format} counts; give --pixel-format "
                               "PolarizeMono8 (BayerRG8 for a colour camera) if it is an 8-bit save, else save the "
                               "frames as 16-bit")
        return _Stored(values=image.astype(np.uint16), kind=f"8-bit {name}", container_bits=8, declared_bits=8)
    if eight_bit:
        raise CaptureError(f"{path}: a 16-bit {name}, but --pixel-format {pixel_format} says 8-bit counts; drop "
                           "--pixel-format (16-bit data are read as they are) or give the format the camera used")
    bits = None if pixel_format is None else bit_depth_of(pixel_format)
    return _Stored(values=image, kind=f"16-bit {name}", container_bits=16, declared_bits=None if bits == 16 else bits)


def _read_stored(path: Path, pixel_format: str | None, width: int | None, height: int | None) -> _Stored:
    suffix = path.suffix.lower()
    if suffix in PREVIEW_SUFFIXES:
        raise CaptureError(f"{path}: a {suffix} file is {_PREVIEW_REASON}; {_SAVE_FIX}")
    if suffix not in ARENA_FRAME_SUFFIXES:
        raise CaptureError(f"{path}: unsupported file type {path.suffix!r}; Arena frames are read from "
                           f"{'/'.join(ARENA_FRAME_SUFFIXES)} files")
    if not path.is_file():
        raise CaptureError(f"{path}: frame not found")
    if suffix in RAW_SUFFIXES:
        return _read_raw(path, pixel_format, width, height)
    stored = _read_picture(path, pixel_format)
    h, w = stored.values.shape
    if (width is not None and width != w) or (height is not None and height != h):
        raise CaptureError(f"{path}: is {w}x{h} but --width/--height say {width}x{height}; drop them (an image file "
                           "has its own size) or give the right ones")
    return stored


# --- bit depth and shift -------------------------------------------------------------------------


def _trailing_zero_bits(value: int) -> int:
    """Number of low zero bits of ``value`` (16 for 0)."""
    return 16 if value == 0 else (value & -value).bit_length() - 1


def _bit_depth_and_shift(values: Sequence[np.ndarray], paths: Sequence[Path],
                         stored: _Stored) -> tuple[int, int, list[str]]:
    """The bit depth of the counts and the left shift they were stored with, found jointly over
    every frame (K arrays (H, W), read from ``paths``), and the notes that say so. Raises
    CaptureError for counts that cannot be the declared format."""
    if stored.container_bits == 8:
        return 8, 0, []
    highs = [int(v.max()) for v in values]
    ors = [int(np.bitwise_or.reduce(v, axis=None)) for v in values]  # every bit set in some count of a frame
    hi = max(highs)
    zeros = _trailing_zero_bits(int(np.bitwise_or.reduce(ors)))
    if stored.declared_bits is not None:  # the format says how many bits (12 here)
        bits = stored.declared_bits
        if hi <= max_count(bits):
            return bits, 0, []
        if zeros < 16 - bits:
            step = 1 << (16 - bits)
            top, odd = paths[highs.index(hi)], paths[next(i for i, o in enumerate(ors) if o % step)]
            where = "not all" if odd == top else f"with counts in {odd.name} that are not"
            raise CaptureError(
                f"{top}: counts up to {hi}, {where} multiples of {step}: these are not {bits}-bit counts (low-bit "
                f"aligned ones stay <= {max_count(bits)}; high-bit aligned ones are multiples of {step}); drop "
                "--pixel-format, or give the format the camera used")
        shift = 16 - bits
    elif shift := left_shift_of(values):
        bits = 16 - shift
    else:
        notes = []
        if hi <= MAX_12BIT:
            notes.append(f"{stored.kind}: the largest count is {hi} (<= {MAX_12BIT}): kept as 16-bit counts (full "
                         f"scale 65535); if they are low-bit aligned 12-bit counts, import with --pixel-format "
                         "PolarizeMono12 so that full scale is 4095")
        return 16, 0, notes
    note = (f"{stored.kind}: every count is a multiple of {1 << shift} and the largest is {hi}: {bits}-bit counts "
            f"stored left-shifted by {shift} (high-bit aligned in 16 bits); shifted right by {shift}, "
            f"camera.bit_depth {bits}")
    return bits, shift, [note]


def read_arena_frame(
    path: str | os.PathLike[str],
    *,
    pixel_format: str | None = None,
    width: int | None = None,
    height: int | None = None,
) -> ArenaFrame:
    """Read one Arena / ArenaView save (module docstring) as low-bit aligned sensor counts.

    Args:
        path: a ``.raw``, ``.tif``/``.tiff`` or ``.png`` file.
        pixel_format: one of :data:`ARENA_PIXEL_FORMATS`. Required for ``.raw``; for an image,
            ``PolarizeMono8`` accepts an 8-bit file and ``PolarizeMono12`` (or 12p, 12Packed) says
            16-bit values are 12-bit counts (low-bit aligned, or shifted left by 4).
        width, height: pixels; required for ``.raw``, checked against an image's size if given.

    Returns:
        :class:`ArenaFrame` ``(counts (H, W) uint16, bit_depth, notes, shift)``; a detected left
        shift is undone, logged and stated in ``notes``.

    Raises:
        CaptureError: a BMP/JPEG or colour image, an 8-bit image without ``PolarizeMono8``, a
            ``.raw`` file without its format and size or whose size does not match them (the message
            lists the sizes that would fit), counts the declared format cannot hold.

    Example:
        >>> frame = read_arena_frame("img.raw", pixel_format="PolarizeMono12p", width=2448, height=2048)  # doctest: +SKIP
        >>> frame.counts.shape, frame.bit_depth  # doctest: +SKIP
        ((2048, 2448), 12)
    """
    path = Path(path)
    stored = _read_stored(path, pixel_format, width, height)
    bits, shift, notes = _bit_depth_and_shift([stored.values], [path], stored)
    for note in notes:
        logger.info("%s: %s", path, note)
    return ArenaFrame(counts=stored.values >> shift, bit_depth=bits, notes=tuple(notes), shift=shift)


# --- import --------------------------------------------------------------------------------------


def _natural_key(path: Path) -> list[Any]:
    """Sort key: digit runs compare as numbers (``img_2`` before ``img_10``)."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def _frames_in_folder(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file()]
    frames = [p for p in files if p.suffix.lower() in ARENA_FRAME_SUFFIXES]
    previews = [p for p in files if p.suffix.lower() in PREVIEW_SUFFIXES]
    if not frames:
        if previews:
            raise CaptureError(f"{folder}: holds only {previews[0].suffix} files ({previews[0].name}, ...): "
                               f"{_PREVIEW_REASON}; {_SAVE_FIX}")
        raise CaptureError(f"{folder}: holds no {'/'.join(ARENA_FRAME_SUFFIXES)} frames; give the folder the Arena "
                           "saves are in, or the frame files")
    kinds = sorted({".tif" if p.suffix.lower() == ".tiff" else p.suffix.lower() for p in frames})
    if len(kinds) > 1:
        raise CaptureError(f"{folder}: holds frames of several kinds ({', '.join(kinds)}); give the files of one "
                           "kind, in light order, instead of the folder")
    if previews:
        logger.info("%s: ignoring %d preview file(s) (%s, ...)", folder, len(previews), previews[0].name)
    frames.sort(key=_natural_key)
    logger.info("%s: %d frame(s) in name order: %s", folder, len(frames), ", ".join(p.name for p in frames[:8]))
    return frames


def _frame_paths(frames: str | os.PathLike[str] | Iterable[str | os.PathLike[str]]) -> list[Path]:
    """A folder (its frames sorted by name, digits as numbers) or frame files in light order."""
    items = [Path(frames)] if isinstance(frames, (str, os.PathLike)) else [Path(f) for f in frames]
    if not items:
        raise CaptureError("no frames given: give the folder of Arena saves, or the frame files in light order")
    if len(items) == 1 and items[0].is_dir():
        return _frames_in_folder(items[0])
    seen: set[Path] = set()
    for path in items:
        if path.is_dir():
            raise CaptureError(f"{path}: is a folder; give either one folder of frames or frame files, not both")
        if not path.is_file():
            raise CaptureError(f"{path}: frame not found")
        if path.resolve() in seen:
            raise CaptureError(f"{path}: given twice; give each frame once, in light order")
        seen.add(path.resolve())
    return items


def _read_all(paths: list[Path], pixel_format: str | None, width: int | None,
              height: int | None) -> tuple[list[np.ndarray], _Stored]:
    """Every frame's stored values (K arrays (H, W)), checked for one size and one kind."""
    first: _Stored | None = None
    values = []
    for path in paths:
        stored = _read_stored(path, pixel_format, width, height)
        if first is None:
            first = stored
            h, w = stored.values.shape
            if h % 2 or w % 2:
                raise CaptureError(f"{path}: is {w}x{h}; a polarisation mosaic needs even width and height (whole 2x2 "
                                   "super-pixels): save the full frame, or a ROI with even size and offset")
        elif stored.values.shape != first.values.shape or stored.kind != first.kind:
            raise CaptureError(f"{path}: is a {stored.kind} of {stored.values.shape[1]}x{stored.values.shape[0]} but "
                               f"{paths[0].name} is a {first.kind} of {first.values.shape[1]}x"
                               f"{first.values.shape[0]}; all frames must come from one camera setting")
        values.append(stored.values)
    assert first is not None
    return values, first


def import_arena(
    frames: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    *,
    lights: str | os.PathLike[str],
    light_frame: LightFrame,
    light_format: LightFileFormat = "auto",
    intensities: str | os.PathLike[str] | None = None,
    pixel_format: str | None = None,
    width: int | None = None,
    height: int | None = None,
    black_level: float = 0.0,
    intrinsics: tuple[float, float, float, float] | None = None,
    overwrite: bool = False,
) -> Capture:
    """Convert Arena / ArenaView saves (module docstring), one per light, into a capture folder.

    Args:
        frames: a folder (its ``.raw``/``.tif``/``.tiff``/``.png`` files sorted by name, digit
            runs as numbers) or the frame files in light order.
        out: the capture folder to create (never a source file or a folder holding one).
        lights: the light file (``x y z`` lines or RTI ``.lp``; see
            :func:`~polarshape.io.importers.read_light_file`).
        light_frame: its frame, ``"opencv"`` (ours) or ``"diligent"`` (y up, z to the viewer);
            never guessed.
        light_format: ``"auto"`` (by suffix), ``"xyz"`` or ``"lp"``.
        intensities: optional file of one intensity (or ``r g b``) per light, in the light file's
            order; default 1 each.
        pixel_format, width, height: as :func:`read_arena_frame` (the same for every frame).
        black_level: dark counts, in counts of the imported bit depth (after any shift).
        intrinsics: ``(fx, fy, cx, cy)`` pinhole intrinsics in raw-mosaic pixels (perspective
            camera); None: orthographic.
        overwrite: replace an existing ``out``.

    Returns:
        The :class:`Capture` written (frames (K, H, W) ``uint16`` low-bit aligned; ``root`` =
        ``out``); ``ground_truth["source"]`` records the files, the shift found and the notes.

    Raises:
        OutputExistsError: ``out`` exists (without ``overwrite``), or is / holds a source; checked first.
        CaptureError: anything :func:`read_arena_frame` refuses, frames of different sizes or
            kinds, a light file that does not fit the frames (count, names, frame), a bad
            intensity, black level or intrinsics.
    """
    out = Path(out)
    paths = _frame_paths(frames)
    light_path = Path(lights)
    extra = [light_path] + ([Path(intensities)] if intensities is not None else [])
    check_import_destination(paths + extra, out, overwrite=overwrite)
    light_file = read_light_file(light_path, frame=light_frame, format=light_format)
    order = match_light_order(light_file, [p.name for p in paths])
    check_camera_side(light_file)
    if intensities is not None:
        light_intensities = read_diligent_intensities(intensities, len(light_file))[order]
    else:
        light_intensities = np.ones(len(paths))
        logger.info("no intensities given; every light has intensity 1")

    values, stored = _read_all(paths, pixel_format, width, height)
    where = f"{paths[0].parent if len({p.parent for p in paths}) == 1 else paths[0]} ({len(paths)} frames)"
    bits, shift, notes = _bit_depth_and_shift(values, paths, stored)
    for note in notes:
        logger.info("%s: %s", where, note)
    counts = np.stack([v >> shift for v in values])  # (K, H, W) uint16, low-bit aligned
    k, h, w = counts.shape

    model = f"imported Lucid Arena/ArenaView saves ({stored.kind}): {bits}-bit counts"
    if shift:
        model += f", stored left-shifted by {shift} bits (high-bit aligned) and shifted right by {shift} on import"
    camera: dict[str, Any] = {"model": model, "projection": "orthographic", "bit_depth": bits,
                              "black_level": float(black_level)}
    if pixel_format is not None and bayer_of(pixel_format) is not None:  # a colour camera's raw mosaic
        camera["mosaic"] = {"bayer": bayer_of(pixel_format)}
    if intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        camera.update(projection="perspective", intrinsics={"fx": fx, "fy": fy, "cx": cx, "cy": cy})
    spec = parse_capture_spec({
        "format": CAPTURE_FORMAT,
        "camera": camera,
        "lights": [
            {"direction": [float(c) for c in light_file.directions[i]], "intensity": float(e),
             "frame": f"frames/{n:03d}.png"}
            for n, (i, e) in enumerate(zip(order, light_intensities, strict=True))
        ],
    }, f"{out} (import of {where})")
    source = {
        "importer": "arena",
        "frames": [str(p.resolve()) for p in paths],
        "stored_as": stored.kind,
        "pixel_format": pixel_format,
        "stored_max_count": int(max(int(v.max()) for v in values)),
        "left_shift": shift,
        "bit_depth": bits,
        "light_file": str(light_path.resolve()),
        "light_frame": light_frame,
        "light_order": [int(i) for i in order],
        "intensities": None if intensities is None else str(Path(intensities).resolve()),
        "notes": notes,
    }
    capture = Capture(spec=spec, frames=counts, ground_truth={"source": source})
    write_capture(out, capture, overwrite=overwrite)
    capture.root = out.resolve()
    logger.info("imported %d Arena frame(s) (%s) into %s: %dx%d, %d-bit%s", k, stored.kind, out, w, h, bits,
                f", left shift {shift} undone" if shift else "")
    return capture

