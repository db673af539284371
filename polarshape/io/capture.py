"""Capture folders (spec capture-format.md): what a camera recorded of one object under K lights.

::

    my_capture/
      capture.yaml        format, camera, lights (validated by :class:`CaptureSpec`)
      frames/000.png …    one raw mosaic per light, 8/16-bit PNG or TIFF, low-bit aligned counts
                          (format 2: several exposures per light, each frame with its exposure_us)
      mask.png            optional object mask (non-zero = object), mosaic or super-pixel size
      ground_truth/       optional: normals.npy, depth.npy, any other *.npy / *.json

Frames live in the camera frame of spec fmbrdf.md §1 (OpenCV: x right, y down, z into the scene).
Every problem found on load is a :class:`CaptureError` naming the file, the field and the fix.
"""

from __future__ import annotations

import json
import logging
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from polarshape.errors import BitDepthWarning, CaptureError
from polarshape.imaging.colour import BAYER_PATTERNS
from polarshape.imaging.mosaic import CHANNEL_ANGLES_DEG, MakerAngles, MosaicLayout
from polarshape.imaging.pixels import BIT_DEPTHS, left_shift_of, max_count, reduce_mask_to_superpixels
from polarshape.io.atomic import atomic_directory, atomic_write_text
from polarshape.io.images import IMAGE_SUFFIXES, ImageError, read_image, write_image
from polarshape.io.yamlfile import load_yaml
from polarshape.lights import Light, Lights, light_from_dict

logger = logging.getLogger(__name__)

__all__ = [
    "CAPTURE_FORMAT",
    "CAPTURE_FORMAT_BRACKETS",
    "BracketFrameSpec",
    "CameraSpec",
    "Capture",
    "CaptureError",
    "CaptureLightSpec",
    "CaptureSpec",
    "Distortion",
    "IntrinsicsSpec",
    "LightSpec",
    "MosaicSpec",
    "Projection",
    "edit_capture_yaml",
    "load_capture",
    "set_light_directions",
    "write_capture",
]

#: Version string of the capture format with one frame per light (read and written).
CAPTURE_FORMAT = "polarshape-capture/1"
#: Version 2: each light may hold several exposures (``exposure_us`` and ``brackets``); read and
#: written (only for captures that use it: one frame per light is written as version 1).
CAPTURE_FORMAT_BRACKETS = "polarshape-capture/2"
CAPTURE_FORMATS = (CAPTURE_FORMAT, CAPTURE_FORMAT_BRACKETS)
CAPTURE_YAML = "capture.yaml"
MASK_FILE = "mask.png"
GROUND_TRUTH_DIR = "ground_truth"
UNIT_TOLERANCE = 1e-3

#: How a camera projects: parallel rays (telecentric lens) or a pinhole.
Projection = Literal["orthographic", "perspective"]
Vec3 = tuple[float, float, float]


def _check_distortion(v: tuple[float, ...]) -> tuple[float, ...]:
    if len(v) not in (4, 5, 8, 12, 14):
        raise ValueError(f"must have 4, 5, 8, 12 or 14 OpenCV coefficients (k1 k2 p1 p2 [k3 ...]); got {len(v)}")
    if not all(math.isfinite(c) for c in v):
        raise ValueError("coefficients must be finite numbers")
    return v


#: OpenCV lens distortion coefficients (k1, k2, p1, p2[, k3, …]), as in ``camera.distortion``.
Distortion = Annotated[tuple[float, ...], AfterValidator(_check_distortion)]


class _Strict(BaseModel):
    # allow_inf_nan=False: every float of capture.yaml (and of the scene/session entries built on these
    # models) must be finite; ``.inf`` or ``.nan`` is an error naming its key
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class IntrinsicsSpec(_Strict):
    """Pinhole intrinsics in raw-mosaic pixels (perspective cameras)."""

    fx: float = Field(gt=0, allow_inf_nan=False, description="focal length along x, pixels")
    fy: float = Field(gt=0, allow_inf_nan=False, description="focal length along y, pixels")
    cx: float = Field(allow_inf_nan=False, description="principal point x (column), pixels")
    cy: float = Field(allow_inf_nan=False, description="principal point y (row), pixels")


