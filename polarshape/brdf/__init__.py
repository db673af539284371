"""The Fresnel Microfacet BRDF forward model (spec ../shared/spec/fmbrdf.md) and its baselines.

Main entry point: :func:`fmbrdf_stokes`. The parameter set of one material: :class:`FMBRDFParams`.
Material tables for repeated evaluation: :func:`build_tables`. Baselines of spec §10:
:mod:`polarshape.brdf.baselines`.
"""

from polarshape.brdf.baselines import (
    MODELS,
    baek_pbrdf_stokes,
    lambertian_stokes,
    oren_nayar_stokes,
    torrance_sparrow_stokes,
)
from polarshape.brdf.fmbrdf import PARAM_BOUNDS, FMBRDFTables, build_tables, fmbrdf_stokes
from polarshape.brdf.params import FMBRDF_PARAM_NAMES, FMBRDFParams
from polarshape.brdf.tabulate import fmbrdf_merl_table

__all__ = [
    "fmbrdf_stokes",
    "build_tables",
    "FMBRDFTables",
    "FMBRDFParams",
    "FMBRDF_PARAM_NAMES",
    "PARAM_BOUNDS",
    "MODELS",
    "lambertian_stokes",
    "oren_nayar_stokes",
    "torrance_sparrow_stokes",
    "baek_pbrdf_stokes",
    "fmbrdf_merl_table",
]
