"""Reference evaluator of the FMBRDF body term (spec §7): direct 4-D quadrature, float64.

For one geometry (N, L, V) the double hemisphere integral

    J = ∫∫ [n·V]₊ D(n) T-Stokes(θ_o, ψ(n)) · exp(κ n·n_i)/Z(n_i) · [n_i·L]₊ D(n_i) T+(θ_i) dω_n dω_{n_i}

is evaluated on two tensor-product rules, one over exit facets n (around N, azimuth measured from
V, integrated only over the arc where n·V > 0, whose ends are closed form) and one over entry
facets n_i (likewise for L). θ panels are graded to α and have a breakpoint at the horizon kink
θ = π/2 − θ_V (resp. θ_L). Z(θ') (eq. 20) is integrated with its azimuth done exactly by the
modified Bessel function I₀. Stokes angles ψ(n) are taken in the pixel frame of spec §1
directly. This shares no tabulation, interpolation or Fourier expansion with
:mod:`polarshape.brdf.body_fast`, which it validates. The rules are refined together until the
result changes by less than ``rtol`` (relative to s0) between levels: adaptive p-refinement.

Differentiable in N, L, V and every parameter: node positions are fixed in the local frames, which
are built from N, L, V with autograd (the clipped integrand vanishes at the arc ends, so moving
limits add no boundary terms).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch
from torch import Tensor

from polarshape.brdf.distribution import d_shape
from polarshape.brdf.fresnel import fresnel
from polarshape.brdf.geometry import angle_between, dot, double_angle, safe_normalize
from polarshape.brdf.quadrature import HALF_PI, composite_rule, gauss_legendre, theta_breaks

logger = logging.getLogger(__name__)

#: (θ points per panel, azimuth points per arc) for each refinement level.
LEVELS: tuple[tuple[int, int], ...] = ((5, 20), (7, 28), (10, 40), (14, 56), (20, 80))


def _tangent(normal: Tensor, toward: Tensor, fallback: Tensor) -> Tensor:
    """Unit tangent of N pointing to ``toward``'s azimuth (``fallback``'s when toward ∥ N)."""
    t = toward - dot(normal, toward) * normal
    if float(dot(t, t).detach()) < 1e-20:
        t = fallback - dot(normal, fallback) * normal
    return safe_normalize(t)


def _facet_rule(
    normal: Tensor, direction: Tensor, fallback: Tensor, alpha: float, beta: float, n_t: int, n_p: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Facet normals (M, 3), weights (M,) incl. sin θ, and polar angles (M,) over the facets that
    see ``direction`` (n·direction > 0)."""
    theta_w = float(angle_between(normal, direction).detach())
    tq, wq = composite_rule(theta_breaks(alpha, beta, max_width=0.05, extra=(HALF_PI - theta_w,)), n_t)
    x, w = gauss_legendre(n_p)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (np.cos(tq) * math.cos(theta_w)) / (np.sin(tq) * math.sin(theta_w))
    full = ~(r < 1.0)
    phic = np.where(full, math.pi, np.arccos(-np.clip(np.nan_to_num(r, nan=1.0, posinf=1.0), -1.0, 1.0)))
    phi = (phic[:, None] * x[None, :]).ravel()
    theta = np.repeat(tq, n_p)
    weight = (wq[:, None] * phic[:, None] * w[None, :]).ravel() * np.sin(theta)
    t1 = _tangent(normal, direction, fallback)
    t2 = torch.linalg.cross(normal, t1, dim=-1)

    def T(v: np.ndarray) -> Tensor:
        return torch.as_tensor(v, dtype=normal.dtype, device=normal.device)

    th, ph = T(theta), T(phi)
    n = (torch.sin(th) * torch.cos(ph))[:, None] * t1 + (torch.sin(th) * torch.sin(ph))[:, None] * t2 + torch.cos(th)[:, None] * normal
    return n, T(weight), th


def _z_normaliser(theta_i: Tensor, alpha: Tensor, beta: Tensor, c: Tensor, kappa: Tensor, n_t: int) -> Tensor:
    """Z(θ') = ∫_Ω exp(κ(n·n_i − 1)) D(n) dω_n (eq. 20, scaled by e^{−κ}) for (M,) θ'.

    The azimuthal integral is 2π e^{κ(cos θ cos θ' − 1)} I₀(κ sin θ sin θ'), written with the
    exponentially scaled i0e for stability."""
    tq, wq = composite_rule(theta_breaks(float(alpha.detach()), float(beta.detach()), max_width=0.02), n_t + 4)
    th = torch.as_tensor(tq, dtype=theta_i.dtype, device=theta_i.device)
    w = torch.as_tensor(wq, dtype=theta_i.dtype, device=theta_i.device)
    dq = w * torch.sin(th) * c * d_shape(th, alpha, beta)  # (Q,)
    z_arg = kappa * torch.sin(th)[None, :] * torch.sin(theta_i)[:, None]
    kern = torch.exp(kappa * (torch.cos(th[None, :] - theta_i[:, None]) - 1.0)) * torch.special.i0e(z_arg)
    return 2.0 * math.pi * (kern * dq).sum(-1)


def body_integral_exact(
    normal: Tensor,
    light: Tensor,
    view: Tensor,
    e_x: Tensor,
    e_y: Tensor,
    *,
    ior: Tensor,
    alpha: Tensor,
    beta: Tensor,
    kappa: Tensor,
    c: Tensor,
    rtol: float = 5e-5,
    chunk: int = 4096,
) -> Tensor:
    """J (3,) = (J0, J1, J2) in the pixel frame for one front-facing geometry (all (3,) float64).

    Refines until successive levels differ by < ``rtol``·|J0| in every component; logs a warning if
    the last level is reached unconverged.
    """
    a, b, kap = float(alpha.detach()), float(beta.detach()), float(kappa.detach())
    prev: Tensor | None = None
    change = float("inf")
    for n_t, n_p in LEVELS:
        nv, wv, tv = _facet_rule(normal, view, light, a, b, n_t, n_p)
        nl, wl, tl = _facet_rule(normal, light, view, a, b, n_t, n_p)
        fo = fresnel(dot(nv, view).clamp_min(0.0), ior)
        cos2, sin2 = double_angle(nv, e_x, e_y)  # ψ(n) in the pixel frame (spec §1, §5)
        hv = (wv * dot(nv, view).clamp_min(0.0) * c * d_shape(tv, alpha, beta))[:, None] * torch.stack(
            [fo.t_plus, -fo.t_minus * cos2, -fo.t_minus * sin2], dim=-1
        )  # (Mv, 3)
        fi = fresnel(dot(nl, light).clamp_min(0.0), ior)
        gl = wl * dot(nl, light).clamp_min(0.0) * c * d_shape(tl, alpha, beta) * fi.t_plus  # (Ml,)
        gl = gl / _z_normaliser(tl, alpha, beta, c, kappa, n_t)
        if kap == 0.0:
            j = hv.sum(0) * gl.sum()
        else:
            j = torch.zeros(3, dtype=normal.dtype, device=normal.device)
            for s in range(0, nl.shape[0], chunk):
                kern = torch.exp(kappa * (nv @ nl[s : s + chunk].T - 1.0))  # (Mv, chunk)
                j = j + hv.T @ (kern @ gl[s : s + chunk])
        if prev is not None:
            change = float((j - prev).detach().abs().max()) / max(abs(float(j[0].detach())), 1e-300)
            if change <= rtol:
                return j
        prev = j
    logger.warning("exact body integral not converged to rtol=%g (last relative change %.3g)", rtol, change)
    return j
