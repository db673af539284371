"""MERL binary BRDF tables (Matusik et al., *A Data-Driven Reflectance Model*, SIGGRAPH 2003).

The layout the MERL/MIT database's ``BRDFRead.cpp`` reads, and with it most BRDF tools:

- a header of three little-endian int32, the dimensions ``(90, 90, 180)`` = (θ_h, θ_d, φ_d);
- then three colour channels (red, green, blue), one after the other, each 90·90·180 little-endian
  float64 in C order over (θ_h, θ_d, φ_d): flat index ``φ_d + 180·(θ_d + 90·θ_h)``;
- the stored numbers are the BRDF (1/sr) divided by a per-channel scale: the BRDF is
  ``stored · (1/1500, 1.15/1500, 1.66/1500)`` for (R, G, B);
- a negative stored number marks a missing sample (below the horizon, or not measured).

Angles (Rusinkiewicz half/difference coordinates of an isotropic BRDF, φ_h dropped): the half
vector's elevation θ_h ∈ [0, π/2] is indexed non-linearly, index = ⌊√(θ_h / (π/2)) · 90⌋ (dense near
the specular peak); the difference elevation θ_d ∈ [0, π/2) linearly, ⌊θ_d / (π/2) · 90⌋; the
difference azimuth φ_d over [0, π), ⌊φ_d / π · 180⌋, after φ_d → φ_d + π for φ_d < 0 (reciprocity:
the table stores one half of φ_d). Out-of-range indices are clamped to the table, as the reference
reader does. The sample angle of an index is the inverse map at the cell's lower edge,
θ_h = (i/90)² · π/2, θ_d = j/90 · π/2, φ_d = k/180 · π (the convention of the database's tools).

:class:`MerlTable` keeps the file's stored numbers unchanged, so a table read and written again
gives the same bytes; :attr:`MerlTable.values` is the BRDF in 1/sr. The angle ↔ index maps
(:func:`merl_angles`, :func:`merl_indices`) live with the table's geometry in
:mod:`polarshape.brdf.tabulate` and are re-exported here.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from polarshape.brdf.tabulate import MERL_SHAPE, merl_angles, merl_indices
from polarshape.io.atomic import atomic_path
from polarshape.io.material import MaterialError

__all__ = [
    "MERL_CHANNEL_SCALE",
    "MERL_MISSING",
    "MERL_SHAPE",
    "MerlTable",
    "merl_angles",
    "merl_indices",
    "read_merl",
    "write_merl",
]

logger = logging.getLogger(__name__)

#: BRDF = stored number × this, per channel (R, G, B).
MERL_CHANNEL_SCALE: tuple[float, float, float] = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)
#: The stored number written for a missing sample (any negative one is read as missing).
MERL_MISSING: float = -1.0

_HEADER_BYTES = 3 * 4
_N_CELLS = MERL_SHAPE[0] * MERL_SHAPE[1] * MERL_SHAPE[2]
_FILE_BYTES = _HEADER_BYTES + 3 * _N_CELLS * 8


def _scale() -> np.ndarray:
    """The channel scale as (3, 1, 1, 1) float64."""
    return np.asarray(MERL_CHANNEL_SCALE, dtype=np.float64).reshape(3, 1, 1, 1)


@dataclass(frozen=True)
class MerlTable:
    """A tabulated isotropic BRDF in the MERL layout.

    Attributes:
        stored: (3, 90, 90, 180) float64, the file's numbers (R, G, B; θ_h, θ_d, φ_d), negative
            where a sample is missing. Kept as stored so that writing it back is bit-exact.
    """

    stored: np.ndarray

    def __post_init__(self) -> None:
        s = self.stored
        if not isinstance(s, np.ndarray) or s.shape != (3, *MERL_SHAPE) or s.dtype != np.float64:
            got = f"{type(s).__name__} {getattr(s, 'shape', '')} {getattr(s, 'dtype', '')}"
            raise ValueError(f"MerlTable.stored must be a (3, 90, 90, 180) float64 array; got {got} "
                             "(build one from BRDF values with MerlTable.from_brdf)")

    @classmethod
    def from_brdf(cls, values: np.ndarray) -> MerlTable:
        """The table of BRDF ``values`` (3, 90, 90, 180) in 1/sr (or (90, 90, 180): the same for all
        three channels); NaN or negative values become missing samples."""
        v = np.asarray(values, dtype=np.float64)
        if v.shape == MERL_SHAPE:
            v = np.broadcast_to(v, (3, *MERL_SHAPE))
        if v.shape != (3, *MERL_SHAPE):
            raise ValueError(f"BRDF values must have shape (3, 90, 90, 180) or (90, 90, 180); got {v.shape}")
        missing = ~(v >= 0)  # NaN too
        stored = np.where(missing, MERL_MISSING, v / _scale())
        return cls(np.ascontiguousarray(stored))

    @property
    def valid(self) -> np.ndarray:
        """(3, 90, 90, 180) bool: the sample is present (stored ≥ 0)."""
        return self.stored >= 0

    @property
    def values(self) -> np.ndarray:
        """(3, 90, 90, 180) float64 BRDF in 1/sr (stored × channel scale); negative where missing."""
        return self.stored * _scale()


def read_merl(path: str | os.PathLike[str]) -> MerlTable:
    """Read a MERL binary BRDF file (``*.binary``).

    Raises:
        MaterialError: missing or unreadable file, dimensions other than (90, 90, 180), a size that
            does not match them, or non-finite numbers; the message names the file and the fix.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise MaterialError(f"{path}: cannot read the MERL BRDF file ({err.strerror or err})") from None
    if len(data) < _HEADER_BYTES:
        raise MaterialError(f"{path}: {len(data)} bytes is too short for a MERL BRDF file (a 12-byte header, "
                            f"then {_FILE_BYTES - _HEADER_BYTES} bytes of samples); is it a MERL .binary file?")
    dims = tuple(int(d) for d in np.frombuffer(data, dtype="<i4", count=3))
    if dims != MERL_SHAPE:
        raise MaterialError(f"{path}: MERL header dimensions {dims}, expected {MERL_SHAPE} (θ_h, θ_d, φ_d); only the "
                            "standard 90×90×180 isotropic table is supported: resample the BRDF to it")
    if len(data) != _FILE_BYTES:
        raise MaterialError(f"{path}: {len(data)} bytes, but a 90×90×180 MERL file has {_FILE_BYTES} "
                            "(12-byte header + 3 channels of float64): the file is truncated or not a MERL file")
    stored = np.frombuffer(data, dtype="<f8", offset=_HEADER_BYTES).astype(np.float64).reshape(3, *MERL_SHAPE)
    if not np.isfinite(stored).all():
        bad = int((~np.isfinite(stored)).sum())
        raise MaterialError(f"{path}: {bad} samples are NaN or infinite; a MERL file marks missing samples with a "
                            "negative number: rewrite them as -1")
    logger.debug("read MERL table %s: %.1f%% samples missing", path, 100.0 * float((stored < 0).mean()))
    return MerlTable(np.ascontiguousarray(stored))


def write_merl(path: str | os.PathLike[str], table: MerlTable, *, overwrite: bool = False) -> Path:
    """Write ``table`` as a MERL binary file, atomically (never over an existing file unless ``overwrite``).

    Returns:
        The path written.
    """
    path = Path(path)
    header = np.asarray(MERL_SHAPE, dtype="<i4").tobytes()
    body = np.ascontiguousarray(table.stored, dtype="<f8").tobytes()
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(header + body)
    return path
