"""``material.json``: a fitted reflectance model that can leave the fit and come back.

A material file holds one model of :data:`polarshape.brdf.MODELS` (``fmbrdf`` and the baselines)
with its parameters, their units, how well the fit explained its data and where the data came
from. ``polarshape material`` writes it; ``polarshape run`` (``recovery.material``) and scene files
(``material: {file: ...}``) read it.

::

    {
      "format": "polarshape-material/1",
      "model": "fmbrdf",
      "parameters": {"ior": 1.52, "alpha": 0.24, "beta": 2.0, "kappa": 0.0, "k_s": 0.91, "k_b": 0.47},
      "units": {"ior": "1", "alpha": "rad", ...},
      "fit": {"objective": "eq25", "observations": 5210, "residual_rms": 0.0031, ...},
      "source": {"capture": "/data/sphere_cap", "frames": ["frames/000.png"], "shape": "sphere", ...}
    }

Parameters must be exactly the model's, finite and inside its bounds (``fmbrdf``: spec §2,
:data:`polarshape.brdf.PARAM_BOUNDS`; the baselines: :data:`MODELS`); ``fit`` and
``source`` are free-form records (JSON objects). Every problem is a :class:`MaterialError` naming
the file, the key and the fix.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from polarshape.brdf import MODELS
from polarshape.brdf.params import FMBRDF_PARAM_NAMES, FMBRDFParams
from polarshape.errors import ConfigError
from polarshape.io.atomic import atomic_write_text
from polarshape.io.results import plain_json

__all__ = ["MATERIAL_FORMAT", "MATERIAL_UNITS", "MaterialError", "MaterialFile", "load_material", "write_material"]

#: Version tag of the material file format.
MATERIAL_FORMAT = "polarshape-material/1"

#: Units of every parameter name any model uses (albedos are in the capture's units: fraction of
#: full scale per unit light intensity).
MATERIAL_UNITS: dict[str, str] = {
    "ior": "1 (refractive index)",
    "alpha": "rad (microfacet roughness)",
    "beta": "1 (shape of the microfacet distribution)",
    "kappa": "1 (microfacet correlation)",
    "k_s": "fraction of full scale per unit light intensity (surface albedo)",
    "k_b": "fraction of full scale per unit light intensity (body albedo)",
    "k_d": "fraction of full scale per unit light intensity (diffuse albedo)",
    "sigma": "rad (Oren-Nayar roughness)",
    "roughness": "1 (Torrance-Sparrow Beckmann slope)",
}


class MaterialError(ConfigError):
    """A material file that cannot be read or does not hold a valid material (exit status 2)."""


class MaterialFile(BaseModel):
    """One material: model, parameters (exactly the model's, within its bounds), units, fit, source."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    format: Literal["polarshape-material/1"] = MATERIAL_FORMAT
    model: Literal["lambertian", "oren_nayar", "torrance_sparrow", "baek", "fmbrdf"]
    parameters: dict[str, float]
    units: dict[str, str] = Field(default_factory=dict)
    fit: dict[str, Any] = Field(default_factory=dict)
    source: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _parameters_of_the_model(self) -> MaterialFile:
        bounds = MODELS[self.model].params
        given, wanted = set(self.parameters), set(bounds)
        if given != wanted:
            missing, extra = sorted(wanted - given), sorted(given - wanted)
            raise ValueError(
                f"parameters of model {self.model!r} are {sorted(wanted)}"
                + (f"; missing {missing}" if missing else "") + (f"; not of this model {extra}" if extra else "")
            )
        if self.model == "fmbrdf":  # the forward model's own ranges (spec §2)
            FMBRDFParams(**self.parameters).validate()
            return self
        for name, value in self.parameters.items():
            lo, hi = bounds[name]
            if not math.isfinite(value) or not lo <= value <= hi:
                raise ValueError(f"parameters.{name} = {value!r} is outside [{lo}, {hi}] for model {self.model!r}")
        return self

    @classmethod
    def from_fmbrdf(cls, params: FMBRDFParams, *, fit: dict[str, Any] | None = None,
                    source: dict[str, Any] | None = None) -> MaterialFile:
        """The FMBRDF material of ``params`` (units filled in)."""
        values = {name: float(getattr(params, name)) for name in FMBRDF_PARAM_NAMES}
        return cls(model="fmbrdf", parameters=values, units={k: MATERIAL_UNITS[k] for k in values},
                   fit=plain_json(fit or {}), source=plain_json(source or {}))

    def fmbrdf_params(self) -> FMBRDFParams:
        """The parameters as :class:`FMBRDFParams` (only for ``model: fmbrdf``).

        Raises:
            MaterialError: another model.
        """
        if self.model != "fmbrdf":
            raise MaterialError(f"material model {self.model!r} is not 'fmbrdf': only an FMBRDF material can be "
                                "used here (fit one with `polarshape material ... --models fmbrdf`)")
        return FMBRDFParams(**{name: self.parameters[name] for name in FMBRDF_PARAM_NAMES})


def load_material(path: str | os.PathLike[str]) -> MaterialFile:
    """Read and validate a ``material.json``.

    Raises:
        MaterialError: missing or unreadable file, not JSON, a duplicate key, an invalid material.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise MaterialError(f"{path}: cannot read the material file ({err.strerror or err})") from None

    def unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in pairs:
            if key in out:
                raise MaterialError(f"{path}: key {key!r} appears twice; keep one")
            out[key] = value
        return out

    try:
        data = json.loads(text, object_pairs_hook=unique)
    except json.JSONDecodeError as err:
        raise MaterialError(f"{path}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
    if not isinstance(data, dict):
        raise MaterialError(f"{path}: a material file is a JSON object with format, model and parameters")
    if data.get("format") != MATERIAL_FORMAT:
        raise MaterialError(f"{path}: format must be {MATERIAL_FORMAT!r}; got {data.get('format')!r} (is this a "
                            "material written by `polarshape material`?)")
    try:
        return MaterialFile.model_validate(data)
    except ValidationError as err:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or 'material'}: {e['msg']}" for e in err.errors())
        raise MaterialError(f"{path}: {problems}") from None


def write_material(path: str | os.PathLike[str], material: MaterialFile, *, overwrite: bool = False) -> Path:
    """Write ``material`` as JSON, atomically (never over an existing file unless ``overwrite``)."""
    path = Path(path)
    atomic_write_text(path, json.dumps(material.model_dump(mode="json"), indent=1, allow_nan=False) + "\n",
                      overwrite=overwrite)
    return path
