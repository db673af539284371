"""Spatial priors on the per-pixel normals: the MAP smoothness prior and filling pixels without data.

- :func:`map_smoothing` — maximum a posteriori normals under a first-order smoothness prior, from
  each pixel's maximum-likelihood estimate and its Gauss–Newton information
  (:func:`polarshape.recover.normal_solver.normal_information`);
- :func:`smooth_normals` — that prior applied to a fitted material (information, MAP, k_b re-solved);
- :func:`fill_unsupported` — mask pixels with too few usable observations take their neighbours'.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor

from polarshape.brdf.fmbrdf import build_tables
from polarshape.brdf.params import FMBRDFParams
from polarshape.metrics import angular_error_deg
from polarshape.recover.normal_solver import NEIGHBOURS_8, NormalProblem, huber_delta, normal_information, unit
from polarshape.recover.observations import RecoveryInputs, flatten_observations

logger = logging.getLogger(__name__)

__all__ = ["MIN_OBSERVATIONS", "fill_unsupported", "map_smoothing", "shift", "smooth_normals"]

#: Usable observations a pixel needs for its own normal (2 DoF + its albedo; photometric stereo's 3).
MIN_OBSERVATIONS = 3

_SHIFTS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def shift(x: Tensor, dy: int, dx: int) -> Tensor:
    """x[i + dy, j + dx] at (i, j) (zeros past the border); x is (H, W, ...)."""
    out = torch.zeros_like(x)
    h, w = x.shape[:2]
    out[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)] = x[max(dy, 0):h - max(-dy, 0), max(dx, 0):w - max(-dx, 0)]
    return out


def _edge_weights(n_hat: Tensor, half_trace: Tensor, pixels: Tensor, lam: float) -> list[Tensor]:
    """Robust prior weights (H, W) per 4-neighbour shift: where the estimates bend faster than their
    noise explains (a limb, a crease), the local Laplacian of n̂ exceeds 3σ_p
    (σ_p² = 1 / (½ trace I_p)) and the prior lets go."""
    inside = pixels.to(n_hat.dtype)
    nb_sum = sum(shift(n_hat, dy, dx) for dy, dx in _SHIFTS)
    nb_cnt = sum(shift(inside, dy, dx) for dy, dx in _SHIFTS) * inside
    laplacian = (n_hat - nb_sum / nb_cnt.clamp_min(1).unsqueeze(-1)).norm(dim=-1)  # (H, W)
    sigma = half_trace.clamp_min(1e-12).rsqrt()
    g = torch.where(pixels & (nb_cnt == 4), 1.0 / (1.0 + (laplacian / (3 * sigma)) ** 2), torch.zeros_like(sigma))
    return [lam * torch.minimum(g, shift(g, dy, dx)) for dy, dx in _SHIFTS]  # (H, W) each, 0 off the mask


def map_smoothing(
    normals: Tensor, info: Tensor, pixels: Tensor, smoothness: float, iterations: int = 60
) -> tuple[Tensor, float]:
    """Maximum a posteriori normals under a first-order smoothness prior, from the per-pixel fit.

    Near each pixel's maximum-likelihood normal n̂_p the data term is ≈ (n − n̂_p)ᵀ I_p (n − n̂_p)
    with I_p the Gauss–Newton information. Adding the prior λ Σ_{p~q} |n_p − n_q|² over 4-neighbours
    inside the mask gives the sparse linear system (I_p + λ d_p) n_p − λ Σ_q n_q = I_p n̂_p, solved
    by Jacobi iterations (I_p is completed along n̂_p with its mean eigenvalue, so that the blocks
    are diagonally dominant), then renormalised. λ = ``smoothness`` × the median of ½ trace I_p: at
    smoothness 1 a neighbour weighs as much as a typical pixel's own data. Pixels with strong data
    keep their estimate; noisy ones borrow from their neighbours. A quadratic prior also smooths
    across creases and depth edges inside the mask: keep ``smoothness`` 0 where they matter.

    Args:
        normals: (H, W, 3) per-pixel estimates n̂ (NaN outside ``pixels``).
        info: (H, W, 3, 3) information of each estimate (zeros outside ``pixels``).
        pixels: (H, W) bool.
        smoothness: prior weight ≥ 0 (dimensionless, above).
        iterations: Jacobi iterations.

    Returns:
        (H, W, 3) smoothed unit normals (NaN outside ``pixels``), and λ.
    """
    n_hat = torch.where(pixels.unsqueeze(-1), normals, torch.zeros_like(normals))
    half_trace_img = info.diagonal(dim1=-2, dim2=-1).sum(-1) / 2  # (H, W)
    half_trace = half_trace_img[pixels]
    lam = smoothness * float(half_trace.median()) if half_trace.numel() else 0.0
    if lam <= 0:
        return normals, lam
    weights = _edge_weights(n_hat, half_trace_img, pixels, lam)
    degree = sum(weights)
    eye = torch.eye(3, dtype=normals.dtype, device=normals.device)
    along = torch.where(pixels, half_trace_img, torch.zeros_like(half_trace_img)).clamp_min(1e-12 * lam)
    full_info = info + along[..., None, None] * n_hat.unsqueeze(-1) * n_hat.unsqueeze(-2)  # (H, W, 3, 3)
    system = full_info + degree[..., None, None] * eye
    system = torch.where(pixels[..., None, None], system, eye.expand_as(system))
    rhs_data = (full_info @ n_hat.unsqueeze(-1)).squeeze(-1)
    n = n_hat.clone()
    for _ in range(iterations):
        total = sum(w.unsqueeze(-1) * shift(n, dy, dx) for w, (dy, dx) in zip(weights, _SHIFTS))
        n = torch.linalg.solve(system, (rhs_data + total).unsqueeze(-1)).squeeze(-1)
    n = unit(n)
    return torch.where(pixels.unsqueeze(-1), n, torch.full_like(n, math.nan)), lam


def smooth_normals(inputs: RecoveryInputs, normals: Tensor, k_b: Tensor, params: FMBRDFParams, *,
                   per_pixel_albedo: bool, smoothness: float) -> tuple[Tensor, Tensor]:
    """:func:`map_smoothing` of fitted normals (H, W, 3) for the material ``params``; k_b (H, W) is
    re-solved at the new normals. Pixels whose smoothed normal would face away keep their own."""
    pixels = inputs.mask & torch.isfinite(normals).all(-1)
    obs = flatten_observations(inputs, pixels)
    p = params
    with torch.no_grad():
        tables = build_tables(ior=p.ior, alpha=p.alpha, beta=p.beta, kappa=p.kappa, device=inputs.stokes.device)
        problem = NormalProblem.build(tables, obs.stokes, p.k_s, per_pixel_albedo, p.k_b, inputs.has_polarisation, 1.0)
        n_ml = normals[pixels]
        r, _ = problem.residual(n_ml, obs)
        problem = problem.with_delta(huber_delta(obs, inputs.noise_std, r))
        info = torch.zeros(*pixels.shape, 3, 3, dtype=n_ml.dtype, device=n_ml.device)
        info[pixels] = normal_information(problem, n_ml, obs, residual=r)
        smoothed, lam = map_smoothing(normals, info, pixels, smoothness)
        n = smoothed[pixels]
        facing = (n * obs.view).sum(-1) > 0
        n = torch.where(facing.unsqueeze(-1), n, n_ml)
        _, kb = problem.residual(n, obs)
    out_n = normals.clone()
    out_n[pixels] = n
    out_kb = k_b.clone()
    out_kb[pixels] = kb
    logger.info("smoothness %.3g: λ = %.4g, mean change %.4f°", smoothness, lam,
                float(angular_error_deg(n, n_ml).mean()) if n.numel() else 0.0)
    return out_n, out_kb


def fill_unsupported(normals: Tensor, k_b: Tensor, pixels: Tensor, supported: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Give mask pixels without enough data the normal and albedo of their neighbours.

    A pixel with fewer than :data:`MIN_OBSERVATIONS` usable observations (shadowed or saturated in
    most lights, or every block straddling a texture edge) has no normal of its own: measured on a
    checker-textured sphere, such pixels kept 60–80° errors. They are filled from the outside in:
    each round, an unfilled pixel with known 8-neighbours takes their normalised mean normal and
    mean albedo. Pixels of a component with no supported pixel keep their values (no neighbour has
    a normal to give) and are marked all the same: no unsupported pixel passes for measured.

    Args:
        normals: (H, W, 3), k_b: (H, W) the fit's results.
        pixels: (H, W) bool mask; supported: (H, W) bool pixels with enough observations.

    Returns:
        normals, k_b (copies) and the (H, W) bool mask of filled pixels: every unsupported mask
        pixel (``pixels & ~supported``), filled from its neighbours where any component pixel has data.
    """
    known = pixels & supported
    todo = pixels & ~supported
    n = torch.where(known.unsqueeze(-1), torch.nan_to_num(normals), torch.zeros_like(normals))
    a = torch.where(known, torch.nan_to_num(k_b), torch.zeros_like(k_b))
    filled = torch.zeros_like(pixels)
    while True:
        kf = known.to(n.dtype)
        count = sum(shift(kf, dy, dx) for dy, dx in NEIGHBOURS_8)
        new = todo & ~known & (count > 0)
        if not bool(new.any()):
            break
        sum_n = sum(shift(n * kf.unsqueeze(-1), dy, dx) for dy, dx in NEIGHBOURS_8)
        sum_a = sum(shift(a * kf, dy, dx) for dy, dx in NEIGHBOURS_8)
        n = torch.where(new.unsqueeze(-1), unit(sum_n), n)
        a = torch.where(new, sum_a / count.clamp_min(1.0), a)
        known = known | new
        filled = filled | new
    out_n = torch.where(filled.unsqueeze(-1), n, normals)
    out_a = torch.where(filled, a, k_b)
    unreachable = todo & ~filled
    if bool(unreachable.any()):
        logger.info("fill: %d mask pixels without data in components without data keep the fit's values (marked filled)",
                    int(unreachable.sum()))
    return out_n, out_a, todo
