"""The recovery's options: one definition, used by the solvers and embedded in ``polarshape run``'s
configuration as its ``initial_normals`` and ``recovery`` sections (validated once, at the edge).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["InitialNormalsOptions", "RecoveryOptions"]


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
    max_outer_iterations: int = Field(20, ge=1, le=1000, description="most alternations of material and normals")
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
