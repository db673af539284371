"""Already-demosaiced polariser stacks (four images per light at 0°, 45°, 90°, 135°) → capture folders.

Camera SDKs and tools such as polanalyser hand out a polarisation camera's data as four polariser
images per light instead of the raw mosaic. A stack folder holds, for every light, **one** of::

    src/
      001_0.png  001_45.png  001_90.png  001_135.png    four single-channel images (.png/.tif/.tiff),
      002_0.png  …                                      <light>_<angle>.<ext>; the angle may be
                                                        zero-padded (000, 045, 090) and the
                                                        separator '-' (polanalyser's example writes
                                                        name-000.png)
    or
      001.npy  002.npy  …                               (4, H, W) or (H, W, 4) arrays, channels in
                                                        the order 0, 45, 90, 135
      001.tif  002.tif  …                               4-page TIFFs, one single-channel page per
                                                        angle, in the order 0, 45, 90, 135
      mask.png                                          optional object mask at the images' size

All lights of a folder use one form. Lights are taken in natural order of ``<light>`` (``2`` before
``10``). Pixels are ``uint8`` or ``uint16`` counts; a float ``.npy`` holds fractions of full scale
in [0, 1] and needs ``bit_depth`` (counts = round(v · (2^bit_depth − 1))). Colour images, a
4-channel (interleaved) TIFF — OpenCV reads those as BGRA and may apply their alpha, so the order
of the channels cannot be trusted —, missing or repeated angles and images of different sizes are
refused, each naming the file and the fix.

What the import does, and why:

- **Angles.** ``angles`` says in which convention the labels 0/45/90/135 are measured
  (:mod:`polarshape.imaging.mosaic`): ``counterclockwise_on_screen`` (the default: the maker's,
  which camera SDKs use), ``polanalyser`` (as polanalyser's ``demosaicing`` labels its outputs; the
  same direction as the maker's) or ``clockwise_on_screen`` (ours: from image x toward image y,
  down). The image labelled a is the polariser at our angle a (clockwise) or −a (the others).
- **Mosaic.** Each stack pixel becomes one 2×2 super-pixel of a raw mosaic in the default camera
  mosaic (:class:`~polarshape.io.capture.MosaicSpec`: the IMX250MZR's maker layout [[90, 45],
  [135, 0]], counter-clockwise on screen), each site holding the image of its polariser angle —
  the mosaic the camera would have recorded, had the four values been seen at one point. So
  ``preprocess.demosaic: superpixel`` gives back exactly the stack's four values; run imported
  captures with it (the bilinear demosaic would interpolate between neighbouring stack pixels).
- **Lights.** Directions come from a light file (:func:`~polarshape.io.importers.read_light_file`:
  ``x y z`` lines or RTI ``.lp``, in the frame given — never guessed), one per light in the
  lights' order; an ``.lp`` file naming every light's ``<light>`` goes by name. Intensities are 1
  unless a file of one value (or ``r g b``) per line gives them (DiLiGenT's
  ``light_intensities.txt``).
- **Sizes.** The capture's super-pixel grid is the stack's pixel grid: ``mask.png`` keeps the
  stack's size (H, W); frames are (2H, 2W). The camera is orthographic; edit ``capture.yaml`` for
  a perspective one (intrinsics in raw-mosaic pixels: twice the stack's).
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from polarshape.errors import CaptureError
from polarshape.imaging.mosaic import CHANNEL_ANGLES_DEG, MAKER_ANGLES, MakerAngles, mosaic_from_intensities, our_angle_deg
from polarshape.imaging.pixels import BIT_DEPTHS, max_count
from polarshape.io.images import ImageError, decode_image
from polarshape.io.capture import CAPTURE_FORMAT, Capture, CaptureSpec, MosaicSpec, write_capture
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

__all__ = ["STACK_CAMERA_MODEL", "STACK_LABELS_DEG", "Stack", "import_stack", "read_stack"]

#: The labels of a stack's four images, in the order of a 4-channel file.
STACK_LABELS_DEG: tuple[int, int, int, int] = (0, 45, 90, 135)

#: ``camera.model`` of an imported capture: what the frames are.
STACK_CAMERA_MODEL = ("imported polariser stack: demosaiced 0/45/90/135 images, each pixel stored as one 2x2 "
                      "super-pixel of the default mosaic (run with preprocess.demosaic: superpixel)")

MASK_PNG = "mask.png"
_SINGLE_SUFFIXES = (".png", ".tif", ".tiff")
_STACK_SUFFIXES = (".npy", ".tif", ".tiff")
_ANGLE_NAME = re.compile(r"^(?P<light>.+?)[_-](?P<angle>0|00|000|45|045|90|090|135)(?P<ext>\.(?:png|tiff?))$",
                         re.IGNORECASE)
_NAMING = ("<light>_<angle>.png (angle 0, 45, 90 or 135; .tif/.tiff too), or one <light>.npy / 4-page <light>.tif "
           "per light")


@dataclass(frozen=True)
class Stack:
    """A stack folder read into memory.

    Attributes:
        images: (K, 4, H, W) ``uint16`` counts, labels 0, 45, 90, 135 (as labelled in the files).
        lights: the K ``<light>`` names, in order.
        files: per light, the file(s) read (names inside the folder).
        form: ``"images"`` (four files per light) or ``"stacks"`` (one file per light).
        bit_depth: the bit depth of the counts.
    """

    images: np.ndarray
    lights: tuple[str, ...]
    files: tuple[tuple[str, ...], ...]
    form: str
    bit_depth: int


def _natural_key(name: str) -> list[Any]:
    """``2`` before ``10``: digits compare as numbers."""
    return [(0, int(part), part) if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", name)]


def _classify(src: Path) -> tuple[dict[str, dict[int, str]], dict[str, str]]:
    """The folder's image files: {light: {label: name}} of single images, {light: name} of stacks."""
    singles: dict[str, dict[int, str]] = {}
    stacks: dict[str, str] = {}
    for path in sorted(src.iterdir(), key=lambda p: _natural_key(p.name)):
        name, suffix = path.name, path.suffix.lower()
        if not path.is_file() or name.startswith(".") or name.lower() == MASK_PNG:
            continue
        match = _ANGLE_NAME.match(name)
        if match:
            light, label = match["light"], int(match["angle"])
            seen = singles.setdefault(light, {})
            if label in seen:
                raise CaptureError(f"{src / name}: the {label}° image of light {light!r} is also {seen[label]}; give "
                                   "each angle of a light once (remove one of them)")
            seen[label] = name
        elif suffix in _STACK_SUFFIXES:
            light = path.stem
            if light in stacks:
                raise CaptureError(f"{src / name}: light {light!r} is also {stacks[light]}; give each light once")
            stacks[light] = name
        elif suffix in _SINGLE_SUFFIXES:
            raise CaptureError(f"{src / name}: a {suffix} file without an angle in its name; name each polariser "
                               f"image {_NAMING}, or move the file out of {src}")
    return singles, stacks


