"""The recovery's options: one definition, used by the solvers and embedded in ``polarshape run``'s
configuration as its ``initial_normals`` and ``recovery`` sections (validated once, at the edge).

``recovery.material`` names a known material (a ``material.json`` of ``polarshape material``,
:mod:`polarshape.io.material`); a relative path starts at the folder of the run configuration
(the validation context's ``base_dir``, as for ``input.path``), else at the working directory.
The file is read and checked here, so a missing or invalid material fails before anything runs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from polarshape.io.material import MaterialError, load_material
from polarshape.io.yamlfile import resolve_config_path

__all__ = ["InitialNormalsOptions", "MATERIAL_USES", "MAX_MATERIALS", "RecoveryOptions", "VALIDATION_MODELS", "ValidationOptions"]

#: Most materials ``recovery.materials`` may ask for (and ``auto`` looks for).
MAX_MATERIALS = 4

#: What ``recovery.material_use`` may say: ``fixed`` (the material's μ, α, β, κ are not re-fitted)
#: or ``initial`` (they start the global fit).
MATERIAL_USES: tuple[str, ...] = ("fixed", "initial")


class _Options(BaseModel):
    # allow_inf_nan=False: ``noise_std: .inf`` is a validation error naming the key, not a failure later
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class InitialNormalsOptions(_Options):
    """Robust Lambertian photometric stereo on s0 (:func:`polarshape.recover.photometric.robust_lambertian_ps`):
    the start of the FMBRDF fit and the whole answer of the ``lambertian`` model. Runs once per recovery."""

    dark_rel: float = Field(0.02, ge=0.0, lt=1.0, description="shadow threshold relative to the brightest observation")
    outlier_rel: float = Field(0.03, gt=0.0, le=10.0, description="highlight threshold relative to the fitted shading")
    noise_std: float = Field(
        0.0, ge=0.0, description="intensity noise sigma (fraction of full scale); the capture's own quantisation "
        "noise estimate is used when larger"
    )


class RecoveryOptions(_Options):
    """Reflectometry and joint refinement of normals and FMBRDF parameters (:func:`polarshape.normals.recover_normals`)."""

    model: Literal["auto", "fmbrdf", "lambertian"] = Field(
        "auto", description="fmbrdf = Fresnel microfacet BRDF joint fit; lambertian = robust Lambertian PS only; "
        "auto = fmbrdf unless the data are unpolarised and Lambertian PS explains them"
    )
    per_pixel_albedo: bool = Field(True, description="one body albedo k_b per pixel (false: one global k_b)")
    fit_kappa: bool | None = Field(None, description="fit the microfacet correlation kappa (null: the recovery decides)")
    max_outer_iterations: int = Field(
        20, ge=1, le=1000, description="most alternations of material and normals (solver joint: most iterations "
        "of the joint Levenberg-Marquardt on the coarsest level)"
    )
    solver: Literal["joint", "alternating"] = Field(
        "alternating", description="coarsest level: joint = normals and material in one Levenberg-Marquardt (Schur "
        "complement of the per-pixel blocks); alternating = material and normals in turn"
    )
    subsample_pixels: int = Field(4096, ge=64, description="pixels used for the material fit")
    coarse_to_fine: bool = Field(True, description="solve on an image pyramid, coarsest level first")
    propagate: bool = Field(
        True, description="after each per-pixel solve, pixels try their neighbours' normals and keep a better fit "
        "(escapes per-pixel local minima)"
    )
    smoothness: float = Field(
        0.0, ge=0.0, le=100.0, description="weight of a normal-smoothness prior after the per-pixel fit (0: per-pixel "
        "maximum likelihood; 0.5: a neighbour weighs half a typical pixel's own data; smooths across creases)"
    )
    materials: Literal["auto"] | int = Field(
        "auto", description="how many materials the object is made of: auto = as many as the data need (a split is "
        "kept when its penalised likelihood pays; 1 when one material explains them), or a number (1: one material "
        "for the whole mask)"
    )
    material: str | None = Field(
        None, description="a known FMBRDF material: a material.json (polarshape material), relative to the config "
        "file's folder; null: fit the material from this capture"
    )
    material_use: Literal["fixed", "initial"] = Field(
        "fixed", description="fixed: keep the material's ior, alpha, beta, kappa and fit only normals and albedos "
        "(k_s, the per-pixel k_b; with per_pixel_albedo false one scale of k_s and k_b, r_k kept); initial: start the "
        "global fit from the material instead of the default guess"
    )

    @field_validator("material")
    @classmethod
    def _material_file(cls, value: str | None, info: ValidationInfo) -> str | None:
        """Resolve against the config's folder and check that the file holds an FMBRDF material."""
        if value is not None and not value.strip():
            raise ValueError("must be the path of a material.json, or null")
        resolved = resolve_config_path(value, info)
        if resolved is None:
            return None
        path = Path(resolved)
        try:
            material = load_material(path)
        except MaterialError as err:  # a ValueError here is reported under the key recovery.material
            raise ValueError(f"{err} (relative paths start at the config file's folder)") from None
        try:
            material.fmbrdf_params()
        except MaterialError as err:
            raise ValueError(f"{path}: {err}") from None
        return str(path)

    @field_validator("materials")
    @classmethod
    def _materials_count(cls, value: str | int) -> str | int:
        if isinstance(value, int) and not 1 <= value <= MAX_MATERIALS:
            raise ValueError(f"must be auto or a number of materials from 1 to {MAX_MATERIALS}, got {value}")
        return value

    @model_validator(mode="after")
    def _material_needs_fmbrdf(self) -> RecoveryOptions:
        if self.material is not None and self.model == "lambertian":
            raise ValueError("recovery.material applies to the fmbrdf model and recovery.model is 'lambertian' "
                             "(photometric stereo has no material to fix); remove recovery.material or set "
                             "recovery.model to fmbrdf or auto")
        if self.material is not None and isinstance(self.materials, int) and self.materials > 1:
            raise ValueError(f"recovery.material is one known material and recovery.materials asks for "
                             f"{self.materials}: remove recovery.material, or set recovery.materials to 1 or auto")
        return self


#: The models the held-out validation can compare (:mod:`polarshape.recover.validation`).
VALIDATION_MODELS: tuple[str, ...] = ("fmbrdf", "lambertian", "l_ts", "baek")


class ValidationOptions(_Options):
    """Held-out-light validation of the run (:func:`polarshape.recover.validation.validate_holdout`):
    fit on the other lights, predict the held-out frames, compare models on the user's own data."""

    holdout: Literal["auto", "none"] | list[int] = Field(
        "auto", description="auto: a few lights spread over the dome (when the capture has at least min_lights); "
        "none: no validation; a list: these light indices (0-based frame order)"
    )
    models: list[Literal["fmbrdf", "lambertian", "l_ts", "baek"]] = Field(
        list(VALIDATION_MODELS), min_length=1, description="models fitted without the held-out lights and compared "
        "on them (fmbrdf warm-started from the run); unset with recovery.model lambertian: lambertian only (the "
        "others cost an FMBRDF fit)"
    )
    lights: int = Field(3, ge=1, le=64, description="how many lights holdout: auto holds out")
    min_lights: int = Field(6, ge=4, le=1000, description="holdout: auto skips the validation below this many lights")
    max_pixels: int = Field(
        2048, ge=64, description="most mask pixels the folds fit and predict: a regular lattice (every s-th row and "
        "column) when the mask has more; the errors are means over them"
    )
