"""The FMBRDF's material parameters (spec §2) as one type.

Used by the simulator's material (:class:`polarshape.scene.materials.FMBRDFMaterial` is one), scene
files (:class:`polarshape.scene.config.FMBRDFConfig` is one), the demo and reflectometry (the fitted
global parameters). The valid range of each parameter is :data:`polarshape.brdf.PARAM_BOUNDS`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from polarshape.brdf.fmbrdf import FMBRDFTables, build_tables, check_param

__all__ = ["FMBRDF_PARAM_NAMES", "FMBRDFParams"]

#: The parameter names, in field order (keyword arguments of :func:`polarshape.brdf.fmbrdf_stokes`).
FMBRDF_PARAM_NAMES: tuple[str, ...] = ("ior", "alpha", "beta", "kappa", "k_s", "k_b")


@dataclass
class FMBRDFParams:
    """The six FMBRDF parameters of one material (spec §2).

    A plain (mutable) dataclass, so ``FMBRDFParams(**{**vars(p), "kappa": 20.0})`` copies with a
    change. Values are not checked on construction (a fit may hold any value while it searches);
    call :meth:`validate` where they come from a user.

    Attributes:
        ior: refractive index μ, in [1, 4].
        alpha: roughness α, radians, in (0, π].
        beta: shape β of the microfacet distribution D, in [0.1, 10].
        kappa: microfacet correlation κ, in [0, 1000].
        k_s: surface albedo, ≥ 0.
        k_b: body albedo, ≥ 0 (reflectometry keeps the global or median per-pixel value here).
    """

    ior: float = 1.5
    alpha: float = 0.3
    beta: float = 2.0
    kappa: float = 0.0
    k_s: float = 1.0
    k_b: float = 0.5

    def validate(self) -> None:
        """Raise ValueError naming the first parameter that is non-finite or outside
        :data:`polarshape.brdf.PARAM_BOUNDS`."""
        for name in FMBRDF_PARAM_NAMES:
            check_param(name, float(getattr(self, name)))

    def as_kwargs(self) -> dict[str, float]:
        """The six parameters by name: keyword arguments of :func:`polarshape.brdf.fmbrdf_stokes`."""
        return {name: getattr(self, name) for name in FMBRDF_PARAM_NAMES}

    def as_dict(self) -> dict[str, float]:
        """The six parameters and the albedo ratio ``r_k = k_b / k_s`` (inf when k_s = 0), as
        written to params.json."""
        r_k = self.k_b / self.k_s if self.k_s > 0 else math.inf
        return {**self.as_kwargs(), "r_k": r_k}

    def build_tables(self, device: torch.device | str | None = None, n_grid: int = 65) -> FMBRDFTables:
        """The fast evaluator's tables of this material's (μ, α, β, κ) at body grid ``n_grid`` (see
        :func:`polarshape.brdf.build_tables`)."""
        return build_tables(ior=self.ior, alpha=self.alpha, beta=self.beta, kappa=self.kappa, device=device,
                            n_grid=n_grid)
