"""DiLiGenT-style photometric-stereo folders → polarshape capture folders.

A DiLiGenT-style folder (the DiLiGenT benchmark's ``*PNG`` folders, and the many data sets laid
out like it)::

    src/
      001.png … 096.png        one image per light (8/16-bit, RGB or grey, linear)
      filenames.txt            optional: the images in light order (else the numbered PNGs, in order)
      light_directions.txt     K lines 'x y z', DiLiGenT's frame (x right, y up, z toward the viewer)
      light_intensities.txt    optional: K lines 'r g b' (or one value), per-channel light intensity
      mask.png                 optional: object mask, non-zero = object
      Normal_gt.mat / .npy     optional: (H, W, 3) ground-truth normals, the lights' frame

What the import does, and why:

- **Frame.** DiLiGenT's ``(x, y, z)`` (y up, z to the viewer) is ours ``(x, -y, -z)`` (OpenCV: y
  down, z into the scene; light directions surface → light, so a camera-side light has z < 0).
  Lights and normals are converted the same way (``light_frame="opencv"`` if the folder is
  already in ours).
- **Colour → mono.** ``mono = w_r R + w_g G + w_b B`` with :data:`DEFAULT_RGB_WEIGHTS` (Rec. 709
  luminance of linear RGB; normalised to sum 1), and each light's ``(r, g, b)`` intensity becomes
  ``w · (r, g, b)`` by the same weights. This is exact for grey objects (or equal channel
  intensities); otherwise it is the usual luminance approximation. A pixel clipped in any channel
  is stored at full scale, so recovery treats it as saturated. Grey images are taken as they are.
- **No polariser.** A capture frame is a polarisation mosaic; these images are plain intensity.
  Each source pixel becomes one 2×2 super-pixel whose four sites are equal, so the super-pixel
  Stokes vector is ``(2 I, 0, 0)``: DoLP exactly 0, and recovery finds no polarisation and runs on
  intensity only. The capture's ``camera.model`` says so, and ``ground_truth/source.json`` records
  the source folder, the weights and the frame. Run such a capture with
  ``preprocess.demosaic: superpixel``: the bilinear demosaic interpolates the four polariser
  images from sites half a pixel apart, which blurs s0 and adds a spurious s1, s2 at edges.
- **Sizes.** The capture's super-pixel grid is the source's pixel grid: ``mask.png`` and
  ``ground_truth/normals.npy`` keep the source size (``(H, W)``; frames are ``(2H, 2W)``). The
  camera is orthographic (DiLiGenT's assumption; distant lights).
"""

from __future__ import annotations

import logging
import math
import os
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from polarshape.errors import CaptureError
from polarshape.imaging.pixels import max_count
from polarshape.io.capture import CAPTURE_FORMAT, Capture, CaptureSpec, write_capture
from polarshape.io.importers.destination import check_import_destination
from polarshape.io.importers.lightfiles import LightFrame, check_camera_side, from_diligent_frame, read_light_file

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_RGB_WEIGHTS",
    "DILIGENT_CAMERA_MODEL",
    "import_diligent",
    "read_diligent_intensities",
    "rgb_to_mono",
]

#: Weights of R, G, B in the mono image and intensity: Rec. 709 / sRGB luminance of linear RGB.
DEFAULT_RGB_WEIGHTS: tuple[float, float, float] = (0.2126, 0.7152, 0.0722)

#: ``camera.model`` of an imported capture: what the frames are.
DILIGENT_CAMERA_MODEL = ("imported DiLiGenT-style folder: plain intensity images, no polariser (each pixel stored as "
                         "one 2x2 super-pixel of four equal sites, DoLP 0)")

FILENAMES_TXT = "filenames.txt"
DIRECTIONS_TXT = "light_directions.txt"
INTENSITIES_TXT = "light_intensities.txt"
MASK_PNG = "mask.png"
NORMALS_NAMES = ("Normal_gt.npy", "Normal_gt.mat")
_NUMBERED_PNG = re.compile(r"^\d+\.png$", re.IGNORECASE)