def _read_single(path: Path) -> np.ndarray:
    """(H, W) uint8/uint16 polariser image."""
    try:
        image = decode_image(path)
    except ImageError as err:
        raise CaptureError(str(err)) from None
    if image.ndim != 2:
        raise CaptureError(f"{path}: a colour image ({image.shape[2]} channels); a polariser image must be one grey "
                           "channel (a mono polarisation camera; for a colour one, import one colour channel or "
                           "its luminance as grey)")
    if image.dtype not in (np.uint8, np.uint16):
        raise CaptureError(f"{path}: pixel type {image.dtype}; 8- or 16-bit unsigned counts expected")
    return image


def _read_tiff_stack(path: Path) -> np.ndarray:
    """(4, H, W) from a 4-page TIFF."""
    ok, pages = cv2.imreadmulti(str(path), flags=cv2.IMREAD_UNCHANGED)
    if not ok or not pages:
        raise CaptureError(f"{path}: cannot be decoded as a TIFF (corrupt, or not a TIFF file)")
    if len(pages) == 1 and pages[0].ndim == 3 and pages[0].shape[2] == 4:
        raise CaptureError(f"{path}: a 4-channel (interleaved) TIFF: OpenCV reads those as BGRA and may apply the "
                           "4th channel as alpha, so the angles' order cannot be trusted; save the light as a "
                           "4-page TIFF (one page per angle 0, 45, 90, 135), a (4, H, W) .npy, or four images "
                           f"{path.stem}_0{path.suffix} … {path.stem}_135{path.suffix}")
    if len(pages) != 4 or any(p.ndim != 2 for p in pages):
        shapes = [tuple(p.shape) for p in pages]
        raise CaptureError(f"{path}: {len(pages)} page(s) of shape {shapes}; a light's TIFF must hold 4 single-channel "
                           f"pages (angles 0, 45, 90, 135); for one polariser image name it {path.stem}_<angle>"
                           f"{path.suffix}")
    return np.stack(pages)


