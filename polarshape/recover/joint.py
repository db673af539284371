"""Joint recovery of per-pixel normals and FMBRDF reflectance from K polarimetric images (spec §9).

Pipeline of :func:`recover_capture` (each stage timed in ``RecoveryResult.timings``):

1. **preprocess** — super-pixel Stokes, dark/saturated observation masks, lights, view directions
   (:mod:`polarshape.recover.preprocess`), cropped to the mask's bounding box.
2. **init** — robust Lambertian photometric stereo on s0 (shadows and highlights trimmed):
   the initial normals (and the whole answer for ``model="lambertian"``).
3. **coarse-to-fine alternation** — on a pyramid (2×2 averaging) whose coarsest level holds at
   most ``4·subsample_pixels`` pixels, alternate
   a. *global parameters* (μ, α, β, [κ]; k_s and per-pixel k_b in closed form) by L-BFGS on a random
      subsample of ``subsample_pixels`` pixels (:func:`polarshape.recover.reflectometry.fit_reflectance`);
   b. *normals*: per-pixel Levenberg–Marquardt, 2 DoF (tangent-plane step, renormalised), Jacobian by
      forward differences of the full model (k_b re-solved in closed form inside the residual:
      variable projection), Huber loss by iteratively reweighted least squares, per-pixel damping
      and acceptance; pixels whose step stayed below 1e-4 rad for two iterations are frozen
      (active set), so later iterations only touch the pixels that still move. Then each pixel
      tries its 8 neighbours' normals and keeps one that fits its own data better, and the pixels
      that switched are polished (:func:`_propagate`): a per-pixel local minimum (measured: a
      patch 20–25° off under a highlight on a dark checker cell) is left through its neighbours.
   The alternation stops when the loss improved by less than 1e-4 (relative) summed over the last
   two outer iterations (a window, not one step) or after ``max_outer_iterations``.
   Finer levels start from the upsampled normals and run step b only.
4. **κ** — with ``fit_kappa=None`` κ is fitted once at the end of the coarse level; if it lowers the
   loss by < 1 % it is reset to 0 (the separable fast path) and the skip recorded.
5. **fill** — mask pixels with fewer than 3 usable observations (shadowed or saturated in most
   lights, blocks straddling a texture edge) have no normal of their own: they take their
   neighbours' (:func:`_fill_unsupported`; ``RecoveryResult.filled`` marks them).

Robust loss: Huber on channel-weighted Stokes residuals (see :mod:`polarshape.recover.reflectometry`),
δ = 3 × the robust (MAD) residual σ of the initial fit, floored at 4 quantisation steps.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm.auto import tqdm

from polarshape.brdf.fmbrdf import FMBRDFTables, build_tables
from polarshape.io.capture import Capture
from polarshape.recover.photometric import robust_lambertian_ps
from polarshape.recover.preprocess import RecoveryInputs, crop_inputs, preprocess_capture
from polarshape.recover.reflectometry import (
    ALPHA_GRID,
    GlobalParams,
    Observations,
    _channel_weights,
    fit_reflectance,
    objective,
    huber,
    render_parts,
    solve_albedos,
)

logger = logging.getLogger(__name__)

__all__ = ["RecoveryConfig", "RecoveryResult", "recover_capture", "recover_inputs", "angular_error_deg"]

_MODELS = ("fmbrdf", "lambertian", "auto")


@dataclass
class RecoveryConfig:
    """Options of :func:`recover_capture` (see the module docstring for the stages)."""

    model: str = "fmbrdf"  # "fmbrdf" | "lambertian" (intensity-only PS baseline) | "auto" (pick the simplest that explains the data)
    per_pixel_albedo: bool = True
    fit_kappa: bool | None = None  # None = decide from the data (skip κ when it adds nothing)
    max_outer_iterations: int = 20
    subsample_pixels: int = 4096  # pixels used for the global parameters
    coarse_to_fine: bool = True
    propagate: bool = True  # pixels try their neighbours' normals (escapes per-pixel local minima), see _propagate
    smoothness: float = 0.0  # weight of the normal-smoothness prior (0: per-pixel maximum likelihood), see _map_smoothing
    demosaic: str = "bilinear"  # "bilinear" | "superpixel" (see polarshape.recover.preprocess)
    sample_at: str = "centre"  # where in each 2×2 block: "centre" | "top_left" | "top_right" | ...
    device: str = "cpu"
    dtype: torch.dtype = torch.float32
    seed: int = 0
    progress: bool = False  # tqdm bars


@dataclass
class RecoveryResult:
    """Output of :func:`recover_capture`; (H, W) is the capture's super-pixel grid."""

    normals: Tensor  # (H, W, 3) camera frame, NaN outside mask
    albedo: Tensor | None  # (H, W) body albedo k_b (NaN outside mask) or None
    params: dict[str, float]  # ior, k_s, k_b (global/mean), alpha, beta, kappa, r_k ...
    model: str
    mask: Tensor  # (H, W) bool
    rendered: Tensor | None  # (K, 3, H, W) Stokes rendered with the result (for the report)
    observed: Tensor  # (K, 3, H, W) observed Stokes
    history: list[dict] = field(default_factory=list)  # per outer iteration: loss, seconds, stage
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage
    skipped: list[str] = field(default_factory=list)  # what was skipped and why (human-readable)
    filled: Tensor | None = None  # (H, W) bool: mask pixels with < 3 usable observations, normal filled from neighbours


def angular_error_deg(a: Tensor, b: Tensor) -> Tensor:
    """Angle between unit vectors (..., 3) in degrees, via atan2(|a×b|, a·b)."""
    a, b = a.to(torch.float64), b.to(torch.float64)
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1)))


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _check_config(config: RecoveryConfig) -> None:
    if config.model not in _MODELS:
        raise ValueError(f"RecoveryConfig.model must be one of {_MODELS}; got {config.model!r}")
    if config.max_outer_iterations < 1:
        raise ValueError(f"RecoveryConfig.max_outer_iterations must be ≥ 1; got {config.max_outer_iterations}")
    if config.subsample_pixels < 16:
        raise ValueError(f"RecoveryConfig.subsample_pixels must be ≥ 16; got {config.subsample_pixels}")
    if not (config.smoothness >= 0 and math.isfinite(config.smoothness)):
        raise ValueError(f"RecoveryConfig.smoothness must be a finite number ≥ 0; got {config.smoothness}")
    if not config.dtype.is_floating_point:
        raise ValueError(f"RecoveryConfig.dtype must be a floating-point torch dtype; got {config.dtype}")