class MosaicSpec(_Strict):
    """The polariser mosaic as the maker labels it (converted to our convention by :meth:`to_layout`).

    ``angles`` says how the labels of ``layout`` are measured (:mod:`polarshape.imaging.mosaic`):
    ``counterclockwise_on_screen`` (the maker's), ``clockwise_on_screen`` (ours: x toward y down),
    or ``polanalyser`` (as the polanalyser library labels them — the maker's direction, so the same
    layout as ``counterclockwise_on_screen``; polanalyser's S2 and AoLP are then −s2 and π − AoLP).
    """

    layout: tuple[tuple[float, float], tuple[float, float]] = ((90.0, 45.0), (135.0, 0.0))
    angles: MakerAngles = "counterclockwise_on_screen"
    #: Colour polarisation sensors (IMX250MYR): colours of the top-left 2×2 polariser blocks of the
    #: stored frames, row by row (:mod:`polarshape.imaging.colour`); None = a mono sensor.
    bayer: str | None = None

    @field_validator("bayer")
    @classmethod
    def _bayer(cls, v: str | None) -> str | None:
        if v is not None and v not in BAYER_PATTERNS:
            raise ValueError(
                f"must be one of {list(BAYER_PATTERNS)} (colours of the top-left 2×2 polariser blocks, row by row; "
                f"the IMX250MYR / TRI050S-QC is RGGB) or null for a mono sensor; got {v!r}"
            )
        return v

    @field_validator("layout")
    @classmethod
    def _permutation(cls, v: tuple[tuple[float, float], tuple[float, float]]) -> tuple[tuple[float, float], ...]:
        flat = sorted(a % 180.0 for row in v for a in row)
        if any(not math.isclose(a, b, abs_tol=1e-6) for a, b in zip(flat, CHANNEL_ANGLES_DEG)):
            raise ValueError(
                f"must hold the polariser angles 0, 45, 90, 135 (degrees) once each, top row then bottom row, "
                f"e.g. [[90, 45], [135, 0]]; got {[list(r) for r in v]}"
            )
        return v

    def to_layout(self) -> MosaicLayout:
        """The layout in our convention (y down, angle from x toward y)."""
        return MosaicLayout.from_maker(self.layout, self.angles)


class CameraSpec(_Strict):
    """Camera model, projection and pixel format."""

    model: str = "unknown"
    projection: Projection
    intrinsics: IntrinsicsSpec | None = None
    distortion: Distortion | None = None
    bit_depth: int
    black_level: float = Field(default=0.0, ge=0, allow_inf_nan=False)
    mosaic: MosaicSpec = MosaicSpec()
    #: The sensor's polarimetric calibration file (``polarshape calibrate polarisation``; a path relative
    #: to the capture folder, or absolute), read and applied by preprocessing; None = ideal analysers.
    polarimetric_calibration: str | None = Field(default=None, min_length=1)

    @field_validator("bit_depth")
    @classmethod
    def _bit_depth(cls, v: int) -> int:
        if v not in BIT_DEPTHS:
            raise ValueError(f"must be one of {BIT_DEPTHS} (significant bits of the sensor counts); got {v}")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> CameraSpec:
        if self.projection == "perspective" and self.intrinsics is None:
            raise ValueError(
                "camera.intrinsics {fx, fy, cx, cy} (raw-mosaic pixels) is required when projection is perspective"
            )
        if self.black_level >= max_count(self.bit_depth):
            raise ValueError(
                f"camera.black_level {self.black_level} must be below the full scale {max_count(self.bit_depth)} "
                f"of bit_depth {self.bit_depth}"
            )
        return self


class LightSpec(_Strict):
    """One light of a capture, scene or session file, camera frame: exactly one of ``direction``
    (toward a distant light) or ``position`` (a point light, metres), and its relative intensity.

    Capture files add the frame recorded under it (:class:`CaptureLightSpec`); the runtime light is
    :meth:`to_light`.
    """

    direction: Vec3 | None = None
    position: Vec3 | None = None
    intensity: float = Field(default=1.0, gt=0, allow_inf_nan=False)

    @field_validator("direction")
    @classmethod
    def _direction(cls, v: Vec3 | None) -> Vec3 | None:
        if v is None:
            return v
        if not all(math.isfinite(c) for c in v):
            raise ValueError(f"must be finite; got {list(v)}")
        if not any(v):
            raise ValueError("must be a non-zero vector toward the light")
        if v[2] > 0:  # z = 0 is a grazing light: it still lights the object's sides
            raise ValueError(
                f"z = {v[2]:.6g} must be < 0, or 0 for a grazing light: the direction points from the object TO the "
                "light, in the camera frame (x right, y down, +z into the scene), so a light on the camera side has "
                "z < 0; z > 0 puts it behind the object. Flip the sign if your convention has +z toward the camera"
            )
        return v

    @field_validator("position")
    @classmethod
    def _position(cls, v: Vec3 | None) -> Vec3 | None:
        if v is not None and not all(math.isfinite(c) for c in v):
            raise ValueError(f"must be finite (metres, camera frame); got {list(v)}")
        return v

    @model_validator(mode="after")
    def _one_kind(self) -> LightSpec:
        if (self.direction is None) == (self.position is None):
            raise ValueError(
                "give exactly one of direction (unit vector to a distant light) or position (point light, metres)"
            )
        return self

    def to_light(self) -> Light:
        """The light this entry describes (:mod:`polarshape.lights`; a direction is normalised there)."""
        return light_from_dict(self.model_dump(include={"direction", "position", "intensity"}, exclude_none=True))