def _read_npy(path: Path, bit_depth: int | None) -> np.ndarray:
    """(4, H, W) uint8/uint16 from a (4, H, W) or (H, W, 4) array (floats in [0, 1] scaled by bit_depth)."""
    try:
        data = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as err:
        raise CaptureError(f"{path}: cannot be read as NPY ({err})") from None
    if data.ndim == 3 and data.shape[0] == 4:
        stack = data
    elif data.ndim == 3 and data.shape[2] == 4:
        stack = np.moveaxis(data, -1, 0)
    else:
        raise CaptureError(f"{path}: shape {data.shape}; a light's array must be (4, H, W) or (H, W, 4), angles "
                           "0, 45, 90, 135 in that order")
    if stack.dtype in (np.uint8, np.uint16):
        return np.ascontiguousarray(stack)
    if not np.issubdtype(stack.dtype, np.floating):
        raise CaptureError(f"{path}: pixel type {stack.dtype}; uint8/uint16 counts, or floats in [0, 1] expected")
    if bit_depth is None:
        raise CaptureError(f"{path}: holds floats ({stack.dtype}); give the bit depth they are fractions of "
                           "(--bit-depth N: counts = round(value * (2**N - 1))), or save uint8/uint16 counts")
    if not np.isfinite(stack).all() or stack.min() < 0 or stack.max() > 1:
        raise CaptureError(f"{path}: float values must be finite fractions of full scale in [0, 1]; got "
                           f"[{np.nanmin(stack):.4g}, {np.nanmax(stack):.4g}] (NaN or inf: "
                           f"{not np.isfinite(stack).all()}); scale them, or save integer counts")
    return np.rint(stack.astype(np.float64) * max_count(bit_depth)).astype(np.uint16)


def _check_bit_depth(bit_depth: int | None) -> None:
    if bit_depth is not None and bit_depth not in BIT_DEPTHS:
        raise CaptureError(f"bit_depth (--bit-depth) {bit_depth} is not one of {BIT_DEPTHS} (significant bits of "
                           "the counts)")


