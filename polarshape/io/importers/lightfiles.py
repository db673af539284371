"""Light files as photometric-stereo tools write them, read into our camera frame.

Two formats:

- ``xyz`` — one light per line, ``x y z`` (whitespace or commas): DiLiGenT's
  ``light_directions.txt``, RobustPhotometricStereo's ``lights.txt``;
- ``lp`` — the RTI / relight ``.lp`` file: the count ``N`` on the first line, then ``N`` lines
  ``filename x y z``.

Blank lines and lines starting with ``#`` are skipped in both. The frame of the numbers is never
guessed: ``frame`` is required,

- ``"opencv"`` — ours (spec fmbrdf.md §1): x right, y down, z into the scene; a direction points
  from the surface to the light, so a light on the camera side has z < 0;
- ``"diligent"`` — DiLiGenT's (and most photometric-stereo code's, OpenGL-like): x right, y up, z
  toward the viewer; a light on the camera side has z > 0. ``(x, y, z)`` becomes ``(x, -y, -z)``
  (a rotation by 180° about x, so handedness is kept).

Every problem is a :class:`~polarshape.errors.CaptureError` naming the file and the line.
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import yaml

from polarshape.errors import CaptureError, SuspiciousInputWarning
from polarshape.io.capture import edit_capture_yaml, parse_capture_spec, set_light_directions

logger = logging.getLogger(__name__)

__all__ = [
    "LIGHT_FILE_FORMATS",
    "LIGHT_FRAMES",
    "LightFile",
    "LightFileFormat",
    "LightFrame",
    "check_camera_side",
    "from_diligent_frame",
    "match_light_order",
    "read_light_file",
    "set_capture_light_directions",
    "to_diligent_frame",
]

#: Frames a light (or normal) file can be written in (module docstring).
LightFrame = Literal["opencv", "diligent"]
LIGHT_FRAMES: tuple[str, ...] = ("opencv", "diligent")

#: Light file formats: ``auto`` picks ``lp`` for a ``.lp`` suffix, else ``xyz``.
LightFileFormat = Literal["auto", "xyz", "lp"]
LIGHT_FILE_FORMATS: tuple[str, ...] = ("auto", "xyz", "lp")

#: Relative spread of the vectors' lengths above which a warning says they may encode intensities.
NORM_SPREAD_WARN = 0.01

_DILIGENT_TO_OPENCV = np.array([1.0, -1.0, -1.0])


def from_diligent_frame(vectors: np.ndarray) -> np.ndarray:
    """(..., 3) vectors in DiLiGenT's frame (x right, y up, z to the viewer) → ours (x right, y down,
    z into the scene): ``(x, y, z) -> (x, -y, -z)``. NaN stays NaN."""
    return np.asarray(vectors, dtype=np.float64) * _DILIGENT_TO_OPENCV


def to_diligent_frame(vectors: np.ndarray) -> np.ndarray:
    """(..., 3) vectors in our frame → DiLiGenT's; the inverse of :func:`from_diligent_frame` (the
    same map: it is its own inverse)."""
    return np.asarray(vectors, dtype=np.float64) * _DILIGENT_TO_OPENCV


@dataclass(frozen=True)
class LightFile:
    """What a light file holds, converted to our frame.

    Attributes:
        directions: (K, 3) float64 unit vectors surface → light, our camera frame (OpenCV).
        filenames: the K image names of a ``.lp`` file (as written there), else None.
        lines: the K 1-based line numbers the lights came from (for messages).
        path: the file read.
        frame: the frame the file was written in.
        norms: (K,) the lengths of the vectors as written (1 for unit vectors).
    """

    directions: np.ndarray
    filenames: tuple[str, ...] | None
    lines: tuple[int, ...]
    path: Path
    frame: str
    norms: np.ndarray

    def __len__(self) -> int:
        return int(self.directions.shape[0])

    def where(self, k: int) -> str:
        """``file:line`` of light ``k`` (for messages)."""
        return f"{self.path}:{self.lines[k]}"


def _content_lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise CaptureError(f"{path}: light file not found") from None
    except UnicodeDecodeError as err:
        raise CaptureError(f"{path}: not a text file ({err}); a light file holds one light per line") from None
    except OSError as err:
        raise CaptureError(f"{path}: cannot be read ({err})") from None
    out = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            out.append((number, stripped))
    return out


def _vector(path: Path, number: int, tokens: list[str], what: str) -> tuple[float, float, float]:
    if len(tokens) != 3:
        hint = (" (if the file holds one light per column, transpose it: one 'x y z' line per light)"
                if len(tokens) > 3 else "")
        raise CaptureError(f"{path}:{number}: expected {what}; got {len(tokens)} value(s) {' '.join(tokens)!r}{hint}")
    try:
        x, y, z = (float(t) for t in tokens)
    except ValueError:
        raise CaptureError(f"{path}:{number}: expected {what} as numbers; got {' '.join(tokens)!r}") from None
    if not all(math.isfinite(c) for c in (x, y, z)):
        raise CaptureError(f"{path}:{number}: the light direction {' '.join(tokens)} is not finite (NaN or inf); "
                           "give a real direction for this light")
    if x == 0 and y == 0 and z == 0:
        raise CaptureError(f"{path}:{number}: the light direction is the zero vector; give a non-zero direction "
                           "toward this light")
    return x, y, z


def _parse_xyz(path: Path, rows: list[tuple[int, str]]) -> tuple[list[tuple[float, float, float]], None, list[int]]:
    vectors = [_vector(path, n, line.replace(",", " ").split(), "three numbers 'x y z'") for n, line in rows]
    return vectors, None, [n for n, _ in rows]


def _parse_lp(path: Path, rows: list[tuple[int, str]]) -> tuple[list[tuple[float, float, float]], list[str], list[int]]:
    if not rows:
        raise CaptureError(f"{path}: empty; an .lp file starts with the number of lights N, then N lines 'filename x y z'")
    n_line, head = rows[0]
    try:
        count = int(head)
    except ValueError:
        raise CaptureError(f"{path}:{n_line}: expected the number of lights N on the first line of an .lp file; "
                           f"got {head!r}") from None
    if count < 1:
        raise CaptureError(f"{path}:{n_line}: the number of lights must be at least 1; got {count}")
    body = rows[1:]
    if len(body) != count:
        raise CaptureError(f"{path}:{n_line}: the header says {count} light(s) but the file has {len(body)} light "
                           "line(s); fix the count on the first line or add/remove lines")
    vectors, names = [], []
    for number, line in body:
        tokens = line.split()
        if len(tokens) < 4:
            raise CaptureError(f"{path}:{number}: expected 'filename x y z'; got {line!r}")
        vectors.append(_vector(path, number, tokens[-3:], "'filename x y z'"))
        names.append(" ".join(tokens[:-3]))
    return vectors, names, [n for n, _ in body]


def read_light_file(
    path: str | os.PathLike[str],
    *,
    frame: LightFrame,
    format: LightFileFormat = "auto",  # noqa: A002 - the file format, as the CLI names it
    count: int | None = None,
) -> LightFile:
    """Read a light file (module docstring) into unit directions in our camera frame.

    Args:
        path: the file (``.txt`` or any other suffix: ``x y z`` lines; ``.lp``: RTI format).
        frame: the frame its numbers are in: ``"opencv"`` (ours) or ``"diligent"`` (y up, z to the
            viewer). Required: a frame is never guessed.
        format: ``"xyz"``, ``"lp"`` or ``"auto"`` (by suffix).
        count: the number of lights expected (e.g. the frames of a capture), or None.

    Returns:
        :class:`LightFile`: ``directions`` (K, 3) unit vectors surface → light, camera frame.

    Raises:
        CaptureError: an unknown frame or format, a missing or empty file, a malformed line, a zero,
            NaN or infinite vector, an ``.lp`` count that does not match its lines, or ``count``
            lights expected and another number found; each names the file and the line.

    Example:
        >>> lights = read_light_file("light_directions.txt", frame="diligent")  # doctest: +SKIP
        >>> lights.directions.shape  # doctest: +SKIP
        (96, 3)
    """
    path = Path(path)
    if frame not in LIGHT_FRAMES:
        raise CaptureError(f"{path}: light frame {frame!r} is not one of {LIGHT_FRAMES}: 'opencv' (x right, y down, "
                           "z into the scene) or 'diligent' (x right, y up, z toward the viewer)")
    if format not in LIGHT_FILE_FORMATS:
        raise CaptureError(f"{path}: light file format {format!r} is not one of {LIGHT_FILE_FORMATS}")
    kind = ("lp" if path.suffix.lower() == ".lp" else "xyz") if format == "auto" else format
    rows = _content_lines(path)
    if not rows:
        raise CaptureError(f"{path}: holds no lights (empty, or only comments); give one 'x y z' line per light")
    vectors, names, lines = (_parse_lp if kind == "lp" else _parse_xyz)(path, rows)
    if count is not None and len(vectors) != count:
        raise CaptureError(f"{path}: {len(vectors)} light(s) for {count} image(s); give one light per image, in "
                           "image order")
    raw = np.asarray(vectors, dtype=np.float64)  # (K, 3)
    norms = np.linalg.norm(raw, axis=1)  # (K,)
    if len(norms) > 1 and (norms.max() - norms.min()) > NORM_SPREAD_WARN * norms.max():
        warnings.warn(SuspiciousInputWarning(
            f"{path}: the light vectors' lengths range from {norms.min():.4g} to {norms.max():.4g}; polarshape uses "
            "only their directions. If the lengths are the lights' intensities, give the intensities separately "
            "(capture.yaml lights[k].intensity)"), stacklevel=2)
    unit = raw / norms[:, None]
    directions = from_diligent_frame(unit) if frame == "diligent" else unit
    logger.info("read %d light(s) from %s (%s format, %s frame)", len(directions), path, kind, frame)
    return LightFile(directions=directions, filenames=None if names is None else tuple(names), lines=tuple(lines),
                     path=path, frame=frame, norms=norms)


def check_camera_side(lights: LightFile) -> None:
    """Refuse a light behind the object (z ≥ 0 in our frame), naming its line and the likely fix.

    Raises:
        CaptureError: the first light with z ≥ 0.
    """
    other = "opencv" if lights.frame == "diligent" else "diligent"
    for k, d in enumerate(lights.directions):
        if not d[2] < 0:
            raise CaptureError(
                f"{lights.where(k)}: light {k} points behind the object in the camera frame (z = {d[2]:.4g} >= 0 "
                f"read as frame {lights.frame!r}); a light on the camera side has z < 0 in 'opencv' and z > 0 in "
                f"'diligent': if the whole file is in the other frame, read it with frame {other!r}"
            )


def _frame_key(name: str) -> str:
    """The stem of an image name, whatever the separators (``C:\\rti\\IMG_01.JPG`` -> ``img_01``)."""
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    return base.rsplit(".", 1)[0].lower() if "." in base else base.lower()


def match_light_order(lights: LightFile, frames: list[str]) -> list[int]:
    """For each capture frame, the index of its light in ``lights``.

    ``.lp`` files name their images: when every frame's stem is one of them, lights go by name;
    when none is, they go in file order (as for ``x y z`` files); anything in between is refused.

    Raises:
        CaptureError: a count mismatch, or names that match some frames but not all.
    """
    if len(lights) != len(frames):
        raise CaptureError(f"{lights.path}: {len(lights)} light(s) for the {len(frames)} frame(s) of the capture; "
                           "give one light per frame, in frame order")
    if lights.filenames is None:
        return list(range(len(frames)))
    by_name: dict[str, int] = {}
    for k, name in enumerate(lights.filenames):
        key = _frame_key(name)
        if key in by_name:
            raise CaptureError(f"{lights.where(k)}: image {name!r} also names the light on line "
                               f"{lights.lines[by_name[key]]}; give each image once")
        by_name[key] = k
    keys = [_frame_key(f) for f in frames]
    found = [key in by_name for key in keys]
    if all(found):
        logger.info("%s: lights matched to the capture's frames by image name", lights.path)
        return [by_name[key] for key in keys]
    if not any(found):
        logger.info("%s: no image name matches a capture frame; lights taken in file order", lights.path)
        return list(range(len(frames)))
    missing = [f for f, ok in zip(frames, found) if not ok]
    raise CaptureError(f"{lights.path}: names some of the capture's frames but not {missing[:5]}; name every frame "
                       "(matched by file stem) or none (then lights go in file order)")


def set_capture_light_directions(capture: str | os.PathLike[str], lights: LightFile) -> Path:
    """Write a light file's directions into an existing capture's ``capture.yaml``, atomically.

    Each light entry gets ``direction`` (a ``position`` is replaced: the file gives distant lights);
    its ``intensity`` and ``frame`` are kept. The new file is validated before it replaces the old
    one, so a refused update leaves ``capture.yaml`` as it was.

    Args:
        capture: the capture folder, or its ``capture.yaml``.
        lights: from :func:`read_light_file`.

    Returns:
        The ``capture.yaml`` written.

    Raises:
        CaptureError: not a capture, a count mismatch, a light behind the object, names that
            match only some frames.
    """
    def edit(doc: dict) -> None:
        spec = parse_capture_spec(doc, str(capture))
        order = match_light_order(lights, [light.frame for light in spec.lights])
        check_camera_side(lights)
        set_light_directions(doc, lights.directions[order])

    path = edit_capture_yaml(capture, edit)
    logger.info("wrote %d light directions from %s into %s", len(lights.directions), lights.path, path)
    return path