def _check_frame_path(v: str) -> str:
    p = PurePosixPath(v)
    if not v or p.is_absolute() or ".." in p.parts or "\\" in v:
        raise ValueError(f"must be a relative path inside the capture folder, e.g. frames/000.png; got {v!r}")
    if p.suffix.lower() not in IMAGE_SUFFIXES:
        raise ValueError(f"must be a {'/'.join(IMAGE_SUFFIXES)} file (lossless); got {v!r}")
    return v


def _check_exposure(v: float) -> float:
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"must be a positive exposure time in microseconds (e.g. 8000); got {v!r}")
    return v


#: A frame's path inside the capture folder, and an exposure time in µs, checked where they are declared.
FramePath = Annotated[str, AfterValidator(_check_frame_path)]
ExposureUs = Annotated[float, AfterValidator(_check_exposure)]


class BracketFrameSpec(_Strict):
    """One more exposure of a light (format 2): the frame and its exposure time in µs."""

    frame: FramePath
    exposure_us: ExposureUs


class CaptureLightSpec(LightSpec):
    """One light of ``capture.yaml`` and the frame recorded under it; ``direction`` is a unit vector.

    Format 2 (:data:`CAPTURE_FORMAT_BRACKETS`) adds ``exposure_us``, the exposure time of ``frame``
    (the light's reference exposure: preprocessing expresses the merged radiance in fractions of full
    scale at it, and ``intensity`` is as seen at it), and ``brackets``, the same light at other exposures.
    """

    frame: FramePath
    exposure_us: ExposureUs | None = None
    brackets: tuple[BracketFrameSpec, ...] = ()

    @field_validator("direction")
    @classmethod
    def _unit(cls, v: Vec3 | None) -> Vec3 | None:
        norm = math.sqrt(sum(c * c for c in v)) if v is not None else 1.0
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            raise ValueError(
                f"must be a unit vector (|d| = {norm:.6f}, tolerance {UNIT_TOLERANCE}): divide it by its norm"
            )
        return v

    @model_validator(mode="after")
    def _bracket(self) -> CaptureLightSpec:
        if self.brackets and self.exposure_us is None:
            raise ValueError("brackets need exposure_us: the exposure time (µs) of frame, the light's reference exposure")
        seen = {self.exposure_us: "frame"}
        for j, b in enumerate(self.brackets):
            if b.exposure_us in seen:
                raise ValueError(
                    f"brackets[{j}].exposure_us {b.exposure_us:g} is also the exposure of {seen[b.exposure_us]}: each "
                    "frame of a light needs its own exposure time (average repeated frames of one exposure into one "
                    "frame, or fix the exposure_us that is wrong)")
            seen[b.exposure_us] = f"brackets[{j}]"
        return self

    def frame_paths(self) -> list[str]:
        """The light's frames: ``frame`` (the reference exposure), then its brackets' in order."""
        return [self.frame, *(b.frame for b in self.brackets)]

    def exposures(self) -> list[float] | None:
        """Exposure times (µs) of :meth:`frame_paths`, or None when ``exposure_us`` is not given."""
        return None if self.exposure_us is None else [self.exposure_us, *(b.exposure_us for b in self.brackets)]