def read_stack(src: str | os.PathLike[str], *, bit_depth: int | None = None) -> Stack:
    """Read a stack folder (module docstring) as it is labelled.

    Args:
        src: the folder (read only).
        bit_depth: significant bits of the counts; None: 8 for ``uint8`` files, 16 for ``uint16``
            (required for float ``.npy`` files).

    Returns:
        :class:`Stack`: ``images`` (K, 4, H, W) ``uint16`` in label order 0, 45, 90, 135.

    Raises:
        CaptureError: no images, both forms in one folder, a missing or repeated angle, a colour or
            interleaved 4-channel image, images of different sizes or pixel types, counts above
            ``bit_depth``; each names the file and the fix.
    """
    src = Path(src)
    if not src.is_dir():
        raise CaptureError(f"{src}: not a folder; give a folder of polariser images ({_NAMING})")
    _check_bit_depth(bit_depth)
    singles, stacks = _classify(src)
    if singles and stacks:
        one, other = next(iter(singles.values())), next(iter(stacks.values()))
        raise CaptureError(f"{src}: holds both single polariser images ({next(iter(one.values()))}) and per-light "
                           f"stacks ({other}); use one form for every light (move the others out)")
    if not singles and not stacks:
        raise CaptureError(f"{src}: no polariser images; name them {_NAMING}")

    names: list[str] = sorted(singles or stacks, key=_natural_key)
    per_light: list[np.ndarray] = []
    files: list[tuple[str, ...]] = []
    for light in names:
        if singles:
            found = singles[light]
            missing = [a for a in STACK_LABELS_DEG if a not in found]
            if missing:
                raise CaptureError(f"{src}: light {light!r} has no {', '.join(f'{a}°' for a in missing)} image "
                                   f"(found {', '.join(found[a] for a in sorted(found))}); give four images "
                                   f"{light}_0, {light}_45, {light}_90, {light}_135 (same suffix)")
            group = tuple(found[a] for a in STACK_LABELS_DEG)
            images = [_read_single(src / name) for name in group]
            for name, image in zip(group[1:], images[1:]):
                if image.shape != images[0].shape or image.dtype != images[0].dtype:
                    raise CaptureError(f"{src / name}: is {image.dtype} {image.shape[1]}x{image.shape[0]} but "
                                       f"{group[0]} is {images[0].dtype} {images[0].shape[1]}x{images[0].shape[0]}; "
                                       "all images must have one size and pixel type")
            stack = np.stack(images)
        else:
            group = (stacks[light],)
            path = src / group[0]
            stack = _read_npy(path, bit_depth) if path.suffix.lower() == ".npy" else _read_tiff_stack(path)
        if per_light and (stack.shape != per_light[0].shape or stack.dtype != per_light[0].dtype):
            first, h, w = files[0][0], *per_light[0].shape[1:]
            raise CaptureError(f"{src / group[0]}: is {stack.dtype} {stack.shape[2]}x{stack.shape[1]} but {first} is "
                               f"{per_light[0].dtype} {w}x{h}; all lights must have one size and pixel type")
        per_light.append(stack)
        files.append(group)

    dtype = per_light[0].dtype
    depth = bit_depth if bit_depth is not None else (8 if dtype == np.uint8 else 16)
    if dtype == np.uint8 and depth > 8:
        raise CaptureError(f"{src / files[0][0]}: 8-bit images but bit_depth {depth}: 8 bits cannot hold {depth}-bit "
                           "counts (the data were probably scaled down); give 16-bit images or --bit-depth 8")
    top = max_count(depth)
    for light_files, stack in zip(files, per_light):
        hi = int(stack.max())
        if hi > top:
            raise CaptureError(f"{src / light_files[0]}: holds counts up to {hi}, above {top} = 2**{depth} - 1 for "
                               f"bit depth {depth}: give the bit depth of the data (--bit-depth), or shift high-bit "
                               f"aligned counts right by {16 - depth} bits")
    images = np.stack(per_light).astype(np.uint16)  # (K, 4, H, W)
    form = "images" if singles else "stacks"
    logger.info("read %d light(s) of %s from %s: %dx%d, %d-bit", len(names), form, src, images.shape[3],
                images.shape[2], depth)
    return Stack(images=images, lights=tuple(names), files=tuple(files), form=form, bit_depth=depth)


def _to_our_order(images: np.ndarray, angles: str) -> np.ndarray:
    """(K, 4, H, W) in label order 0, 45, 90, 135 (convention ``angles``) → our channel order."""
    ours = [CHANNEL_ANGLES_DEG.index(our_angle_deg(label, angles)) for label in STACK_LABELS_DEG]  # label -> channel
    out = np.empty_like(images)
    for label_index, channel in enumerate(ours):
        out[:, channel] = images[:, label_index]
    return out


def _read_mask(src: Path, shape: tuple[int, int]) -> np.ndarray | None:
    path = src / MASK_PNG
    if not path.is_file():
        return None
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise CaptureError(f"{path}: object mask cannot be decoded as an image")
    if mask.shape[:2] != shape:
        raise CaptureError(f"{path}: is {mask.shape[1]}x{mask.shape[0]} but the polariser images are "
                           f"{shape[1]}x{shape[0]}; give the mask at the images' size")
    return (mask != 0) if mask.ndim == 2 else (mask != 0).any(axis=-1)


