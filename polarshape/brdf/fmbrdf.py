"""The Fresnel Microfacet BRDF (spec §1–§7): the functional entry point and its material tables.

``fmbrdf_stokes`` returns the linear Stokes vector (s0, s1, s2) reflected toward V for unit
irradiance at normal incidence from a light in direction L: surface reflection (§6) plus body
reflection (§7), in each pixel's Stokes frame (§1).

Two evaluators:
- fast (default): per-material tables (:class:`FMBRDFTables`: D's normalisation, the Smith
  projected area P(θ), and the body table W(θ_V, θ_L, Δφ)) built once for (μ, α, β, κ) by
  differentiable quadrature, then interpolated. Build a table set with :func:`build_tables` and
  pass it as ``tables=`` to evaluate many batches of one material without rebuilding.
- exact (``exact=True``): reference quadrature converged to 5e-5 relative, float64, slow, per
  element; for tests and error measurements.
Both are differentiable in N, L, V and in every parameter (μ, k_s, k_b, α, β, κ).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Union

import torch
from torch import Tensor

from polarshape.brdf.body_exact import body_integral_exact
from polarshape.brdf.body_fast import BodyTable, body_stokes_fast, build_body_table
from polarshape.brdf.distribution import d_normalisation
from polarshape.brdf.geometry import angle_between, dot, safe_normalize, shading_geometry, stokes_frame
from polarshape.brdf.smith import SmithTable, build_smith_table, projected_area_exact
from polarshape.brdf.surface import surface_stokes
from polarshape.checks import check_dtype_floating, check_finite, check_shape, check_tensor
from polarshape.errors import ShapeError

Param = Union[float, Tensor]

#: Valid parameter ranges (spec §2): name -> (lower, upper, inclusive lower).
PARAM_BOUNDS: dict[str, tuple[float, float, bool]] = {
    "ior": (1.0, 4.0, True),
    "alpha": (0.0, math.pi, False),
    "beta": (0.1, 10.0, True),
    "kappa": (0.0, 1000.0, True),
    "k_s": (0.0, math.inf, True),
    "k_b": (0.0, math.inf, True),
}


def check_param(name: str, value: Param) -> None:
    """Raise ValueError naming the parameter if any value is non-finite or outside PARAM_BOUNDS."""
    lo, hi, incl = PARAM_BOUNDS[name]
    v = torch.as_tensor(value).detach()
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"FMBRDF parameter {name!r} must be finite; got {value!r}")
    vmin, vmax = float(v.min()), float(v.max())
    if (vmin < lo if incl else vmin <= lo) or vmax > hi:
        bracket = "[" if incl else "("
        raise ValueError(f"FMBRDF parameter {name!r} must lie in {bracket}{lo}, {hi}]; got min {vmin:g}, max {vmax:g}")


def _scalar(name: str, value: Param, device: torch.device) -> Tensor:
    """0-dim float64 tensor on ``device`` (keeps autograd); table parameters must be one value."""
    t = torch.as_tensor(value, device=device)
    if t.numel() != 1:
        raise ValueError(
            f"the fast FMBRDF evaluator takes one value of {name!r} per call (one table per material); "
            f"got shape {tuple(t.shape)}. Group pixels by material, or use exact=True."
        )
    return t.reshape(()).to(device=device, dtype=torch.float64)


@dataclass(frozen=True)
class FMBRDFTables:
    """Everything the fast evaluator precomputes for one material (μ, α, β, κ), float64.

    Differentiable: the tensors carry autograd history back to the parameters they were built from.
    """

    ior: Tensor
    alpha: Tensor
    beta: Tensor
    kappa: Tensor
    c: Tensor
    smith: SmithTable
    body: BodyTable

    def to(self, device: torch.device | str) -> "FMBRDFTables":
        """The same tables on another device."""
        s = SmithTable(self.smith.warp, self.smith.excess.to(device))
        b = BodyTable(self.body.values.to(device), self.body.warp, self.body.n_modes)
        return FMBRDFTables(*(t.to(device) for t in (self.ior, self.alpha, self.beta, self.kappa, self.c)), smith=s, body=b)


def build_tables(
    *,
    ior: Param,
    alpha: Param,
    beta: Param,
    kappa: Param,
    device: torch.device | str | None = None,
    n_grid: int = 65,
    n_dphi: int | None = None,
    layout: tuple[float, float, float] | None = None,
) -> FMBRDFTables:
    """Build the fast evaluator's tables for one material (typically 10–300 ms on a CPU).

    Args:
        ior, alpha, beta, kappa: one value each (floats or 1-element tensors, may require grad).
        device: where to build (default: the device of the first tensor argument, else CPU).
        n_grid, n_dphi: body-table resolution in θ_V, θ_L and in Δφ (see build_body_table).
        layout: (α, β, κ) at which to place the quadrature nodes and grids (default: the values
            themselves). Fix it to make the tables smooth functions of the parameters with a fixed
            discretisation (gradient checks; consistent line searches in a fit).
    """
    for name, v in (("ior", ior), ("alpha", alpha), ("beta", beta), ("kappa", kappa)):
        check_param(name, v)
    if device is None:
        device = next((v.device for v in (ior, alpha, beta, kappa) if isinstance(v, Tensor)), torch.device("cpu"))
    dev = torch.device(device)
    mu, a, b, k = (_scalar(n, v, dev) for n, v in (("ior", ior), ("alpha", alpha), ("beta", beta), ("kappa", kappa)))
    c = d_normalisation(a, b, layout=None if layout is None else layout[:2])
    return FMBRDFTables(
        ior=mu, alpha=a, beta=b, kappa=k, c=c,
        smith=build_smith_table(a, b, c, layout=None if layout is None else layout[:2]),
        body=build_body_table(mu, a, b, k, c, n_grid=n_grid, n_dphi=n_dphi, layout=layout),
    )


def _check_vectors(normal: Tensor, light: Tensor, view: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    for name, v in (("normal", normal), ("light", light), ("view", view)):
        check_tensor(v, name)
        check_shape(v, ["*", "3"], name)
        check_dtype_floating(v, name)
        check_finite(v, name)  # one reduction per argument, here at the entry, never in the evaluators
    dtype = torch.promote_types(torch.promote_types(normal.dtype, light.dtype), view.dtype)
    try:
        n, l, v = torch.broadcast_tensors(normal.to(dtype), light.to(dtype), view.to(dtype))
    except RuntimeError as err:
        raise ShapeError(
            f"normal {tuple(normal.shape)}, light {tuple(light.shape)} and view {tuple(view.shape)} do not broadcast"
        ) from err
    return safe_normalize(n), safe_normalize(l), safe_normalize(v)


def fmbrdf_stokes(
    normal: Tensor,
    light: Tensor,
    view: Tensor,
    *,
    ior: Param,
    k_s: Param,
    k_b: Param,
    alpha: Param,
    beta: Param,
    kappa: Param,
    exact: bool = False,
    tables: FMBRDFTables | None = None,
) -> Tensor:
    """Polarimetric FMBRDF: Stokes (s0, s1, s2) reflected toward V for unit irradiance (spec §6–§8).

    Args:
        normal: (..., 3) surface normal N, camera frame (OpenCV: x right, y down, z forward).
        light: (..., 3) unit direction from the surface point to the light, L.
        view: (..., 3) unit direction from the surface point to the camera, V.
            The three broadcast together; they are normalised defensively. Each must be finite
            (a NaN or Inf raises ``ValueError`` naming it).
        ior: μ ≥ 1. k_s: surface albedo ≥ 0. k_b: body albedo ≥ 0 (may be per pixel, broadcastable
            to (...)). alpha: roughness α > 0 (rad). beta: shape β. kappa: correlation κ ≥ 0.
            Fast evaluator: μ, α, β, κ one value each (one table per material); k_s, k_b any
            broadcastable tensors. Exact evaluator: all parameters broadcastable.
        exact: use the reference quadrature (float64 internally, slow: ~0.01–5 s per element).
        tables: prebuilt :func:`build_tables` result for this material (fast evaluator only); its
            μ, α, β, κ are then used and the ones passed are ignored.

    Returns:
        (..., 3) Stokes vector in each pixel's Stokes frame (spec §1), dtype of the inputs; zero
        where N·L ≤ 0 or N·V ≤ 0. AoLP = ½ atan2(s2, s1), DoLP = √(s1² + s2²)/s0.

    Example:
        >>> n = torch.tensor([0.0, 0.0, -1.0]); v = torch.tensor([0.0, 0.0, -1.0])
        >>> l = torch.tensor([0.5, 0.0, -0.866])
        >>> s = fmbrdf_stokes(n, l, v, ior=1.5, k_s=1.0, k_b=0.5, alpha=0.3, beta=2.0, kappa=0.0)
        >>> s.shape
        torch.Size([3])
    """
    n, l, v = _check_vectors(normal, light, view)
    check_param("k_s", k_s)
    check_param("k_b", k_b)
    if exact:
        return _fmbrdf_stokes_exact(n, l, v, ior=ior, k_s=k_s, k_b=k_b, alpha=alpha, beta=beta, kappa=kappa)
    if tables is None:
        tables = build_tables(ior=ior, alpha=alpha, beta=beta, kappa=kappa, device=n.device)
    geo = shading_geometry(n, l, v)  # shared by both terms
    surf = surface_stokes(
        n, l, v, ior=tables.ior, k_s=k_s, alpha=tables.alpha, beta=tables.beta, c=tables.c,
        projected_area=tables.smith.projected_area, geometry=geo,
    )
    body = body_stokes_fast(tables.body, n, l, v, k_b=k_b, geometry=geo)
    return surf + body


def _fmbrdf_stokes_exact(n: Tensor, l: Tensor, v: Tensor, *, ior: Param, k_s: Param, k_b: Param, alpha: Param, beta: Param, kappa: Param) -> Tensor:
    """Reference evaluation, one element at a time in float64 (see :mod:`polarshape.brdf.body_exact`)."""
    for name, val in (("ior", ior), ("alpha", alpha), ("beta", beta), ("kappa", kappa)):
        check_param(name, val)
    dt, dev = n.dtype, n.device
    f64 = torch.float64
    params = [torch.as_tensor(p, device=dev).to(f64) for p in (ior, k_s, k_b, alpha, beta, kappa)]
    shape = torch.broadcast_shapes(n.shape[:-1], *(p.shape for p in params))
    n, l, v = (x.to(f64).expand(*shape, 3).reshape(-1, 3) for x in (n, l, v))
    mu, ks, kb, a, b, k = (p.expand(shape).reshape(-1) for p in params)
    e_x, e_y = stokes_frame(v)
    out = []
    for i in range(n.shape[0]):
        ni, li, vi = n[i], l[i], v[i]
        if not (float(dot(ni, li).detach()) > 0 and float(dot(ni, vi).detach()) > 0):
            out.append(torch.zeros(3, dtype=f64, device=dev) * (ks[i] + kb[i] + mu[i] + a[i] + b[i] + k[i]))
            continue
        c = d_normalisation(a[i], b[i], n=24)

        def area(theta: Tensor, ai: Tensor = a[i], bi: Tensor = b[i], ci: Tensor = c) -> Tensor:
            return projected_area_exact(theta, ai, bi, ci)

        surf = surface_stokes(ni, li, vi, ior=mu[i], k_s=ks[i], alpha=a[i], beta=b[i], c=c, projected_area=area)
        j = body_integral_exact(ni, li, vi, e_x[i], e_y[i], ior=mu[i], alpha=a[i], beta=b[i], kappa=k[i], c=c)
        theta_l = angle_between(ni, li)
        theta_v = angle_between(ni, vi)
        # s_b = (k_b/π) G1(L) G1(V)/(N·V) J = (k_b/π)(N·L) J / (P(L) P(V))   (spec §4, §7)
        body = (kb[i] / math.pi) * dot(ni, li) * j / (area(theta_l) * area(theta_v))
        out.append(surf + body)
    return torch.stack(out).reshape(*shape, 3).to(dt)