class CaptureSpec(_Strict):
    """The content of ``capture.yaml``."""

    format: Literal["polarshape-capture/1", "polarshape-capture/2"]
    camera: CameraSpec
    lights: tuple[CaptureLightSpec, ...] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique_frames(self) -> CaptureSpec:
        seen: dict[str, str] = {}
        for k, light in enumerate(self.lights):
            names = [f"lights[{k}].frame"] + [f"lights[{k}].brackets[{j}].frame" for j in range(len(light.brackets))]
            for name, frame in zip(names, light.frame_paths()):
                key = frame.lower()
                if key in seen:
                    raise ValueError(f"{name} {frame!r} is also the frame of {seen[key]}: give every frame its own file")
                seen[key] = name
        return self

    @model_validator(mode="after")
    def _brackets(self) -> CaptureSpec:
        if self.format == CAPTURE_FORMAT:
            for k, light in enumerate(self.lights):
                if light.exposure_us is not None or light.brackets:
                    raise ValueError(
                        f"lights[{k}] has exposure_us/brackets (several exposures per light), which need format "
                        f"{CAPTURE_FORMAT_BRACKETS!r}: change the format line of capture.yaml")
            return self
        for k, light in enumerate(self.lights):
            if light.exposure_us is None:
                raise ValueError(
                    f"lights[{k}].exposure_us is required by format {CAPTURE_FORMAT_BRACKETS!r}: the exposure time "
                    f"(µs) of lights[{k}].frame {light.frame!r}")
        counts = [len(light.brackets) for light in self.lights]
        for k, n in enumerate(counts):
            if n != counts[0]:
                raise ValueError(
                    f"lights[{k}] has {n + 1} exposure(s) (frame and {n} brackets) but lights[0] has {counts[0] + 1}: "
                    "every light needs the same number of exposures; capture the missing ones or drop the extra "
                    "brackets")
        return self

    @property
    def bracket_size(self) -> int:
        """Frames per light (1 in format 1)."""
        return 1 + len(self.lights[0].brackets)

    @property
    def exposures_us(self) -> np.ndarray | None:
        """(K, B) exposure times (µs) of every light's frames (reference first), or None in format 1."""
        if self.format == CAPTURE_FORMAT:
            return None
        return np.array([light.exposures() for light in self.lights], dtype=np.float64)


def _format_validation_error(source: str, err: ValidationError) -> str:
    lines = [f"{source}: {err.error_count()} problem(s):"]
    for e in err.errors():
        loc = ""
        for part in e["loc"]:
            loc += f"[{part}]" if isinstance(part, int) else (f".{part}" if loc else str(part))
        msg = e["msg"].removeprefix("Value error, ")
        hint = ""
        if e["type"] == "extra_forbidden":
            hint = " (unknown field: remove it or fix its spelling; the capture format is described in the README)"
        elif e["type"] == "missing":
            hint = " (required field: add it)"
        elif e["type"] == "literal_error" and loc == "format":
            hint = f" (this polarshape reads {CAPTURE_FORMAT!r} and {CAPTURE_FORMAT_BRACKETS!r})"
        got = "" if "; got " in msg or e["type"] == "missing" else f"; got {e.get('input')!r}"  # once
        lines.append(f"  - {loc or '(top level)'}: {msg}{hint}{got}"[:600])
    return "\n".join(lines)


def parse_capture_spec(data: Any, source: str = CAPTURE_YAML) -> CaptureSpec:
    """Validate a parsed ``capture.yaml`` mapping. Raises :class:`CaptureError` naming each bad field."""
    if not isinstance(data, dict):
        raise CaptureError(
            f"{source}: must be a YAML mapping with format, camera and lights; got {type(data).__name__}"
        )
    try:
        return CaptureSpec.model_validate(data)
    except ValidationError as err:
        raise CaptureError(_format_validation_error(source, err)) from None


@dataclass
class Capture:
    """One object recorded under K lights.

    Attributes:
        spec: the validated ``capture.yaml``.
        frames: (K, H, W) ``uint16`` raw mosaics in sensor counts (low-bit aligned, also for
            8-bit data), frame k under ``spec.lights[k]``; H and W even.
        mask: (H/2, W/2) bool object mask at super-pixel resolution, or None.
        ground_truth: optional reference data by file stem, e.g. ``"normals"`` -> (H/2, W/2, 3)
            float camera-frame unit normals; ``*.npy`` files give arrays, ``*.json`` files
            give the parsed JSON.
        root: the folder it was loaded from, if any.
        brackets: (K, B − 1, H, W) the other exposures of each light (format 2), in the order of its
            ``brackets`` (same dtype as ``frames``); None when every light has one frame.
    """

    spec: CaptureSpec
    frames: np.ndarray
    mask: np.ndarray | None = None
    ground_truth: dict[str, Any] = field(default_factory=dict)
    root: Path | None = None
    brackets: np.ndarray | None = None

    @property
    def has_brackets(self) -> bool:
        """Whether the lights hold more than one exposure each."""
        return self.spec.bracket_size > 1

    def bracket(self, k: int) -> np.ndarray:
        """(B, H, W) every frame of light ``k``, its reference exposure first (the brackets after)."""
        if self.brackets is None:
            return self.frames[k : k + 1]
        return np.concatenate([self.frames[k : k + 1], self.brackets[k]])

    @property
    def layout(self) -> MosaicLayout:
        """The mosaic layout of the stored frames, our convention."""
        return self.spec.camera.mosaic.to_layout()

    @property
    def bit_depth(self) -> int:
        return self.spec.camera.bit_depth

    @property
    def num_lights(self) -> int:
        return len(self.spec.lights)

    def lights(self) -> Lights:
        """The K lights of ``capture.yaml``, in frame order: ``lights().illuminate(points (..., 3))``
        gives L (K, ..., 3) and E (K, ...) for directional and point lights alike."""
        return Lights.from_entries(self.spec.lights)