def _flatten(inputs: RecoveryInputs, pixels: Tensor) -> Observations:
    """Observations of the pixels where ``pixels`` (H, W) is True, row-major."""
    stokes = inputs.stokes.permute(2, 3, 0, 1)[pixels]  # (P, K, 3)
    weight = inputs.valid.permute(1, 2, 0)[pixels].to(stokes.dtype)  # (P, K)
    lights = inputs.lights if inputs.lights.ndim == 2 else inputs.lights.permute(1, 2, 0, 3)[pixels]
    irr = inputs.irradiance if inputs.irradiance.ndim == 1 else inputs.irradiance.permute(1, 2, 0)[pixels]
    return Observations(stokes, weight, lights, irr, inputs.view[pixels])


def _downsample(inputs: RecoveryInputs) -> RecoveryInputs:
    """Half resolution: 2×2 means of Stokes over valid observations; a pixel is in the mask when all
    four are; an observation is valid when all four are."""
    h, w = inputs.shape
    h2, w2 = h // 2, w // 2
    st = inputs.stokes[..., : 2 * h2, : 2 * w2]
    va = inputs.valid[:, : 2 * h2, : 2 * w2]
    m = inputs.mask[: 2 * h2, : 2 * w2]
    valid = F.avg_pool2d(va.to(st.dtype).unsqueeze(1), 2).squeeze(1) > 0.999  # (K, h2, w2)
    mask = F.avg_pool2d(m.to(st.dtype)[None, None], 2)[0, 0] > 0.999
    stokes = F.avg_pool2d(st, 2)
    sat = F.max_pool2d(inputs.saturated[:, : 2 * h2, : 2 * w2].to(st.dtype).unsqueeze(1), 2).squeeze(1) > 0
    view = F.avg_pool2d(inputs.view[: 2 * h2, : 2 * w2].permute(2, 0, 1).unsqueeze(0), 2)[0].permute(1, 2, 0)
    view = view / view.norm(dim=-1, keepdim=True)
    lights, irr = inputs.lights, inputs.irradiance
    if lights.ndim == 4:
        lights = F.avg_pool2d(lights[:, : 2 * h2, : 2 * w2].permute(0, 3, 1, 2), 2).permute(0, 2, 3, 1)
        lights = lights / lights.norm(dim=-1, keepdim=True)
    if irr.ndim == 3:
        irr = F.avg_pool2d(irr[:, : 2 * h2, : 2 * w2].unsqueeze(1), 2).squeeze(1)
    return RecoveryInputs(stokes, valid & mask, sat, mask, lights, irr, view, inputs.noise_std / 2,
                          inputs.has_polarisation, inputs.offset)