def _weights(rgb_weights: tuple[float, float, float]) -> np.ndarray:
    w = np.asarray(rgb_weights, dtype=np.float64)
    if w.shape != (3,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
        raise CaptureError(f"rgb_weights: must be three non-negative numbers (R, G, B) with a positive sum, e.g. "
                           f"{list(DEFAULT_RGB_WEIGHTS)}; got {list(np.ravel(w))}")
    return w / w.sum()


def rgb_to_mono(image: np.ndarray, rgb_weights: tuple[float, float, float] = DEFAULT_RGB_WEIGHTS) -> np.ndarray:
    """One intensity per pixel from an (H, W) grey or (H, W, 3) **RGB-ordered** image.

    Args:
        image: (H, W) or (H, W, 3) ``uint8``/``uint16``, linear counts, channels R, G, B.
        rgb_weights: weights of R, G, B (normalised to sum 1).

    Returns:
        (H, W) of the input dtype: ``round(w · rgb)``; a pixel with any channel at the dtype's top
        count is set to the top count (clipped, so recovery treats it as saturated).
    """
    if image.ndim == 2:
        return image
    top = np.iinfo(image.dtype).max
    mono = np.rint(image.astype(np.float64) @ _weights(rgb_weights))  # (H, W)
    mono[(image >= top).any(axis=-1)] = top
    return np.clip(mono, 0, top).astype(image.dtype)


def _read_foreign_image(path: Path, what: str) -> np.ndarray:
    """(H, W) or (H, W, 3) RGB-ordered uint8/uint16 (OpenCV reads BGR; alpha dropped)."""
    if not path.is_file():
        raise CaptureError(f"{path}: {what} not found")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CaptureError(f"{path}: {what} cannot be decoded as an image (corrupt, or not a {path.suffix} file)")
    if image.dtype not in (np.uint8, np.uint16):
        raise CaptureError(f"{path}: {what} has pixel type {image.dtype}; 8- or 16-bit unsigned integers expected")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] in (3, 4):
        image = image[:, :, 2::-1]  # BGR(A) -> RGB
    elif image.ndim != 2:
        raise CaptureError(f"{path}: {what} has shape {image.shape}; a grey or RGB image expected")
    return np.ascontiguousarray(image)


def _frame_names(src: Path) -> list[str]:
    listing = src / FILENAMES_TXT
    if listing.is_file():
        names = [line.strip() for line in listing.read_text(encoding="utf-8-sig").splitlines() if line.strip()]
        if not names:
            raise CaptureError(f"{listing}: lists no images; give one image file name per line, in light order")
        for number, name in enumerate(names, start=1):
            p = Path(name)
            if p.is_absolute() or ".." in p.parts:
                raise CaptureError(f"{listing}:{number}: {name!r} must be a file name inside {src}")
        return names
    names = sorted((p.name for p in src.iterdir() if _NUMBERED_PNG.match(p.name)), key=lambda n: int(n[:-4]))
    if not names:
        raise CaptureError(f"{src}: no {FILENAMES_TXT} and no numbered images (001.png, 002.png, …): not a "
                           "DiLiGenT-style folder")
    logger.info("%s: no %s; using the %d numbered PNGs in numeric order", src, FILENAMES_TXT, len(names))
    return names


