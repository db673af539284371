"""Polarimetric calibration files: a sensor's per-pixel analysers, written once, referenced by captures.

``polcal.npz`` (NumPy archive, no pickles) holds the arrays of
:class:`polarshape.imaging.analyser.PolarimetricCalibration` at raw-mosaic resolution (2H, 2W):

- ``angle_rad`` float64, ``diattenuation`` float64, ``gain`` float64, ``black_level`` float64 (counts),
  ``defects`` bool;
- ``meta``: a JSON string ``{"format": "polarshape-polcal/1", "bit_depth": …, "info": {…}}``.

A capture uses it with ``camera.polarimetric_calibration: polcal.npz`` in capture.yaml (a path relative
to the capture folder, or absolute). Every problem on read is a :class:`CaptureError` naming the file
and the fix.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from polarshape.errors import CaptureError
from polarshape.imaging.analyser import PolarimetricCalibration
from polarshape.imaging.pixels import BIT_DEPTHS
from polarshape.io.atomic import atomic_path

if TYPE_CHECKING:
    from polarshape.io.capture import Capture

#: The capture.yaml field that names the calibration file (quoted in every error about it).
_FIELD = "camera.polarimetric_calibration"

__all__ = [
    "POLCAL_FORMAT", "capture_polarimetric_calibration", "read_polarimetric_calibration",
    "polarimetric_calibration_record", "resolve_polarimetric_calibration_path", "write_polarimetric_calibration",
]

#: Version string of the calibration files this module reads and writes.
POLCAL_FORMAT = "polarshape-polcal/1"
_ARRAYS = ("angle_rad", "diattenuation", "gain", "black_level", "defects")


def write_polarimetric_calibration(path: str | os.PathLike[str], calibration: PolarimetricCalibration, *,
                                   overwrite: bool = False) -> Path:
    """Write ``calibration`` to ``path`` (``.npz``) atomically; ``read_…(write_…(p, c))`` reproduces ``c``.

    Raises:
        OutputExistsError: ``path`` exists and ``overwrite`` is False.
    """
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise ValueError(f"{path}: a polarimetric calibration is a .npz file; name it e.g. polcal.npz")
    meta = {"format": POLCAL_FORMAT, "bit_depth": calibration.bit_depth, "info": calibration.info}
    arrays = {name: getattr(calibration, name).detach().cpu().numpy() for name in _ARRAYS}
    with atomic_path(path, overwrite=overwrite) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, meta=np.array(json.dumps(meta)), **arrays)
    return path


def read_polarimetric_calibration(path: str | os.PathLike[str],
                                  expect_shape: tuple[int, int] | None = None) -> PolarimetricCalibration:
    """Read and validate a calibration file.

    Args:
        path: the ``.npz`` file.
        expect_shape: (2H, 2W) the frames it is applied to must have (None: not checked).

    Raises:
        CaptureError: missing or unreadable file, wrong format version, missing or malformed arrays, a
            shape other than ``expect_shape``, values out of range.
    """
    path = Path(path)
    fix = "re-run `polarshape calibrate polarisation`, or fix camera.polarimetric_calibration in capture.yaml"
    if not path.is_file():
        raise CaptureError(f"{path}: polarimetric calibration file not found; {fix}")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [n for n in (*_ARRAYS, "meta") if n not in data.files]
            if missing:
                raise CaptureError(f"{path}: not a polarimetric calibration (missing {', '.join(missing)}); {fix}")
            meta = json.loads(str(data["meta"]))
            arrays = {n: np.array(data[n]) for n in _ARRAYS}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise CaptureError(f"{path}: cannot be read as a polarimetric calibration ({err}); {fix}") from None
    if not isinstance(meta, dict) or meta.get("format") != POLCAL_FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else meta
        raise CaptureError(f"{path}: format {got!r} is not {POLCAL_FORMAT!r}; {fix}")
    if meta.get("bit_depth") not in BIT_DEPTHS:
        raise CaptureError(f"{path}: bit_depth {meta.get('bit_depth')!r} must be one of {BIT_DEPTHS}; {fix}")
    if arrays["defects"].dtype != np.bool_:
        raise CaptureError(f"{path}: defects must be a bool array; got {arrays['defects'].dtype}; {fix}")
    shape = arrays["angle_rad"].shape
    if expect_shape is not None and tuple(shape) != tuple(expect_shape):
        raise CaptureError(
            f"{path}: is for {shape[1] if len(shape) > 1 else '?'}×{shape[0]} (W×H) frames but the capture's frames "
            f"are {expect_shape[1]}×{expect_shape[0]}: calibrate with the same sensor region (ROI, binning); {fix}"
        )
    try:
        return PolarimetricCalibration(
            **{n: torch.from_numpy(a if n == "defects" else a.astype(np.float64)) for n, a in arrays.items()},
            bit_depth=int(meta["bit_depth"]), info=dict(meta.get("info") or {}),
        )
    except (ValueError, TypeError) as err:
        raise CaptureError(f"{path}: {err}; {fix}") from None


def resolve_polarimetric_calibration_path(capture: Capture) -> Path | None:
    """The file ``camera.polarimetric_calibration`` of capture.yaml names (relative to the capture
    folder, or absolute), or None when the capture has none."""
    name = capture.spec.camera.polarimetric_calibration
    if name is None:
        return None
    path = Path(name).expanduser()
    if not path.is_absolute() and capture.root is not None:
        path = Path(capture.root) / path
    return path


def capture_polarimetric_calibration(capture: Capture) -> PolarimetricCalibration | None:
    """Read and validate the calibration a capture references (None without one).

    Raises:
        CaptureError: the file is missing or invalid, its size is not the frames', its bit depth is
            not ``camera.bit_depth``; the message names ``camera.polarimetric_calibration``.
    """
    path = resolve_polarimetric_calibration_path(capture)
    if path is None:
        return None
    where = f"{_FIELD} in capture.yaml ({capture.spec.camera.polarimetric_calibration!r})"
    if capture.root is None and not path.is_absolute():
        raise CaptureError(f"{where}: a relative path needs the capture's folder; give an absolute path")
    try:
        calibration = read_polarimetric_calibration(path, expect_shape=tuple(capture.frames.shape[-2:]))
    except CaptureError as err:
        raise CaptureError(f"{where}: {err}") from None
    if calibration.bit_depth != capture.bit_depth:
        raise CaptureError(
            f"{where}: {path} was made from {calibration.bit_depth}-bit frames but camera.bit_depth is "
            f"{capture.bit_depth}: calibrate in the pixel format the captures use"
        )
    return calibration


def polarimetric_calibration_record(capture: Capture) -> dict[str, object] | None:
    """params.json's record of the calibration a capture uses: its path and ``info`` (None without one).

    Reads only the file's JSON header (not the arrays); an unreadable header gives ``info: null``.
    """
    path = resolve_polarimetric_calibration_path(capture)
    if path is None:
        return None
    info: object = None
    try:
        with np.load(path, allow_pickle=False) as data:
            info = json.loads(str(data["meta"])).get("info")
    except (OSError, ValueError, KeyError, AttributeError, zipfile.BadZipFile):
        pass
    return {"path": str(path.absolute()), "info": info}
