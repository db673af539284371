"""Materials of simulated objects: polarimetric reflectance models with a per-point albedo scale.

A material answers one question: the Stokes vector (s0, s1, s2) reflected toward V for unit
irradiance at normal incidence from direction L (the N·L foreshortening is inside), in each
pixel's Stokes frame (spec fmbrdf.md §1), zero where N·L ≤ 0 or N·V ≤ 0. A per-point
``albedo_scale`` multiplies the diffuse/body albedo (k_b or k_d) — how textures act.

Colour (a colour polarisation sensor, :mod:`polarshape.imaging.colour`): white lights, so a material
reflects every colour channel with the same surface (specular) term and its own body albedo; an
FMBRDF material's ``k_b_rgb`` holds those (R, G, B) albedos and :func:`colour_albedo_factors` the
per-channel multipliers of ``k_b`` that the renderer applies to each raw pixel's colour (Stokes are
linear in k_b, so this equals rendering three colours and keeping each pixel's own). Materials
without a colour (Lambertian, Baek, an FMBRDF without ``k_b_rgb``) are grey: factors (1, 1, 1).

:func:`material_from_file` turns a ``material.json`` (:mod:`polarshape.io.material`) into one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import torch
from torch import Tensor

from polarshape.brdf.baselines import baek_pbrdf_stokes, lambertian_stokes
from polarshape.brdf.fmbrdf import FMBRDFTables, check_param, fmbrdf_stokes
from polarshape.brdf.params import FMBRDFParams
from polarshape.io.material import MaterialError, MaterialFile

__all__ = [
    "BaekMaterial", "FMBRDFMaterial", "LambertianMaterial", "Material", "colour_albedo_factors", "material_from_file",
]


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
        k_b_rgb: body albedo per colour channel (R, G, B) for a colour sensor, or None (grey:
            every channel ``k_b``). When given, ``k_b`` is set to their mean — what a mono sensor
            (and the channel-mean recovery) sees under white light.
    """

    exact: bool = False
    k_b_rgb: tuple[float, float, float] | None = None
    _tables: dict[str, FMBRDFTables] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.k_b_rgb is not None:
            rgb = tuple(float(v) for v in self.k_b_rgb)
            if len(rgb) != 3:
                raise ValueError(f"k_b_rgb must hold three body albedos (R, G, B); got {self.k_b_rgb!r}")
            for v in rgb:
                check_param("k_b", v)
            self.k_b_rgb = rgb  # type: ignore[assignment]
            self.k_b = sum(rgb) / 3.0
        self.validate()

    @property
    def colour_factors(self) -> tuple[float, float, float]:
        """(R, G, B) multipliers of ``k_b`` giving each channel's body albedo ((1, 1, 1) if grey)."""
        if self.k_b_rgb is None:
            return (1.0, 1.0, 1.0)
        if self.k_b <= 0:
            return (0.0, 0.0, 0.0)  # all channels black
        return tuple(v / self.k_b for v in self.k_b_rgb)  # type: ignore[return-value]

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


def colour_albedo_factors(material: Material) -> tuple[float, float, float]:
    """(R, G, B) multipliers of a material's body/diffuse albedo for the colour channels.

    A material with a ``colour_factors`` attribute (:class:`FMBRDFMaterial` with ``k_b_rgb``)
    gives its own; every other material is grey, (1, 1, 1).
    """
    factors = getattr(material, "colour_factors", (1.0, 1.0, 1.0))
    return (float(factors[0]), float(factors[1]), float(factors[2]))


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