# --- validation shared by load and write -------------------------------------------------------


def _check_frames(spec: CaptureSpec, frames: np.ndarray, where: str) -> None:
    k = len(spec.lights)
    if not isinstance(frames, np.ndarray) or frames.ndim != 3:
        raise CaptureError(f"{where}: frames must be a (K, H, W) array; got {getattr(frames, 'shape', type(frames))}")
    if frames.shape[0] != k:
        raise CaptureError(
            f"{where}: {frames.shape[0]} frames for {k} lights in capture.yaml; give one frame per light"
        )
    h, w = frames.shape[1:]
    if h % 2 or w % 2 or h == 0 or w == 0:
        raise CaptureError(
            f"{where}: frames are {w}×{h} (W×H); a polarisation mosaic needs even width and height (whole 2×2 "
            "super-pixels): crop one column/row, and if you crop at the top or left, change camera.mosaic.layout"
        )
    if spec.camera.mosaic.bayer is not None and (h < 4 or w < 4):
        raise CaptureError(
            f"{where}: frames are {w}×{h} (W×H); a colour polarisation mosaic (camera.mosaic.bayer "
            f"{spec.camera.mosaic.bayer}) needs at least 4×4 pixels (one Bayer super-block of 2×2 polariser blocks)"
        )
    if frames.dtype not in (np.uint8, np.uint16):
        raise CaptureError(f"{where}: frames must be uint16 (or uint8) sensor counts; got {frames.dtype}")


def _check_counts(image: np.ndarray, bit_depth: int, where: str) -> None:
    top = max_count(bit_depth)
    hi = int(image.max()) if image.size else 0
    if hi > top:
        shift = 16 - bit_depth
        raise CaptureError(
            f"{where}: holds counts up to {hi}, above {top} = 2**{bit_depth} - 1 for camera.bit_depth {bit_depth}: "
            f"if the counts are high-bit aligned, shift them right by {shift} bits before saving; otherwise fix "
            "camera.bit_depth"
        )


def _check_alignment(frames: np.ndarray, where: str) -> None:
    """16-bit frames (K, H, W) holding high-bit aligned counts of a shallower ADC: fine for 12-bit
    (the IMX250MZR's PolarizeMono16; saturation is taken at 65520), a warning for 10 or 8 bits,
    whose clipped sites would not be flagged as saturated."""
    shift = left_shift_of(frames)
    if shift == 4:
        logger.info("%s: 12-bit counts stored high-bit aligned (multiples of 16, as PolarizeMono16): clipping is "
                    "taken at 65520", where)
    elif shift:
        bits = 16 - shift
        warnings.warn(BitDepthWarning(
            f"{where}: every count is a multiple of {1 << shift} and the largest is {int(frames.max())}: these look "
            f"like {bits}-bit counts left-shifted by {shift} (high-bit aligned) declared camera.bit_depth 16, so "
            f"sites clipped at {max_count(bits) << shift} are not flagged as saturated (16-bit clipping is taken at "
            f"65520). Fix: shift the frames right by {shift} and set camera.bit_depth: {bits}, or re-import the "
            "source with `polarshape import arena` (which does both and records it)"), stacklevel=3)