def read_diligent_intensities(path: str | os.PathLike[str], count: int,
                              rgb_weights: tuple[float, float, float] = DEFAULT_RGB_WEIGHTS) -> np.ndarray:
    """``light_intensities.txt`` (K lines ``r g b``, or one value per line) → (K,) mono intensities
    ``w · (r, g, b)`` (the weights of :func:`rgb_to_mono`).

    Raises:
        CaptureError: a malformed line, a non-finite or non-positive intensity, or not ``count`` lines;
            each names the file and the line.
    """
    path = Path(path)
    w = _weights(rgb_weights)
    rows = [(n, line.strip()) for n, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), start=1)
            if line.strip() and not line.strip().startswith("#")]
    if len(rows) != count:
        raise CaptureError(f"{path}: {len(rows)} intensity line(s) for {count} image(s); give one 'r g b' line per "
                           "image, in light order")
    out = []
    for number, line in rows:
        tokens = line.replace(",", " ").split()
        try:
            values = [float(t) for t in tokens]
        except ValueError:
            raise CaptureError(f"{path}:{number}: expected 'r g b' (or one intensity) as numbers; got {line!r}") from None
        if len(values) not in (1, 3):
            raise CaptureError(f"{path}:{number}: expected 'r g b' (or one intensity); got {len(values)} values {line!r}")
        value = values[0] if len(values) == 1 else float(np.dot(w, values))
        if not all(math.isfinite(v) for v in values) or not value > 0 or any(v < 0 for v in values):
            raise CaptureError(f"{path}:{number}: light intensities must be finite, non-negative, with a positive "
                               f"weighted sum; got {line!r}")
        out.append(value)
    return np.asarray(out, dtype=np.float64)


def _read_normals(src: Path, shape: tuple[int, int], frame: LightFrame) -> tuple[np.ndarray | None, str | None]:
    for name in NORMALS_NAMES:
        path = src / name
        if not path.is_file():
            continue
        if path.suffix == ".npy":
            try:
                value: Any = np.load(path, allow_pickle=False)
            except (ValueError, OSError) as err:
                raise CaptureError(f"{path}: cannot be read as NPY ({err})") from None
        else:
            from scipy.io import loadmat  # only for .mat ground truth

            try:
                data = loadmat(str(path))
            except (ValueError, OSError, NotImplementedError) as err:
                raise CaptureError(f"{path}: cannot be read as a MATLAB file ({err}; v7.3 files: save with -v7)") from None
            arrays = {k: v for k, v in data.items() if not k.startswith("__")}
            value = arrays.get("Normal_gt", next(iter(arrays.values())) if len(arrays) == 1 else None)
            if value is None:
                raise CaptureError(f"{path}: no variable 'Normal_gt' (found {sorted(arrays)})")
        value = np.asarray(value)
        if value.shape != (*shape, 3) or not np.issubdtype(value.dtype, np.floating):
            raise CaptureError(f"{path}: ground-truth normals must be an (H, W, 3) float array of the images' size "
                               f"{(*shape, 3)}; got {value.dtype} {value.shape}")
        normals = from_diligent_frame(value) if frame == "diligent" else value.astype(np.float64)
        missing = ~(np.linalg.norm(np.nan_to_num(normals), axis=-1) > 0)  # DiLiGenT stores 0 off the object
        normals[missing] = np.nan
        return normals.astype(np.float32), name
    return None, None