def import_stack(
    src: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    lights: str | os.PathLike[str],
    light_frame: LightFrame,
    light_format: LightFileFormat = "auto",
    intensities: str | os.PathLike[str] | None = None,
    angles: MakerAngles = "counterclockwise_on_screen",
    bit_depth: int | None = None,
    overwrite: bool = False,
) -> Capture:
    """Convert a folder of demosaiced polariser images (module docstring) into a capture folder, atomically.

    Args:
        src: the stack folder (read only).
        out: the capture folder to create (never the source or a folder holding it).
        lights: the light file (``x y z`` lines or RTI ``.lp``), one light per stack light.
        light_frame: its frame: ``"opencv"`` (ours) or ``"diligent"`` (y up, z toward the viewer).
        light_format: ``"auto"`` (by suffix), ``"xyz"`` or ``"lp"``.
        intensities: optional file of one intensity (or ``r g b``) per light; else all 1.
        angles: the convention of the labels 0/45/90/135 (:data:`~polarshape.imaging.mosaic.MAKER_ANGLES`).
        bit_depth: significant bits of the counts (default: 8 for 8-bit files, 16 for 16-bit).
        overwrite: replace an existing ``out``.

    Returns:
        The :class:`Capture` written: frames (K, 2H, 2W) for (H, W) images, the default mosaic,
        orthographic; ``root`` = ``out``.

    Raises:
        OutputExistsError: ``out`` exists (without ``overwrite``), or is / holds ``src``; checked first.
        CaptureError: a malformed folder or light file (named, with the fix), a count mismatch, a
            light behind the object.

    Example:
        >>> import_stack("stack", "capture", lights="lights.txt", light_frame="diligent")  # doctest: +SKIP
    """
    src, out = Path(src), Path(out)
    if not src.is_dir():
        raise CaptureError(f"{src}: not a folder; give a folder of polariser images ({_NAMING})")
    check_import_destination([src], out, overwrite=overwrite)
    if angles not in MAKER_ANGLES:
        raise CaptureError(f"angles (--angles) {angles!r} is not one of {MAKER_ANGLES}: the convention the labels "
                           "0/45/90/135 are measured in")
    stack = read_stack(src, bit_depth=bit_depth)
    k, _, h, w = stack.images.shape
    light_file = read_light_file(lights, frame=light_frame, format=light_format)
    keys = [f"{name}{Path(files[0]).suffix}" for name, files in zip(stack.lights, stack.files)]
    order = match_light_order(light_file, keys)  # count checked here, naming the light file
    check_camera_side(light_file)
    directions = light_file.directions[order]
    values = read_diligent_intensities(intensities, k) if intensities is not None else np.ones(k)

    mosaic = MosaicSpec()
    channels = _to_our_order(stack.images, angles)  # (K, 4, H, W), our 0°, 45°, 90°, 135°
    frames = mosaic_from_intensities(torch.from_numpy(channels.astype(np.int32)), mosaic.to_layout())  # (K, 2H, 2W)
    spec = CaptureSpec.model_validate({
        "format": CAPTURE_FORMAT,
        "camera": {"model": STACK_CAMERA_MODEL, "projection": "orthographic", "bit_depth": stack.bit_depth,
                   "mosaic": mosaic.model_dump(mode="json")},
        "lights": [
            {"direction": [float(c) for c in d], "intensity": float(e), "frame": f"frames/{i:03d}.png"}
            for i, (d, e) in enumerate(zip(directions, values, strict=True))
        ],
    })
    source = {
        "importer": "stack",
        "source": str(src.resolve()),
        "polarisation": True,
        "frames": "demosaiced polariser images; each stack pixel stored as one 2x2 super-pixel of the default mosaic",
        "form": stack.form,
        "lights": list(stack.lights),
        "files": [list(f) for f in stack.files],
        "angles": angles,
        "light_file": str(Path(lights).resolve()),
        "light_frame": light_frame,
        "intensities": None if intensities is None else str(Path(intensities).resolve()),
        "max_count": max_count(stack.bit_depth),
    }
    capture = Capture(spec=spec, frames=frames.numpy().astype(np.uint16), mask=_read_mask(src, (h, w)),
                      ground_truth={"source": source})
    write_capture(out, capture, overwrite=overwrite)
    capture.root = out.resolve()
    logger.info("imported %s into %s: %d lights, %dx%d pixels, %d-bit, labels %s, mask %s", src, out, k, w, h,
                stack.bit_depth, angles, "yes" if capture.mask is not None else "no")
    return capture