def _mask_to_superpixels(mask: np.ndarray, frame_hw: tuple[int, int], where: str) -> np.ndarray:
    h, w = frame_hw
    if mask.ndim != 2:
        raise CaptureError(f"{where}: the mask must be a single-channel image; got shape {mask.shape}")
    if mask.shape == (h, w):
        return reduce_mask_to_superpixels(mask != 0, mode="all")
    if mask.shape == (h // 2, w // 2):
        return mask != 0
    raise CaptureError(
        f"{where}: mask is {mask.shape[1]}×{mask.shape[0]} (W×H) but the frames are {w}×{h}: give the mask at "
        f"mosaic resolution ({w}×{h}) or super-pixel resolution ({w // 2}×{h // 2})"
    )


def _check_capture(capture: Capture) -> None:
    """Consistency of an in-memory capture before writing (raises CaptureError)."""
    if not isinstance(capture.spec, CaptureSpec):
        raise CaptureError(f"Capture.spec must be a CaptureSpec; got {type(capture.spec).__name__}")
    _check_frames(capture.spec, capture.frames, "Capture.frames")
    _check_counts(capture.frames, capture.bit_depth, "Capture.frames")
    h, w = capture.frames.shape[1:]
    _check_brackets(capture)
    if capture.mask is not None:
        m = capture.mask
        if not isinstance(m, np.ndarray) or m.shape != (h // 2, w // 2):
            raise CaptureError(
                f"Capture.mask must be a ({h // 2}, {w // 2}) bool array at super-pixel resolution; got "
                f"{getattr(m, 'shape', type(m).__name__)}"
            )
    for name, value in capture.ground_truth.items():
        if not name or "/" in name or "\\" in name or name.startswith("."):
            raise CaptureError(f"Capture.ground_truth key {name!r} must be a plain file stem, e.g. 'normals'")
        if isinstance(value, np.ndarray) and value.dtype == object:
            raise CaptureError(f"Capture.ground_truth[{name!r}] is an object array; store numeric arrays only")


def _check_brackets(capture: Capture) -> None:
    """Capture.brackets against the spec's brackets (raises CaptureError)."""
    k, h, w = capture.frames.shape
    extra = capture.spec.bracket_size - 1
    b = capture.brackets
    if b is None or (isinstance(b, np.ndarray) and b.ndim == 4 and b.shape[1] == 0):
        if extra:
            raise CaptureError(f"Capture.brackets is missing: the spec lists {extra} bracket frame(s) per light; give "
                               f"a ({k}, {extra}, {h}, {w}) array")
        return
    if not isinstance(b, np.ndarray) or b.shape != (k, extra, h, w) or b.dtype != capture.frames.dtype:
        raise CaptureError(
            f"Capture.brackets must be a ({k}, {extra}, {h}, {w}) {capture.frames.dtype} array (the spec's brackets of "
            f"each light, frames' size); got {getattr(b, 'shape', type(b).__name__)} {getattr(b, 'dtype', '')}")
    _check_counts(b, capture.bit_depth, "Capture.brackets")


# --- load --------------------------------------------------------------------------------------


def _read_yaml(path: Path) -> Any:
    if not path.is_file():
        raise CaptureError(
            f"{path}: not found; a capture folder must hold capture.yaml (format, camera, lights) — see the capture "
            "format in the README"
        )
    return load_yaml(path, error=CaptureError)  # not YAML, not UTF-8, or a key given twice


def edit_capture_yaml(path: str | os.PathLike[str], edit: Callable[[dict[str, Any]], None], *,
                      check_before: bool = True) -> Path:
    """Change a capture.yaml in place, atomically: read it, apply ``edit`` to the parsed mapping,
    validate the result and write it; a refused edit leaves the file as it was.

    Args:
        path: the capture.yaml, or the capture folder holding it.
        edit: changes the mapping in place (may raise to refuse).
        check_before: refuse a file that is not a valid capture.yaml before editing it; when False,
            a file that was valid must still be valid after the edit (one being written step by
            step, e.g. by calibration, may stay incomplete).

    Returns:
        The path of the capture.yaml written.

    Raises:
        CaptureError: not found, not YAML, invalid before (``check_before``) or after the edit.
    """
    path = Path(path)
    if path.is_dir():
        path = path / CAPTURE_YAML
    doc = _read_yaml(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("lights"), list) or not isinstance(doc.get("camera"), dict):
        raise CaptureError(f"{path} is not a capture.yaml (needs a 'camera' mapping and a 'lights' list)")
    valid = True
    try:
        parse_capture_spec(doc, str(path))
    except CaptureError:
        if check_before:
            raise
        valid = False
    edit(doc)
    if valid:
        parse_capture_spec(doc, str(path))
    atomic_write_text(path, yaml.safe_dump(doc, sort_keys=False, default_flow_style=None), overwrite=True)
    logger.info("updated %s", path)
    return path


def set_light_directions(doc: dict[str, Any], directions: np.ndarray) -> None:
    """Give each ``lights`` entry of a capture.yaml mapping its row of ``directions`` (K, 3) (unit,
    camera frame, surface → light); a ``position`` is dropped (the entry becomes a distant light),
    ``intensity`` and ``frame`` are kept.

    Raises:
        CaptureError: not one direction per entry.
    """
    dirs = np.asarray(directions, dtype=np.float64)
    if dirs.shape != (len(doc["lights"]), 3):
        raise CaptureError(f"{dirs.shape[0] if dirs.ndim else 0} light directions for the {len(doc['lights'])} "
                           "lights of capture.yaml: give one per light, in the order of capture.yaml")
    for entry, direction in zip(doc["lights"], dirs, strict=True):
        if "position" in entry:
            logger.info("the point light of frame %s becomes a distant light", entry.get("frame"))
        entry.pop("position", None)
        entry["direction"] = [float(c) for c in direction]


def _read_frame(root: Path, k: int, light: CaptureLightSpec, bit_depth: int, j: int = 0) -> np.ndarray:
    """Frame ``j`` of light ``k`` (0: ``frame``, j ≥ 1: ``brackets[j − 1]``)."""
    key = f"lights[{k}].frame" if j == 0 else f"lights[{k}].brackets[{j - 1}].frame"
    path = root / light.frame_paths()[j]
    where = f"{path} ({key} in {CAPTURE_YAML})"
    if not path.is_file():
        raise CaptureError(f"{where}: file not found; add the frame or fix {key}")
    try:
        image = read_image(path)
    except ImageError as err:
        raise CaptureError(f"{err} ({key})") from None
    if image.dtype == np.uint8 and bit_depth > 8:
        raise CaptureError(
            f"{where}: is an 8-bit image but camera.bit_depth is {bit_depth}: 8 bits cannot hold {bit_depth}-bit "
            "counts (the data were probably scaled down); save the frames as 16-bit PNG/TIFF with low-bit aligned "
            "counts, or set camera.bit_depth: 8 if the sensor delivered 8 bits"
        )
    _check_counts(image, bit_depth, where)
    return image


def _read_frames(root: Path, spec: CaptureSpec) -> list[list[np.ndarray]]:
    """Every light's frames ([k][j], :func:`_read_frame`), decoded on torch's threads (OpenCV's decoders let go
    of the GIL: a full TRI050S-PC frame's 16-bit PNG takes ~0.1 s); the first failing frame in order raises."""
    import torch  # (the thread count the run was given)

    keys = [(k, light, j) for k, light in enumerate(spec.lights) for j in range(spec.bracket_size)]
    read = lambda key: _read_frame(root, key[0], key[1], spec.camera.bit_depth, key[2])  # noqa: E731
    workers = min(len(keys), max(1, torch.get_num_threads()))
    if workers > 1:
        with ThreadPoolExecutor(workers) as pool:
            flat = list(pool.map(read, keys))
    else:
        flat = [read(key) for key in keys]
    nb = spec.bracket_size
    return [flat[k * nb:(k + 1) * nb] for k in range(len(spec.lights))]


def _read_ground_truth(folder: Path, frame_hw: tuple[int, int]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if not folder.is_dir():
        return out
    h, w = frame_hw
    for path in sorted(folder.iterdir()):
        suffix = path.suffix.lower()
        if not path.is_file() or suffix not in (".npy", ".json"):
            logger.debug("ignoring %s (only *.npy and *.json are ground truth)", path)
            continue
        if path.stem in out:
            raise CaptureError(f"{path}: a ground-truth file with the stem {path.stem!r} already exists; rename one")
        try:
            value: Any = np.load(path, allow_pickle=False) if suffix == ".npy" else json.loads(path.read_text("utf-8"))
        except (ValueError, OSError) as err:
            raise CaptureError(f"{path}: cannot be read as {suffix[1:].upper()} ({err})") from None
        if path.stem == "normals" and not (
            isinstance(value, np.ndarray)
            and value.ndim == 3
            and value.shape[2] == 3
            and value.shape[:2] in ((h // 2, w // 2), (h, w))
        ):
            raise CaptureError(
                f"{path}: normals must be an (H, W, 3) array of camera-frame unit normals at super-pixel "
                f"({h // 2}, {w // 2}, 3) or mosaic ({h}, {w}, 3) resolution; got {getattr(value, 'shape', type(value))}"
            )
        out[path.stem] = value
    return out


def load_capture(path: str | os.PathLike[str]) -> Capture:
    """Read and validate a capture folder.

    Args:
        path: the capture folder (or its capture.yaml).

    Returns:
        The :class:`Capture`; frames as (K, H, W) ``uint16``.

    Raises:
        CaptureError: missing or invalid capture.yaml (unknown or wrong fields), missing or
            unreadable frames, frames of different or odd sizes, counts above the bit depth,
            8-bit frames for a deeper bit depth, a mask of the wrong size, bad ground truth.
    """
    root = Path(path)
    if root.name == CAPTURE_YAML and root.is_file():
        root = root.parent
    if not root.is_dir():
        raise CaptureError(f"{root}: capture folder not found (expected a folder holding {CAPTURE_YAML} and frames/)")
    yaml_path = root / CAPTURE_YAML
    spec = parse_capture_spec(_read_yaml(yaml_path), str(yaml_path))
    bit_depth = spec.camera.bit_depth
    nb = spec.bracket_size
    images = _read_frames(root, spec)
    h, w = images[0][0].shape
    for k, light in enumerate(spec.lights):
        for j, image in enumerate(images[k]):
            if image.shape != (h, w):
                key = f"lights[{k}].frame" if j == 0 else f"lights[{k}].brackets[{j - 1}].frame"
                raise CaptureError(
                    f"{root / light.frame_paths()[j]} ({key}): is {image.shape[1]}×{image.shape[0]} (W×H) but "
                    f"{spec.lights[0].frame} is {w}×{h}; all frames must have the same size (same camera and ROI)"
                )
    stack = np.stack([[image.astype(np.uint16, copy=False) for image in light] for light in images])  # (K, B, H, W)
    del images
    frames = np.ascontiguousarray(stack[:, 0])
    brackets = np.ascontiguousarray(stack[:, 1:]) if nb > 1 else None
    _check_frames(spec, frames, str(root / spec.lights[0].frame))
    if bit_depth == 16:
        _check_alignment(stack if nb > 1 else frames, str(root / "frames"))
    del stack
    mask = None
    mask_path = root / MASK_FILE
    if mask_path.exists():
        try:
            mask_image = read_image(mask_path)
        except ImageError as err:
            raise CaptureError(f"{err} (optional object mask; remove it or save it as a grayscale PNG)") from None
        mask = _mask_to_superpixels(mask_image, (h, w), str(mask_path))
    ground_truth = _read_ground_truth(root / GROUND_TRUTH_DIR, (h, w))
    logger.info("loaded capture %s: %d light(s) × %d exposure(s) of %dx%d, %d-bit", root, len(spec.lights), nb, w, h,
                bit_depth)
    return Capture(spec=spec, frames=frames, mask=mask, ground_truth=ground_truth, root=root.resolve(),
                   brackets=brackets)


# --- write -------------------------------------------------------------------------------------


def _spec_to_yaml(spec: CaptureSpec) -> str:
    data = spec.model_dump(mode="json", exclude_none=True)
    for light in data["lights"]:
        if not light.get("brackets"):
            light.pop("brackets", None)  # format 1 has no such key; format 2 without brackets needs none
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, allow_unicode=True)


def _not_a_capture(path: Path) -> str | None:
    """Why ``overwrite`` may not replace ``path``: it exists and is neither a capture nor empty."""
    if not path.exists() or (path / CAPTURE_YAML).is_file() or (path.is_dir() and not any(path.iterdir())):
        return None
    kind = "folder" if path.is_dir() else "file"
    return (f"this {kind} is not a capture (no {CAPTURE_YAML}), and overwrite only replaces captures; choose "
            "another folder or remove it yourself")


def write_capture(path: str | os.PathLike[str], capture: Capture, *, overwrite: bool = False) -> Path:
    """Write a capture folder atomically (nothing appears at ``path`` until it is complete).

    Frames are written as 16-bit images (8-bit when ``bit_depth == 8``) at the paths the lights
    name (format 2: every exposure of every light); the mask as ``mask.png`` (super-pixel resolution, 0/255); ground-truth arrays as
    ``ground_truth/<key>.npy`` and other values as ``ground_truth/<key>.json``.
    ``load_capture(write_capture(p, c))`` reproduces ``c`` exactly.

    Args:
        path: the folder to create.
        capture: what to write (validated first).
        overwrite: replace an existing capture folder (one holding capture.yaml) or an empty
            folder at ``path`` — never any other folder or file.

    Returns:
        The folder written.

    Raises:
        OutputExistsError: ``path`` exists and ``overwrite`` is False, or it is not a capture.
    """
    _check_capture(capture)
    spec = capture.spec
    eight_bit = spec.camera.bit_depth == 8
    with atomic_directory(path, overwrite=overwrite, protect=_not_a_capture if overwrite else None) as tmp:
        for k, light in enumerate(spec.lights):
            for name, frame in zip(light.frame_paths(), capture.bracket(k), strict=True):
                write_image(tmp / name, frame.astype(np.uint8 if eight_bit else np.uint16))
        if capture.mask is not None:
            write_image(tmp / MASK_FILE, np.where(capture.mask, 255, 0).astype(np.uint8))
        for name, value in capture.ground_truth.items():
            target = tmp / GROUND_TRUTH_DIR / name
            target.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(value, np.ndarray):
                np.save(target.with_suffix(".npy"), value, allow_pickle=False)
            else:
                try:
                    text = json.dumps(value, indent=1)
                except TypeError as err:
                    raise CaptureError(
                        f"Capture.ground_truth[{name!r}]: neither an array nor JSON-serialisable ({err})"
                    ) from None
                atomic_write_text(target.with_suffix(".json"), text)
        atomic_write_text(tmp / CAPTURE_YAML, _spec_to_yaml(spec))
    logger.info("wrote capture %s (%d lights × %d exposures)", path, len(spec.lights), spec.bracket_size)
    return Path(path)