def import_diligent(
    src: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    light_frame: LightFrame = "diligent",
    rgb_weights: tuple[float, float, float] = DEFAULT_RGB_WEIGHTS,
    overwrite: bool = False,
) -> Capture:
    """Convert a DiLiGenT-style folder (module docstring) into a capture folder, atomically.

    Args:
        src: the DiLiGenT-style folder (read only).
        out: the capture folder to create (never the source or a folder holding it).
        light_frame: the frame of ``light_directions.txt`` and the ground-truth normals:
            ``"diligent"`` (x right, y up, z toward the viewer) or ``"opencv"`` (ours).
        rgb_weights: weights of R, G, B for the mono images and intensities.
        overwrite: replace an existing ``out``.

    Returns:
        The :class:`Capture` written (frames (K, 2H, 2W) for (H, W) source images; ``root`` = ``out``).

    Raises:
        OutputExistsError: ``out`` exists (without ``overwrite``), or is / holds ``src``; checked first.
        CaptureError: a missing or malformed file (named, with the line), images of different
            sizes or bit depths, a count mismatch, a light behind the object.
    """
    src, out = Path(src), Path(out)
    if not src.is_dir():
        raise CaptureError(f"{src}: not a folder; give a DiLiGenT-style folder (images, {DIRECTIONS_TXT}, …)")
    check_import_destination([src], out, overwrite=overwrite)
    weights = _weights(rgb_weights)
    names = _frame_names(src)
    if not (src / DIRECTIONS_TXT).is_file():
        raise CaptureError(f"{src / DIRECTIONS_TXT}: not found; a DiLiGenT-style folder gives one 'x y z' light "
                           "direction per image there")
    lights = read_light_file(src / DIRECTIONS_TXT, frame=light_frame, format="xyz", count=len(names))
    check_camera_side(lights)
    intensities_path = src / INTENSITIES_TXT
    if intensities_path.is_file():
        intensities = read_diligent_intensities(intensities_path, len(names), tuple(weights))
    else:
        intensities = np.ones(len(names))
        logger.info("%s: no %s; every light has intensity 1", src, INTENSITIES_TXT)

    frames, dtype, shape, rgb = [], None, None, False
    for name in names:
        image = _read_foreign_image(src / name, "image")
        rgb |= image.ndim == 3
        if dtype is None:
            dtype, shape = image.dtype, image.shape[:2]
        elif image.dtype != dtype or image.shape[:2] != shape:
            raise CaptureError(f"{src / name}: is {image.dtype} {image.shape[1]}x{image.shape[0]} but {names[0]} is "
                               f"{dtype} {shape[1]}x{shape[0]}; all images must have one size and bit depth")
        mono = rgb_to_mono(image, tuple(weights))  # (H, W)
        frames.append(np.repeat(np.repeat(mono, 2, axis=0), 2, axis=1))  # (2H, 2W): four equal sites
    assert dtype is not None and shape is not None
    bit_depth = 8 if dtype == np.uint8 else 16

    mask = None
    if (src / MASK_PNG).is_file():
        m = _read_foreign_image(src / MASK_PNG, "object mask")
        if m.shape[:2] != shape:
            raise CaptureError(f"{src / MASK_PNG}: is {m.shape[1]}x{m.shape[0]} but the images are "
                               f"{shape[1]}x{shape[0]}; give the mask at the images' size")
        mask = (m != 0) if m.ndim == 2 else (m != 0).any(axis=-1)
    normals, normals_name = _read_normals(src, shape, light_frame)

    spec = CaptureSpec.model_validate({
        "format": CAPTURE_FORMAT,
        "camera": {"model": DILIGENT_CAMERA_MODEL, "projection": "orthographic", "bit_depth": bit_depth},
        "lights": [
            {"direction": [float(c) for c in d], "intensity": float(e), "frame": f"frames/{k:03d}.png"}
            for k, (d, e) in enumerate(zip(lights.directions, intensities, strict=True))
        ],
    })
    ground_truth: dict[str, Any] = {
        "source": {
            "importer": "diligent",
            "source": str(src.resolve()),
            "polarisation": False,
            "frames": "plain intensity images; each source pixel stored as a 2x2 super-pixel of four equal sites",
            "images": names,
            "light_frame": light_frame,
            "rgb_weights": [float(v) for v in weights],
            "rgb_images": bool(rgb),
            "normals": normals_name,
            "max_count": max_count(bit_depth),
        }
    }
    if normals is not None:
        ground_truth["normals"] = normals
    capture = Capture(spec=spec, frames=np.stack(frames), mask=mask, ground_truth=ground_truth)
    write_capture(out, capture, overwrite=overwrite)
    capture.root = out.resolve()
    logger.info("imported %s into %s: %d lights, %dx%d images, %d-bit, mask %s, ground truth %s", src, out,
                len(names), shape[1], shape[0], bit_depth, "yes" if mask is not None else "no", normals_name or "none")
    return capture
