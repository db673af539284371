"""Materials of simulated objects: polarimetric reflectance models with a per-point albedo scale.

A material answers one question: the Stokes vector (s0, s1, s2) reflected toward V for unit
irradiance at normal incidence from direction L (the N·L foreshortening is inside), in each
pixel's Stokes frame (spec fmbrdf.md §1), zero where N·L ≤ 0 or N·V ≤ 0. A per-point
``albedo_scale`` multiplies the diffuse/body albedo (k_b or k_d) — how textures act.

:func:`material_from_file` turns a ``material.json`` (:mod:`polarshape.io.material`) into one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import torch
from torch import Tensor

from polarshape.brdf.baselines import baek_pbrdf_stokes, lambertian_stokes
from polarshape.brdf.fmbrdf import FMBRDFTables, fmbrdf_stokes
from polarshape.brdf.params import FMBRDFParams
from polarshape.io.material import MaterialError, MaterialFile

__all__ = ["BaekMaterial", "FMBRDFMaterial", "LambertianMaterial", "Material", "material_from_file"]


@runtime_checkable
class Material(Protocol):
    """What the renderer needs from a material."""

    def stokes(self, normal: Tensor, light: Tensor, view: Tensor, albedo_scale: Tensor) -> Tensor:
        """Stokes for unit irradiance.

        Args:
            normal, light, view: (M, 3) unit N, L (to the light), V (to the camera), camera frame.
            albedo_scale: (M,) multiplier of the diffuse/body albedo (1 = untextured).

        Returns:
            (M, 3) (s0, s1, s2) in each point's Stokes frame (spec §1).
        """
        ...


@dataclass
class FMBRDFMaterial(FMBRDFParams):
    """The Fresnel Microfacet BRDF (spec §2–§7), via :func:`polarshape.brdf.fmbrdf_stokes`: an
    :class:`~polarshape.brdf.FMBRDFParams` (checked on construction) that renders.

    The fast evaluator's tables for (ior, alpha, beta, kappa) are built once per device and kept,
    so rendering many lights costs one table build. ``k_b`` is scaled per point by a texture.

    Attributes:
        exact: use the reference quadrature instead of the tables (slow; tests only).
    """

    exact: bool = False
    _tables: dict[str, FMBRDFTables] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.validate()

    def tables_on(self, device: torch.device | str) -> FMBRDFTables:
        """This material's fast-path tables on ``device``, built once per device and kept."""
        key = str(device)
        if key not in self._tables:
            self._tables[key] = self.build_tables(device=device)
        return self._tables[key]

    def stokes(self, normal: Tensor, light: Tensor, view: Tensor, albedo_scale: Tensor) -> Tensor:
        params = {**self.as_kwargs(), "k_b": self.k_b * albedo_scale}
        if self.exact:
            return fmbrdf_stokes(normal, light, view, exact=True, **params)
        return fmbrdf_stokes(normal, light, view, tables=self.tables_on(normal.device), **params)


@dataclass
class LambertianMaterial:
    """Lambertian, unpolarised (spec §10): s0 = (k_d/π)(N·L)₊, s1 = s2 = 0, via
    :func:`polarshape.brdf.baselines.lambertian_stokes`."""

    k_d: float = 0.5

    def __post_init__(self) -> None:
        if not self.k_d >= 0:
            raise ValueError(f"lambertian k_d must be >= 0, got {self.k_d}")

    def stokes(self, normal: Tensor, light: Tensor, view: Tensor, albedo_scale: Tensor) -> Tensor:
        return lambertian_stokes(normal, light, view, k_d=self.k_d * albedo_scale)


@dataclass
class BaekMaterial:
    """Baek et al. 2018 pBRDF (spec §10), via :func:`polarshape.brdf.baselines.baek_pbrdf_stokes`.

    Attributes:
        ior: μ. k_s: specular albedo. k_d: diffuse albedo (scaled per point by a texture).
        alpha: roughness (GGX α, or Beckmann RMS slope). distribution: ``ggx`` or ``beckmann``
            (Beckmann = Mitsuba 3's ``pplastic``).
    """

    ior: float = 1.5
    k_s: float = 1.0
    k_d: float = 0.5
    alpha: float = 0.3
    distribution: Literal["ggx", "beckmann"] = "ggx"

    def __post_init__(self) -> None:
        if not (self.ior >= 1 and self.k_s >= 0 and self.k_d >= 0 and self.alpha > 0):
            raise ValueError(f"baek material needs ior >= 1, k_s >= 0, k_d >= 0, alpha > 0; got {self}")
        if self.distribution not in ("ggx", "beckmann"):
            raise ValueError(f"baek distribution must be ggx or beckmann, got {self.distribution!r}")

    def stokes(self, normal: Tensor, light: Tensor, view: Tensor, albedo_scale: Tensor) -> Tensor:
        return baek_pbrdf_stokes(
            normal, light, view, ior=self.ior, k_s=self.k_s, k_d=self.k_d * albedo_scale, alpha=self.alpha,
            distribution=self.distribution,
        )


def material_from_file(material: MaterialFile, source: str = "material file") -> Material:
    """The simulator's material of a ``material.json``: ``fmbrdf`` → :class:`FMBRDFMaterial`,
    ``lambertian`` → :class:`LambertianMaterial` (k_d), ``baek`` → :class:`BaekMaterial` (ior, k_s,
    k_d, alpha; GGX, the distribution :func:`polarshape.brdf.baselines.baek_pbrdf_stokes` fits with).

    Raises:
        MaterialError: a model the simulator has no material for (``oren_nayar``, ``torrance_sparrow``),
            naming ``source`` and the fix.
    """
    values = material.parameters
    if material.model == "fmbrdf":
        return FMBRDFMaterial(**material.fmbrdf_params().as_kwargs())
    if material.model == "lambertian":
        return LambertianMaterial(values["k_d"])
    if material.model == "baek":
        return BaekMaterial(values["ior"], values["k_s"], values["k_d"], values["alpha"])
    raise MaterialError(f"{source}: model {material.model!r} has no simulator material (scenes render fmbrdf, "
                        "lambertian and baek); fit one of those (`polarshape material ... --models fmbrdf`)")