def _tangent_basis(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors (P, 3) orthogonal to n (P, 3) and to each other."""
    ref = torch.zeros_like(n)
    use_x = n[:, 0].abs() < 0.9
    ref[:, 0] = use_x.to(n.dtype)
    ref[:, 1] = (~use_x).to(n.dtype)
    t1 = torch.linalg.cross(n, ref)
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(n, t1)
    return t1, t2


class _NormalProblem:
    """Per-pixel residuals r(N) (P, K, 3) with k_b solved in closed form (variable projection)."""

    def __init__(self, tables: FMBRDFTables, obs: Observations, k_s: float, per_pixel: bool, k_b_global: float,
                 polarised: bool, delta: float) -> None:
        self.tables, self.obs, self.per_pixel, self.delta = tables, obs, per_pixel, delta
        self.k_s = torch.tensor(k_s, dtype=obs.stokes.dtype, device=obs.stokes.device)
        self.k_b_global = k_b_global
        self.cw = _channel_weights(obs.stokes, polarised).sqrt()  # (3,)
        self.polarised = polarised

    def residual(self, normals: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
        """Weighted residual (P, K, 3) and k_b (P,) for normals (P, 3) of the pixels in ``obs``."""
        surf, body = render_parts(self.tables, normals, obs)
        if self.per_pixel:
            _, k_b = solve_albedos(surf, body, obs, per_pixel=True, polarised=self.polarised, k_s=self.k_s)
        else:
            k_b = torch.full((normals.shape[0],), self.k_b_global, dtype=surf.dtype, device=surf.device)
        r = (obs.stokes - self.k_s * surf - k_b[:, None, None] * body) * self.cw
        return r * obs.weight.sqrt().unsqueeze(-1), k_b

    def loss(self, r: Tensor) -> Tensor:
        """Per-pixel Huber loss (P,)."""
        return huber(r, self.delta).sum((1, 2))


def _refine_normals(
    problem: _NormalProblem, normals: Tensor, obs: Observations, *, max_iter: int, step_h: float = 2e-3,
    max_step: float = 0.25,
) -> tuple[Tensor, Tensor, Tensor, int]:
    """Per-pixel Levenberg–Marquardt on the normals (P, 3); returns normals, k_b, per-pixel loss, iterations."""
    p = normals.shape[0]
    dt, dev = normals.dtype, normals.device
    with torch.no_grad():
        r, k_b = problem.residual(normals, obs)
        loss = problem.loss(r)
        lam = torch.full((p,), 1e-3, dtype=dt, device=dev)
        small = torch.zeros(p, dtype=torch.int64, device=dev)
        active = torch.ones(p, dtype=torch.bool, device=dev)
        it = 0
        for it in range(1, max_iter + 1):
            idx = torch.nonzero(active).flatten()
            if idx.numel() == 0:
                break
            sub = obs.select(idx)
            n = normals[idx]
            r0 = r[idx].reshape(idx.numel(), -1)  # (A, M)
            t1, t2 = _tangent_basis(n)
            r1, _ = problem.residual(_unit(n + step_h * t1), sub)
            r2, _ = problem.residual(_unit(n + step_h * t2), sub)
            jac = torch.stack([(r1.reshape(r0.shape) - r0) / step_h, (r2.reshape(r0.shape) - r0) / step_h], -1)  # (A, M, 2)
            a = r0.abs()
            irls = torch.where(a <= problem.delta, torch.ones_like(a), problem.delta / a.clamp_min(1e-30))  # Huber IRLS
            jw = jac * irls.unsqueeze(-1)
            h = jw.transpose(1, 2) @ jac  # (A, 2, 2)
            g = (jw * r0.unsqueeze(-1)).sum(1)  # (A, 2)
            diag = torch.diagonal(h, dim1=1, dim2=2)
            damp = h + torch.diag_embed(lam[idx, None] * (diag + 1e-12))
            det = damp[:, 0, 0] * damp[:, 1, 1] - damp[:, 0, 1] * damp[:, 1, 0]
            ok = det.abs() > 1e-30
            safe = torch.where(ok, det, torch.ones_like(det))
            d0 = -(damp[:, 1, 1] * g[:, 0] - damp[:, 0, 1] * g[:, 1]) / safe
            d1 = -(-damp[:, 1, 0] * g[:, 0] + damp[:, 0, 0] * g[:, 1]) / safe
            step = torch.stack([d0, d1], -1)
            step = torch.where(ok[:, None], step, torch.zeros_like(step))
            norm = step.norm(dim=-1)
            step = step * (max_step / norm.clamp_min(max_step)).unsqueeze(-1)
            trial = _unit(n + step[:, :1] * t1 + step[:, 1:] * t2)
            facing = (trial * sub.view).sum(-1) > 0
            rt, kbt = problem.residual(trial, sub)
            lt = problem.loss(rt)
            accept = facing & (lt < loss[idx]) & torch.isfinite(lt)
            ai = idx[accept]
            normals[ai] = trial[accept]
            r[ai] = rt[accept]
            k_b[ai] = kbt[accept]
            rel = (loss[idx] - lt) / loss[idx].clamp_min(1e-30)
            loss[ai] = lt[accept]
            lam[idx] = torch.where(accept, (lam[idx] / 3).clamp_min(1e-7), (lam[idx] * 4).clamp_max(1e7))
            tiny_step = (step.norm(dim=-1) < 1e-4) | (accept & (rel < 1e-7)) | (~accept & (lam[idx] > 1e6))
            small[idx] = torch.where(tiny_step, small[idx] + 1, torch.zeros_like(small[idx]))
            active = small < 2
    return normals, k_b, loss, it


#: Pixels per chunk of the per-pixel solve: the residual and its intermediates ((P, K) tensors,
#: a few dozen of them) then stay a few MB each instead of hundreds at 1024² super-pixels.
_CHUNK_PIXELS = 32768


def _refine_normals_chunked(
    problem: _NormalProblem, normals: Tensor, obs: Observations, *, max_iter: int
) -> tuple[Tensor, Tensor, Tensor, int]:
    """:func:`_refine_normals` over chunks of pixels (the pixels are independent): same result, less memory traffic."""
    p = normals.shape[0]
    if p <= _CHUNK_PIXELS:
        return _refine_normals(problem, normals, obs, max_iter=max_iter)
    parts = []
    for start in range(0, p, _CHUNK_PIXELS):
        idx = torch.arange(start, min(start + _CHUNK_PIXELS, p), device=normals.device)
        parts.append(_refine_normals(problem, normals[idx].clone(), obs.select(idx), max_iter=max_iter))
    return (torch.cat([q[0] for q in parts]), torch.cat([q[1] for q in parts]), torch.cat([q[2] for q in parts]),
            max(q[3] for q in parts))


#: (dy, dx) offsets of the 8-neighbourhood.
_NEIGHBOURS_8 = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))


def _neighbour_index(pixels: Tensor) -> Tensor:
    """(P, 8) flat indices (row-major over ``pixels`` (H, W) True) of each pixel's 8 neighbours
    inside ``pixels``; −1 where a neighbour is outside."""
    h, w = pixels.shape
    flat = torch.full((h, w), -1, dtype=torch.int64, device=pixels.device)
    flat[pixels] = torch.arange(int(pixels.sum()), device=pixels.device)
    padded = F.pad(flat, (1, 1, 1, 1), value=-1)
    cols = [padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w][pixels] for dy, dx in _NEIGHBOURS_8]
    return torch.stack(cols, -1)


_COS_5DEG = math.cos(math.radians(5.0))


def _propagate(
    problem: _NormalProblem, normals: Tensor, k_b: Tensor, loss: Tensor, obs: Observations, neighbours: Tensor,
    *, passes: int = 3, max_iter: int = 6,
) -> tuple[Tensor, Tensor, Tensor, int]:
    """Escape per-pixel local minima: each pixel tries its neighbours' normals (PatchMatch-style
    propagation) and takes one that fits its own data better, then Levenberg–Marquardt polishes the
    pixels that switched. A smooth surface hands its neighbours a start inside the right basin
    where the initial (Lambertian) normal was outside it (e.g. under a highlight on a dark albedo).

    Args:
        problem: the per-pixel problem (fixed material).
        normals, k_b, loss: (P, 3), (P,), (P,) current per-pixel solution and its loss (updated in place).
        obs: observations of the P pixels.
        neighbours: (P, 8) from :func:`_neighbour_index`.
        passes: propagation rounds (each reaches at least one pixel further). Only neighbours whose
            normal differs from the pixel's by > 5° are tried (closer ones are in the same basin).

    Returns:
        normals, k_b, loss, and the number of pixels that switched.
    """
    switched_total = 0
    with torch.no_grad():
        for _ in range(passes):
            switched = torch.zeros(normals.shape[0], dtype=torch.bool, device=normals.device)
            for j in range(neighbours.shape[1]):
                nb = neighbours[:, j]
                # only neighbours that differ (> 5°) from the pixel's own normal are worth a try
                differs = (normals * normals[nb.clamp_min(0)]).sum(-1) < _COS_5DEG
                cand_idx = torch.nonzero((nb >= 0) & differs).flatten()
                if cand_idx.numel() == 0:
                    continue
                for start in range(0, cand_idx.numel(), _CHUNK_PIXELS):
                    idx = cand_idx[start:start + _CHUNK_PIXELS]
                    sub = obs.select(idx)
                    cand = normals[nb[idx]]
                    facing = (cand * sub.view).sum(-1) > 0
                    r, kb = problem.residual(cand, sub)
                    lc = problem.loss(r)
                    better = facing & torch.isfinite(lc) & (lc < loss[idx])
                    bi = idx[better]
                    normals[bi] = cand[better]
                    k_b[bi] = kb[better]
                    loss[bi] = lc[better]
                    switched[bi] = True
            moved = torch.nonzero(switched).flatten()
            if moved.numel() == 0:
                break
            switched_total += int(moved.numel())
            n_m, kb_m, l_m, _ = _refine_normals(problem, normals[moved].clone(), obs.select(moved), max_iter=max_iter)
            normals[moved], k_b[moved], loss[moved] = n_m, kb_m, l_m
    return normals, k_b, loss, switched_total


def _unit(x: Tensor) -> Tensor:
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _subsample(p: int, n: int, seed: int, device: torch.device) -> Tensor:
    if p <= n:
        return torch.arange(p, device=device)
    gen = torch.Generator().manual_seed(seed)
    return torch.randperm(p, generator=gen)[:n].sort().values.to(device)


def _huber_delta(obs: Observations, noise_std: float, residual: Tensor | None = None) -> float:
    floor = 4.0 * noise_std
    if residual is None:
        return max(floor, 0.01)
    v = residual[obs.weight > 0].abs().flatten()
    if v.numel() == 0:
        return floor
    sigma = float(v.median()) * 1.4826
    return max(3.0 * sigma, floor)


def _information(problem: _NormalProblem, normals: Tensor, obs: Observations, step_h: float = 2e-3,
                 residual: Tensor | None = None) -> Tensor:
    """Gauss–Newton information (P, 3, 3) of each pixel's normal (P, 3) in the camera frame.

    JᵀWJ of the (Huber-reweighted) residuals in the tangent plane (forward differences, as in
    :func:`_refine_normals`), mapped to 3-D: T (JᵀWJ) Tᵀ with T = [t1 t2] (P, 3, 2). Rank 2: the data
    say nothing along N itself. ``residual``: ``problem.residual(normals, obs)[0]`` when the caller has it.
    """
    with torch.no_grad():
        r0 = problem.residual(normals, obs)[0] if residual is None else residual
        r0 = r0.reshape(normals.shape[0], -1)  # (P, M)
        t1, t2 = _tangent_basis(normals)
        cols = [(problem.residual(_unit(normals + step_h * t), obs)[0].reshape(r0.shape) - r0) / step_h for t in (t1, t2)]
        jac = torch.stack(cols, -1)  # (P, M, 2)
        a = r0.abs()
        irls = torch.where(a <= problem.delta, torch.ones_like(a), problem.delta / a.clamp_min(1e-30))
        h = (jac * irls.unsqueeze(-1)).transpose(1, 2) @ jac  # (P, 2, 2)
        basis = torch.stack([t1, t2], -1)  # (P, 3, 2)
        return basis @ h @ basis.transpose(1, 2)


_SHIFTS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def _shift(x: Tensor, dy: int, dx: int) -> Tensor:
    """x[i + dy, j + dx] at (i, j) (zeros past the border); x is (H, W, ...)."""
    out = torch.zeros_like(x)
    h, w = x.shape[:2]
    out[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)] = x[max(dy, 0):h - max(-dy, 0), max(dx, 0):w - max(-dx, 0)]
    return out


def _map_smoothing(
    normals: Tensor, info: Tensor, pixels: Tensor, smoothness: float, iterations: int = 60
) -> tuple[Tensor, float]:
    """Maximum a posteriori normals under a first-order smoothness prior, from the per-pixel fit.

    Near each pixel's maximum-likelihood normal n̂_p the data term is ≈ (n − n̂_p)ᵀ I_p (n − n̂_p)
    with I_p the Gauss–Newton information (:func:`_information`). Adding the prior
    λ Σ_{p~q} |n_p − n_q|² over 4-neighbours inside the mask gives the sparse linear system
    (I_p + λ d_p) n_p − λ Σ_q n_q = I_p n̂_p, solved by Jacobi iterations (I_p is completed along
    n̂_p with its mean eigenvalue, so that the blocks are diagonally dominant), then renormalised.
    λ = ``smoothness`` × the median of ½ trace I_p: at smoothness 1 a neighbour weighs as much as a
    typical pixel's own data. Pixels with strong data (large I_p) keep their estimate; noisy ones
    borrow from their neighbours. A quadratic prior also smooths across creases and depth edges
    inside the mask: keep ``smoothness`` 0 (per-pixel maximum likelihood) where they matter.

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
    inside = pixels.to(normals.dtype)
    # robust edge weights: where the estimates bend faster than their noise explains (a limb, a
    # crease), the local Laplacian of n̂ exceeds 3σ_p (σ_p² = 1 / (½ trace I_p)) and the prior lets go
    nb_sum = sum(_shift(n_hat, dy, dx) for dy, dx in _SHIFTS)
    nb_cnt = sum(_shift(inside, dy, dx) for dy, dx in _SHIFTS) * inside
    laplacian = (n_hat - nb_sum / nb_cnt.clamp_min(1).unsqueeze(-1)).norm(dim=-1)  # (H, W)
    sigma = half_trace_img.clamp_min(1e-12).rsqrt()
    g = torch.where(pixels & (nb_cnt == 4), 1.0 / (1.0 + (laplacian / (3 * sigma)) ** 2), torch.zeros_like(sigma))
    weights = [lam * torch.minimum(g, _shift(g, dy, dx)) for dy, dx in _SHIFTS]  # (H, W) each, 0 off the mask
    degree = sum(weights)
    eye = torch.eye(3, dtype=normals.dtype, device=normals.device)
    along = torch.where(pixels, half_trace_img, torch.zeros_like(half_trace_img)).clamp_min(1e-12 * lam)
    full_info = info + along[..., None, None] * n_hat.unsqueeze(-1) * n_hat.unsqueeze(-2)  # (H, W, 3, 3)
    system = full_info + degree[..., None, None] * eye
    system = torch.where(pixels[..., None, None], system, eye.expand_as(system))
    rhs_data = (full_info @ n_hat.unsqueeze(-1)).squeeze(-1)
    n = n_hat.clone()
    for _ in range(iterations):
        total = sum(w.unsqueeze(-1) * _shift(n, dy, dx) for w, (dy, dx) in zip(weights, _SHIFTS))
        n = torch.linalg.solve(system, (rhs_data + total).unsqueeze(-1)).squeeze(-1)
    n = _unit(n)
    return torch.where(pixels.unsqueeze(-1), n, torch.full_like(n, math.nan)), lam


# --------------------------------------------------------------------------------------------
# Stages
# --------------------------------------------------------------------------------------------


def _lambertian(inputs: RecoveryInputs, pixels: Tensor) -> tuple[Tensor, Tensor]:
    """Robust Lambertian PS on s0: normals (H, W, 3), albedo (H, W) (pixels outside: N = V, 0)."""
    s0 = inputs.stokes[:, 0]  # (K, H, W)
    k = s0.shape[0]
    if k < 3:
        raise ValueError(
            f"capture: {k} light(s); recovery needs at least 3 non-coplanar lights for the initial normals"
        )
    obs_mask = inputs.valid & pixels.unsqueeze(0)
    # lights (K, 3) or (K, H, W, 3) and irradiance (K,) or (K, H, W) are the shapes robust PS takes;
    # pixels are independent: solve bands of rows (less memory traffic on large images)
    h, w = pixels.shape
    rows = max(1, _CHUNK_PIXELS // max(w, 1))
    normals, albedo = [], []
    for r0 in range(0, h, rows):
        band = slice(r0, min(r0 + rows, h))
        lights = inputs.lights if inputs.lights.ndim == 2 else inputs.lights[:, band]
        irr = inputs.irradiance if inputs.irradiance.ndim == 1 else inputs.irradiance[:, band]
        res = robust_lambertian_ps(
            s0[:, band], lights, irr, obs_mask[:, band], view_dirs=inputs.view[band], saturation=None,
            noise_std=inputs.noise_std,
        )
        normals.append(res.normals)
        albedo.append(res.albedo)
    return torch.cat(normals), torch.cat(albedo)


#: Usable observations a pixel needs for its own normal (2 DoF + its albedo; photometric stereo's 3).
_MIN_OBSERVATIONS = 3


def _fill_unsupported(normals: Tensor, k_b: Tensor, pixels: Tensor, supported: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Give mask pixels without enough data the normal and albedo of their neighbours.

    A pixel with fewer than :data:`_MIN_OBSERVATIONS` usable observations (shadowed or saturated in
    most lights, or every block straddling a texture edge) has no normal of its own: measured on a
    checker-textured sphere, such pixels kept 60–80° errors. They are filled from the outside in:
    each round, an unfilled pixel with known 8-neighbours takes their normalised mean normal and
    mean albedo. Pixels of a component with no supported pixel keep their values.

    Args:
        normals: (H, W, 3), k_b: (H, W) the fit's results.
        pixels: (H, W) bool mask; supported: (H, W) bool pixels with enough observations.

    Returns:
        normals, k_b (copies) and the (H, W) bool mask of filled pixels.
    """
    known = pixels & supported
    todo = pixels & ~supported
    n = torch.where(known.unsqueeze(-1), torch.nan_to_num(normals), torch.zeros_like(normals))
    a = torch.where(known, torch.nan_to_num(k_b), torch.zeros_like(k_b))
    filled = torch.zeros_like(pixels)
    while True:
        kf = known.to(n.dtype)
        count = sum(_shift(kf, dy, dx) for dy, dx in _NEIGHBOURS_8)
        new = todo & ~known & (count > 0)
        if not bool(new.any()):
            break
        sum_n = sum(_shift(n * kf.unsqueeze(-1), dy, dx) for dy, dx in _NEIGHBOURS_8)
        sum_a = sum(_shift(a * kf, dy, dx) for dy, dx in _NEIGHBOURS_8)
        n = torch.where(new.unsqueeze(-1), _unit(sum_n), n)
        a = torch.where(new, sum_a / count.clamp_min(1.0), a)
        known = known | new
        filled = filled | new
    out_n = torch.where(filled.unsqueeze(-1), n, normals)
    out_a = torch.where(filled, a, k_b)
    return out_n, out_a, filled


@dataclass
class _State:
    params: GlobalParams
    normals: Tensor  # (H, W, 3) at the current level
    k_b: Tensor  # (H, W)


def _profile_alpha(normals: Tensor, obs: Observations, params: GlobalParams, per_pixel: bool, delta: float) -> GlobalParams:
    """Starting α for intensity-only data: each grid α scored after a few normal iterations.

    Without polarisation nothing but the lobe ties the normals to the material, and the initial
    (Lambertian) normals lean toward the highlights: scored at those normals a broad lobe wins, the
    fit then drops the specular term (k_s → 0) and never recovers it (measured on a 56² sphere,
    α 0.3, no polariser: α 0.97, β 6, k_s 0, 3.2° mean error). Scoring each α after the normals
    of the subsample have moved to it (4 LM iterations) ranks the lobes as the data do.

    Args:
        normals: (P, 3) subsample normals; obs: its observations (intensity only).
        params: current parameters (all but α kept).
        per_pixel: per-pixel body albedo.
        delta: Huber threshold.

    Returns:
        ``params`` with the best α of :data:`polarshape.recover.reflectometry.ALPHA_GRID`.
    """
    best = (math.inf, params.alpha)
    for a in ALPHA_GRID:
        tables = build_tables(ior=params.ior, alpha=a, beta=params.beta, kappa=params.kappa, device=normals.device,
                              n_grid=33)
        surf, body = render_parts(tables, normals, obs)
        k_s, k_b = solve_albedos(surf, body, obs, per_pixel=per_pixel, polarised=False)
        problem = _NormalProblem(tables, obs, float(k_s), per_pixel, float(k_b.median()), False, delta)
        _, _, loss, _ = _refine_normals(problem, normals.clone(), obs, max_iter=4)
        total = float(loss.sum())
        if total < best[0]:
            best = (total, a)
    logger.info("intensity-only: α %.3g from the profiled grid", best[1])
    return GlobalParams(**{**vars(params), "alpha": best[1]})


def _fit_level(
    inputs: RecoveryInputs, normals: Tensor, params: GlobalParams, config: RecoveryConfig, *, fit_globals: bool,
    fit_kappa: bool | None, history: list[dict], timings: dict[str, float], skipped: list[str], level: int,
    t_start: float,
) -> _State:
    """Alternate global parameters and normals on one pyramid level."""
    pixels = inputs.mask
    obs = _flatten(inputs, pixels)
    n = normals[pixels].clone()  # (P, 3)
    p_count = n.shape[0]
    polarised = inputs.has_polarisation
    delta = _huber_delta(obs, inputs.noise_std)
    sub_idx = _subsample(p_count, config.subsample_pixels, config.seed + level, n.device)
    neighbours = _neighbour_index(pixels) if config.propagate else None
    window: list[float] = []
    k_b = torch.zeros(p_count, dtype=n.dtype, device=n.device)
    outer = config.max_outer_iterations if fit_globals else 1
    kappa_decided = fit_kappa is not None
    for it in tqdm(range(outer), desc=f"level {level}", unit="iteration", disable=not config.progress):
        if fit_globals:
            t0 = time.perf_counter()
            grid = it == 0 and level_is_first(history)
            if grid and not polarised:
                params = _profile_alpha(n[sub_idx], obs.select(sub_idx), params, config.per_pixel_albedo, delta)
                grid = False
            fit = fit_reflectance(
                n[sub_idx], obs.select(sub_idx), init=params, per_pixel_albedo=config.per_pixel_albedo,
                fit_kappa=bool(fit_kappa), polarised=polarised, delta=delta, grid_search=grid,
                max_iter=12 if it == 0 else 4 if it == 1 else 2,
                # the initial (Lambertian) normals are biased by highlights: fit the lobe width first,
                # free μ and β once the normals have moved to the model
                fit_names=("alpha",) if it == 0 else ("alpha", "beta") if it == 1 else None,
            )
            params = fit.params
            timings["global_params"] = timings.get("global_params", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        tables = build_tables(ior=params.ior, alpha=params.alpha, beta=params.beta, kappa=params.kappa, device=n.device)
        problem = _NormalProblem(tables, obs, params.k_s, config.per_pixel_albedo, params.k_b, polarised, delta)
        n, k_b, loss_pp, n_iter = _refine_normals_chunked(problem, n, obs, max_iter=6 if fit_globals else 10)
        if config.propagate:
            n, k_b, loss_pp, moved = _propagate(problem, n, k_b, loss_pp, obs, neighbours)
            if moved:
                logger.info("level %d outer %d: %d pixels took a neighbour's normal", level, it, moved)
        timings["normals"] = timings.get("normals", 0.0) + time.perf_counter() - t0
        loss = float(loss_pp.sum() / obs.weight.sum().clamp_min(1.0))
        if it == 0 and fit_globals:
            with torch.no_grad():
                r, _ = problem.residual(n, obs)
            new_delta = _huber_delta(obs, inputs.noise_std, r)
            if abs(new_delta - delta) > 0.25 * delta:
                delta = new_delta
                loss_pp = problem_loss_with(problem, n, obs, delta)
                loss = float(loss_pp.sum() / obs.weight.sum().clamp_min(1.0))
        history.append({"stage": f"level{level}", "iteration": it, "loss": loss, "lm_iterations": n_iter,
                        "seconds": time.perf_counter() - t_start, **params.as_dict()})
        logger.info("level %d outer %d: loss %.6g, %s", level, it, loss, params.as_dict())
        window.append(loss)
        # converged: the loss changed by ≤ 0.1 % over the last two outer iterations (a window)
        if len(window) >= 3 and abs(window[-3] - window[-1]) <= 1e-3 * abs(window[-3]):
            if not kappa_decided and fit_globals:
                kappa_decided = True
                t0 = time.perf_counter()
                # cheap probe first (coarse tables): does any κ lower the loss by ≥ 1 %? It holds
                # μ, α, β at their κ = 0 values, so a weak correlation can go unseen (measured: κ = 40
                # data not detected; fit_kappa: true recovers it)
                sub_n, sub_obs = n[sub_idx], obs.select(sub_idx)
                base_loss = objective(params, sub_n, sub_obs, per_pixel_albedo=config.per_pixel_albedo,
                                      polarised=polarised, delta=delta, n_grid=33)
                probes = {kap: objective(GlobalParams(**{**vars(params), "kappa": kap}), sub_n, sub_obs,
                                         per_pixel_albedo=config.per_pixel_albedo, polarised=polarised, delta=delta,
                                         n_grid=33)
                          for kap in (5.0, 20.0, 60.0)}
                best_kappa = min(probes, key=lambda kap: probes[kap])
                trial_loss = probes[best_kappa]
                if (base_loss - trial_loss) >= 0.01 * base_loss:
                    trial = fit_reflectance(sub_n, sub_obs, init=GlobalParams(**{**vars(params), "kappa": best_kappa}),
                                            per_pixel_albedo=config.per_pixel_albedo, fit_kappa=True,
                                            polarised=polarised, delta=delta, grid_search=False, max_iter=6)
                    trial_loss = trial.loss
                    # compare like with like: the fit's loss uses full-resolution tables
                    base_loss = objective(params, sub_n, sub_obs, per_pixel_albedo=config.per_pixel_albedo,
                                          polarised=polarised, delta=delta)
                gain = (base_loss - trial_loss) / max(base_loss, 1e-30)
                timings["kappa_test"] = time.perf_counter() - t0
                if gain < 0.01:
                    skipped.append(f"kappa: κ > 0 changed the loss by {-100 * gain:+.2f}% (needs ≤ -1%): κ = 0, separable fast path "
                                   "(fit_kappa: true forces κ)")
                else:
                    params = trial.params
                    fit_kappa = True
                    window.clear()
                    continue
            break
    else:
        if fit_globals:
            logger.info("level %d: reached max_outer_iterations=%d", level, outer)
    if not kappa_decided and fit_globals and not fit_kappa:
        skipped.append("kappa: not tested (alternation did not converge within max_outer_iterations): κ kept at 0")
    normals_img = torch.full_like(normals, math.nan)
    normals_img[pixels] = n
    kb_img = torch.full(pixels.shape, math.nan, dtype=n.dtype, device=n.device)
    kb_img[pixels] = k_b
    return _State(params, normals_img, kb_img)


def _smooth_state(inputs: RecoveryInputs, state: _State, config: RecoveryConfig) -> _State:
    """Apply :func:`_map_smoothing` to the finest level's normals; re-solve k_b at the new normals."""
    pixels = inputs.mask & torch.isfinite(state.normals).all(-1)
    obs = _flatten(inputs, pixels)
    p = state.params
    with torch.no_grad():
        tables = build_tables(ior=p.ior, alpha=p.alpha, beta=p.beta, kappa=p.kappa, device=inputs.stokes.device)
        problem = _NormalProblem(tables, obs, p.k_s, config.per_pixel_albedo, p.k_b, inputs.has_polarisation, 1.0)
        n_ml = state.normals[pixels]
        r, _ = problem.residual(n_ml, obs)
        problem.delta = _huber_delta(obs, inputs.noise_std, r)
        info = torch.zeros(*pixels.shape, 3, 3, dtype=n_ml.dtype, device=n_ml.device)
        info[pixels] = _information(problem, n_ml, obs, residual=r)
        smoothed, lam = _map_smoothing(state.normals, info, pixels, config.smoothness)
        n = smoothed[pixels]
        facing = (n * obs.view).sum(-1) > 0
        n = torch.where(facing.unsqueeze(-1), n, n_ml)
        _, k_b = problem.residual(n, obs)
    normals = state.normals.clone()
    normals[pixels] = n
    kb_img = state.k_b.clone()
    kb_img[pixels] = k_b
    logger.info("smoothness %.3g: λ = %.4g, mean change %.4f°", config.smoothness, lam,
                float(angular_error_deg(n, n_ml).mean()) if n.numel() else 0.0)
    return _State(p, normals, kb_img)


def problem_loss_with(problem: "_NormalProblem", normals: Tensor, obs: Observations, delta: float) -> Tensor:
    """Per-pixel loss (P,) of ``normals`` with a new Huber threshold (also stored in ``problem``)."""
    problem.delta = delta
    with torch.no_grad():
        r, _ = problem.residual(normals, obs)
    return problem.loss(r)


def level_is_first(history: list[dict]) -> bool:
    """True before any alternation was recorded (the grid search runs once per recovery)."""
    return not any(h.get("stage", "").startswith("level") for h in history)


def _render(inputs: RecoveryInputs, state: _State) -> Tensor:
    """(K, 3, H, W) Stokes rendered with the recovered normals, parameters and albedo (0 outside)."""
    pixels = inputs.mask
    obs = _flatten(inputs, pixels)
    p = state.params
    with torch.no_grad():
        tables = build_tables(ior=p.ior, alpha=p.alpha, beta=p.beta, kappa=p.kappa, device=inputs.stokes.device)
        surf, body = render_parts(tables, state.normals[pixels], obs)
        s = p.k_s * surf + state.k_b[pixels][:, None, None] * body  # (P, K, 3)
    out = torch.zeros(inputs.stokes.shape[-2], inputs.stokes.shape[-1], *s.shape[1:], dtype=s.dtype, device=s.device)
    out[pixels] = s
    return out.permute(2, 3, 0, 1)


def recover_inputs(inputs: RecoveryInputs, config: RecoveryConfig = RecoveryConfig()) -> RecoveryResult:
    """Recovery on preprocessed inputs (same grid as ``inputs``); see :func:`recover_capture`."""
    _check_config(config)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    history: list[dict] = []
    skipped: list[str] = []
    full_shape = inputs.shape
    cropped = crop_inputs(inputs)
    if cropped.shape != full_shape:
        skipped.append(f"crop: solved on the mask's bounding box {cropped.shape} of {full_shape} super-pixels")
    k = inputs.num_lights
    if k < 3:
        raise ValueError(f"capture: {k} light(s); recovery needs at least 3 non-coplanar lights (add lights)")

    t0 = time.perf_counter()
    n0, albedo0 = _lambertian(cropped, cropped.mask)
    timings["init_lambertian"] = time.perf_counter() - t0

    model = config.model
    if model == "auto":
        model = _choose_model(cropped, n0, albedo0, skipped)
    if model == "fmbrdf" and not cropped.has_polarisation:
        skipped.append("polarisation: no linear polarisation above the noise (no polariser or an unpolarised "
                       "scene): intensity-only fit")

    if model == "lambertian":
        state = _State(GlobalParams(), n0, albedo0)
        params = {"k_d_mean": float(albedo0[cropped.mask].mean()) if bool(cropped.mask.any()) else 0.0}
        rendered_c = (albedo0.unsqueeze(0) * (torch.einsum("hwc,kc->khw", n0, cropped.lights) if cropped.lights.ndim == 2
                      else (n0.unsqueeze(0) * cropped.lights).sum(-1)).clamp_min(0)
                      * (cropped.irradiance.reshape(-1, 1, 1) if cropped.irradiance.ndim == 1 else cropped.irradiance))
        rendered_c = torch.stack([rendered_c, torch.zeros_like(rendered_c), torch.zeros_like(rendered_c)], 1)
        rendered_c = torch.where(cropped.mask, rendered_c, torch.zeros_like(rendered_c))
        normals_c = torch.where(cropped.mask.unsqueeze(-1), n0, torch.full_like(n0, math.nan))
        filled_c = torch.zeros_like(cropped.mask)
        albedo_c = torch.where(cropped.mask, albedo0, torch.full_like(albedo0, math.nan))
    else:
        levels = [cropped]
        if config.coarse_to_fine:
            while int(levels[-1].mask.sum()) > 4 * config.subsample_pixels and min(levels[-1].shape) >= 32:
                levels.append(_downsample(levels[-1]))
        if len(levels) == 1:
            skipped.append("coarse_to_fine: single level (image small enough or disabled)")
        t0 = time.perf_counter()
        initial = [n0]  # Lambertian normals at every level (fallback where the coarser level has none)
        for _ in range(len(levels) - 1):
            initial.append(_unit(F.avg_pool2d(initial[-1].permute(2, 0, 1).unsqueeze(0), 2)[0].permute(1, 2, 0)))
        normals = initial[-1]
        timings["pyramid"] = time.perf_counter() - t0
        params = GlobalParams()
        state = None
        for depth in range(len(levels) - 1, -1, -1):
            level = levels[depth]
            if state is not None:
                up = state.normals.permute(2, 0, 1).unsqueeze(0)
                up = torch.nan_to_num(up, nan=0.0)
                up = F.interpolate(up, scale_factor=2, mode="nearest")[0].permute(1, 2, 0)
                h, w = level.shape
                full = initial[depth].clone()
                hh, ww = min(h, up.shape[0]), min(w, up.shape[1])
                ok = up[:hh, :ww].norm(dim=-1) > 0.5
                full[:hh, :ww][ok] = _unit(up[:hh, :ww][ok])
                normals = full
            state = _fit_level(
                level, normals, params, config, fit_globals=(state is None), fit_kappa=config.fit_kappa,
                history=history, timings=timings, skipped=skipped, level=depth, t_start=t_start,
            )
            params = state.params
        assert state is not None
        supported = cropped.valid.sum(0) >= _MIN_OBSERVATIONS
        filled_n, filled_a, filled_c = _fill_unsupported(state.normals, state.k_b, cropped.mask, supported)
        if bool(filled_c.any()):
            state = _State(state.params, filled_n, filled_a)
            skipped.append(f"fill: {int(filled_c.sum())} mask pixels with < {_MIN_OBSERVATIONS} usable observations "
                           "took their neighbours' normal and albedo (result.filled)")
        if config.smoothness > 0:
            t0 = time.perf_counter()
            state = _smooth_state(cropped, state, config)
            timings["smoothing"] = time.perf_counter() - t0
        else:
            skipped.append("smoothness: 0, per-pixel maximum-likelihood normals (no spatial prior)")
        t0 = time.perf_counter()
        rendered_c = _render(cropped, state)
        timings["render"] = time.perf_counter() - t0
        normals_c, albedo_c = state.normals, state.k_b
        params = state.params.as_dict()
        if not config.per_pixel_albedo:
            skipped.append("per_pixel_albedo: disabled by config (one global k_b)")

    # paste the cropped result back into the full grid
    h, w = full_shape
    r0, c0 = cropped.offset[0] - inputs.offset[0], cropped.offset[1] - inputs.offset[1]
    ch, cw = cropped.shape
    dt, dev = inputs.stokes.dtype, inputs.stokes.device
    normals_out = torch.full((h, w, 3), math.nan, dtype=dt, device=dev)
    normals_out[r0:r0 + ch, c0:c0 + cw] = normals_c.to(dt)
    albedo_out = torch.full((h, w), math.nan, dtype=dt, device=dev)
    albedo_out[r0:r0 + ch, c0:c0 + cw] = albedo_c.to(dt)
    rendered = torch.zeros_like(inputs.stokes)
    rendered[..., r0:r0 + ch, c0:c0 + cw] = rendered_c.to(dt)
    filled = torch.zeros((h, w), dtype=torch.bool, device=dev)
    filled[r0:r0 + ch, c0:c0 + cw] = filled_c
    timings["total"] = time.perf_counter() - t_start
    return RecoveryResult(
        normals=normals_out, albedo=albedo_out, params=params, model=model, mask=inputs.mask.clone(),
        rendered=rendered, observed=inputs.stokes, history=history, timings=timings, skipped=skipped, filled=filled,
    )


def _choose_model(inputs: RecoveryInputs, n0: Tensor, albedo0: Tensor, skipped: list[str]) -> str:
    """"auto": Lambertian when robust PS explains s0 to 3 % of the median intensity (robust residual
    σ; shot noise alone gives ≈ 1–2 %) and the light is unpolarised (median DoLP < 2 %, about the
    noise level of 12-bit data), else the FMBRDF."""
    m = inputs.mask
    s0 = inputs.stokes[:, 0]
    light = inputs.lights
    shade = torch.einsum("hwc,kc->khw", n0, light) if light.ndim == 2 else (n0.unsqueeze(0) * light).sum(-1)
    e = inputs.irradiance.reshape(-1, 1, 1) if inputs.irradiance.ndim == 1 else inputs.irradiance
    pred = albedo0.unsqueeze(0) * shade.clamp_min(0) * e
    use = inputs.valid & m.unsqueeze(0)
    res = (s0 - pred)[use]
    sigma = float(res.abs().median() * 1.4826) if res.numel() else 0.0
    lin = inputs.stokes[:, 1:].norm(dim=1)
    dolp = (lin / s0.clamp_min(1e-6))[use]
    med_dolp = float(dolp.median()) if dolp.numel() else 0.0
    scale = float(s0[use].median()) if bool(use.any()) else 0.0
    if sigma <= 0.03 * scale and med_dolp < 0.02:
        skipped.append(
            f"fmbrdf: Lambertian PS explains the data (robust residual σ {sigma:.2e}, median DoLP {med_dolp:.3f}): "
            "model 'lambertian' chosen"
        )
        return "lambertian"
    return "fmbrdf"


def recover_capture(capture: Capture, config: RecoveryConfig = RecoveryConfig()) -> RecoveryResult:
    """Recover per-pixel normals and reflectance from a polarimetric capture under K known lights.

    Args:
        capture: the capture (frames, lights, mask); directional lights (point lights need a depth
            estimate, see :func:`polarshape.recover.preprocess.preprocess_capture`).
        config: :class:`RecoveryConfig`.

    Returns:
        :class:`RecoveryResult` at the capture's super-pixel resolution (H, W) = frames / 2.

    Raises:
        ValueError: fewer than 3 lights, coplanar lights, invalid configuration or capture.
    """
    _check_config(config)
    torch.manual_seed(config.seed)
    t0 = time.perf_counter()
    inputs = preprocess_capture(capture, dtype=config.dtype, device=config.device, demosaic=config.demosaic,
                                sample_at=config.sample_at)
    t_pre = time.perf_counter() - t0
    result = recover_inputs(inputs, config)
    result.timings["preprocess"] = t_pre
    result.timings["total"] += t_pre
    return result
