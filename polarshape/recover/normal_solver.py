"""Per-pixel normal solver: Levenberg–Marquardt on each pixel's normal for a fixed material.

Each pixel's normal has 2 degrees of freedom (a step in its tangent plane, renormalised); its body
albedo k_b is solved in closed form inside the residual (variable projection,
:func:`polarshape.recover.reflectometry.solve_albedos`). The loss is Huber on channel-weighted Stokes
residuals, minimised by iteratively reweighted least squares with per-pixel damping and
acceptance; the Jacobian is taken by forward differences of the full model, then updated from each
accepted trial (Broyden) instead of taken again. Pixels are independent, so they are solved in chunks
(less memory traffic) and frozen once they stop moving (active set): a pixel whose step is below
:data:`LINEAR_STEP` takes it on the linear model and stops, so a pixel started near its optimum (a
finer pyramid level's bilinear start) costs its residual and two Jacobian columns — 3 evaluations of
the model instead of the 7–10 of an LM that evaluates each trial and confirms with a second one.

:func:`propagate_normals` moves pixels out of per-pixel local minima through their neighbours;
:func:`normal_information` gives each pixel's Gauss–Newton information for the spatial prior
(:mod:`polarshape.recover.priors`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.brdf.geometry import tangent_basis
from polarshape.brdf.fmbrdf import FMBRDFTables
from polarshape.recover.observations import Observations
from polarshape.recover.reflectometry import channel_weights, huber, render_parts, solve_albedos

__all__ = [
    "BROYDEN_MAX_STEP", "CHUNK_PIXELS", "LINEAR_STEP", "NEIGHBOURS_8", "STEP_TOL", "NormalProblem", "huber_delta", "irls_weights", "neighbour_index",
    "normal_information", "normal_jacobian", "propagate_normals", "refine_normals", "tangent_basis", "unit",
]

#: Pixels per chunk of the per-pixel solve: the residual and its intermediates ((P, K) tensors,
#: a few dozen of them) then stay a few MB each instead of hundreds at 1024² super-pixels.
CHUNK_PIXELS = 32768

#: (dy, dx) offsets of the 8-neighbourhood.
NEIGHBOURS_8 = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))

_COS_5DEG = math.cos(math.radians(5.0))

#: A pixel whose Levenberg–Marquardt step (radians in its tangent plane) is below this, nearly
#: undamped, has converged (0.0057°: far below the solve's accuracy, ~0.1°).
STEP_TOL = 1e-4

#: Damping at or below which a step is (nearly) the Gauss–Newton step, so its length measures the
#: distance to the model's optimum (λ starts at 1e-3 and falls by 3 on each accepted step).
_LAM_CONVERGED = 1e-2

#: A (nearly undamped) step shorter than this (radians; 0.17°) is the pixel's last: taken on the
#: linear model, not evaluated (its error is the residual's curvature times the step squared).
LINEAR_STEP = 3e-3

#: Longest accepted step (radians) after which the Jacobian is updated (Broyden) rather than taken
#: again by forward differences (3°: the model's curvature changes the Jacobian by a few % over it).
BROYDEN_MAX_STEP = 0.05


def unit(x: Tensor) -> Tensor:
    """x / |x| along the last axis (zero vectors stay finite)."""
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


@dataclass(frozen=True)
class NormalProblem:
    """Per-pixel residuals r(N) (P, K, 3) for a fixed material, k_b solved in closed form.

    Attributes:
        tables: the material's tables (:func:`polarshape.brdf.build_tables`).
        k_s: 0-dim global specular albedo.
        per_pixel: solve k_b per pixel (else ``k_b_global`` everywhere).
        k_b_global: the global body albedo (used when not ``per_pixel``).
        polarised: fit s1, s2 too (else intensity only).
        delta: Huber threshold on the weighted residuals.
        cw: (3,) square roots of the channel weights.
    """

    tables: FMBRDFTables
    k_s: Tensor
    per_pixel: bool
    k_b_global: float
    polarised: bool
    delta: float
    cw: Tensor

    @classmethod
    def build(cls, tables: FMBRDFTables, like: Tensor, k_s: float, per_pixel: bool, k_b_global: float,
              polarised: bool, delta: float) -> NormalProblem:
        """The problem for observations whose Stokes tensor is ``like`` (its dtype and device)."""
        ks = torch.tensor(float(k_s), dtype=like.dtype, device=like.device)
        return cls(tables, ks, per_pixel, float(k_b_global), polarised, float(delta), channel_weights(like, polarised).sqrt())

    def with_delta(self, delta: float) -> NormalProblem:
        """The same problem with another Huber threshold."""
        return replace(self, delta=float(delta))

    def residual(self, normals: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
        """Weighted residual (P, K, 3) and k_b (P,) for normals (P, 3) of the pixels in ``obs``."""
        surf, body = render_parts(self.tables, normals, obs)
        return self.residual_of_parts(surf, body, obs)

    def residual_of_parts(self, surf: Tensor, body: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
        """:meth:`residual` of rendered parts (P, K, 3) each (:func:`render_parts` of these tables):
        the weighted residual (P, K, 3) and k_b (P,) for this problem's k_s (and k_b)."""
        if self.per_pixel:
            _, k_b = solve_albedos(surf, body, obs, per_pixel=True, polarised=self.polarised, k_s=self.k_s)
        else:
            k_b = torch.full((surf.shape[0],), self.k_b_global, dtype=surf.dtype, device=surf.device)
        r = (obs.stokes - self.k_s * surf - k_b[:, None, None] * body) * self.cw
        return r * obs.weight.sqrt().unsqueeze(-1), k_b

    def loss(self, r: Tensor) -> Tensor:
        """Per-pixel Huber loss (P,) of residuals (P, K, 3)."""
        return huber(r, self.delta).sum((1, 2))

    def pixel_loss(self, normals: Tensor, obs: Observations) -> Tensor:
        """Per-pixel loss (P,) of ``normals`` (P, 3)."""
        with torch.no_grad():
            return self.loss(self.residual(normals, obs)[0])


def normal_jacobian(problem: NormalProblem, n: Tensor, r0: Tensor, obs: Observations, step_h: float
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """Forward-difference Jacobian (A, M, 2) of the flat residuals r0 (A, M) in the tangent basis (t1, t2)."""
    jac, _, t1, t2 = _jacobian_and_albedo(problem, n, r0, None, obs, step_h)
    return jac, t1, t2


def _jacobian_and_albedo(problem: NormalProblem, n: Tensor, r0: Tensor, kb0: Tensor | None, obs: Observations,
                         step_h: float) -> tuple[Tensor, Tensor | None, Tensor, Tensor]:
    """:func:`normal_jacobian` and, from the same evaluations, the derivative (A, 2) of the closed-form
    k_b (A,) (``kb0`` at ``n``; None: not wanted)."""
    t1, t2 = tangent_basis(n)
    cols, kb_cols = [], []
    for t in (t1, t2):
        r, kb = problem.residual(unit(n + step_h * t), obs)
        cols.append((r.reshape(r0.shape) - r0) / step_h)
        if kb0 is not None:
            kb_cols.append((kb - kb0) / step_h)
    return torch.stack(cols, -1), None if kb0 is None else torch.stack(kb_cols, -1), t1, t2


def irls_weights(problem: NormalProblem, r0: Tensor) -> Tensor:
    """Huber IRLS weights of residuals r0."""
    a = r0.abs()
    return torch.where(a <= problem.delta, torch.ones_like(a), problem.delta / a.clamp_min(1e-30))


def _damped_step(jac: Tensor, r0: Tensor, irls: Tensor, lam: Tensor, max_step: float) -> Tensor:
    """Levenberg–Marquardt step (A, 2) of the 2×2 damped normal equations, capped at ``max_step``."""
    jw = jac * irls.unsqueeze(-1)
    h = jw.transpose(1, 2) @ jac  # (A, 2, 2)
    g = (jw * r0.unsqueeze(-1)).sum(1)  # (A, 2)
    diag = torch.diagonal(h, dim1=1, dim2=2)
    damp = h + torch.diag_embed(lam[:, None] * (diag + 1e-12))
    det = damp[:, 0, 0] * damp[:, 1, 1] - damp[:, 0, 1] * damp[:, 1, 0]
    ok = det.abs() > 1e-30
    safe = torch.where(ok, det, torch.ones_like(det))
    d0 = -(damp[:, 1, 1] * g[:, 0] - damp[:, 0, 1] * g[:, 1]) / safe
    d1 = -(-damp[:, 1, 0] * g[:, 0] + damp[:, 0, 0] * g[:, 1]) / safe
    step = torch.stack([d0, d1], -1)
    step = torch.where(ok[:, None], step, torch.zeros_like(step))
    norm = step.norm(dim=-1)
    return step * (max_step / norm.clamp_min(max_step)).unsqueeze(-1)


def _subset(obs: Observations, index: Tensor) -> Observations:
    """``obs.select(index)`` for sorted unique indices (A,) — ``obs`` itself, not a copy, when they are all."""
    return obs if index.numel() == obs.view.shape[0] else obs.select(index)


def _refine_chunk(problem: NormalProblem, normals: Tensor, obs: Observations, *, max_iter: int,
                  step_h: float = 2e-3, max_step: float = 0.25) -> tuple[Tensor, Tensor, Tensor, int]:
    """Levenberg–Marquardt on the normals (P, 3) of one chunk; returns normals, k_b, loss, iterations.

    The Jacobian is taken by forward differences (2 evaluations) at the start and after a rejected
    step; after an accepted step of at most :data:`BROYDEN_MAX_STEP` it is updated from the trial's
    own residual (Broyden's rank-1 update, no evaluation: exact along the step, the other direction
    off by the step times the curvature — the forward difference's own order at these steps).
    A pixel leaves the active set as soon as its (nearly undamped) step is below :data:`LINEAR_STEP`:
    that last step is taken on the linear model (residual, k_b and loss predicted, not evaluated;
    off by the residual's curvature times the step squared — measured: mean and median normal
    errors unchanged to 0.0003°, README). Otherwise it leaves after two iterations without progress."""
    p = normals.shape[0]
    dt, dev = normals.dtype, normals.device
    normals = normals.clone()
    with torch.no_grad():
        r, k_b = problem.residual(normals, obs)
        loss = problem.loss(r)
        shape = r.shape[1:]
        r = r.reshape(p, -1)  # (P, M)
        jac3 = torch.zeros(p, r.shape[1], 3, dtype=dt, device=dev)  # (P, M, 3): dr/dN in the tangent plane
        kb3 = torch.zeros(p, 3, dtype=dt, device=dev)  # (P, 3): dk_b/dN in the tangent plane
        have_jac = torch.zeros(p, dtype=torch.bool, device=dev)  # jac3 usable at the pixel's normal
        exact_jac = torch.zeros(p, dtype=torch.bool, device=dev)  # jac3 by forward differences at it
        lam = torch.full((p,), 1e-3, dtype=dt, device=dev)
        small = torch.zeros(p, dtype=torch.int64, device=dev)
        active = torch.ones(p, dtype=torch.bool, device=dev)
        it = 0
        for it in range(1, max_iter + 1):
            idx = torch.nonzero(active).flatten()
            if idx.numel() == 0:
                break
            sub = _subset(obs, idx)
            n = normals[idx]
            r0 = r[idx]  # (A, M)
            fd = torch.nonzero(~have_jac[idx]).flatten()
            if fd.numel():
                jac_fd, kb_fd, t1, t2 = _jacobian_and_albedo(problem, n[fd], r0[fd], k_b[idx[fd]], _subset(sub, fd),
                                                             step_h)
                basis = torch.stack([t1, t2], -2)  # (F, 2, 3)
                jac3[idx[fd]] = jac_fd @ basis
                kb3[idx[fd]] = (kb_fd.unsqueeze(1) @ basis).squeeze(1)
                have_jac[idx[fd]] = True
                exact_jac[idx[fd]] = True
            t1, t2 = tangent_basis(n)
            jac = jac3[idx] @ torch.stack([t1, t2], -1)  # (A, M, 2)
            step = _damped_step(jac, r0, irls_weights(problem, r0), lam[idx], max_step)
            linear = (step.norm(dim=-1) < LINEAR_STEP) & (lam[idx] <= _LAM_CONVERGED)
            li = torch.nonzero(linear).flatten()
            if li.numel():  # converged: the last step on the linear model
                d3 = step[li, :1] * t1[li] + step[li, 1:] * t2[li]  # (L, 3)
                last = unit(n[li] + d3)
                ok = (last * sub.view[li]).sum(-1) > 0
                pi = idx[li][ok]
                r_lin = r0[li] + (jac[li] @ step[li].unsqueeze(-1)).squeeze(-1)
                normals[pi] = last[ok]
                r[pi] = r_lin[ok]
                k_b[pi] = k_b[pi] + (kb3[pi] * d3[ok]).sum(-1)
                loss[pi] = problem.loss(r_lin[ok].reshape(-1, *shape))
                active[idx[li]] = False
            go = torch.nonzero(~linear).flatten()
            if go.numel() < idx.numel():  # only the pixels still moving try a step
                idx, step, n, t1, t2, r0 = idx[go], step[go], n[go], t1[go], t2[go], r0[go]
                sub = _subset(sub, go)
            if idx.numel() == 0:
                break
            trial = unit(n + step[:, :1] * t1 + step[:, 1:] * t2)
            facing = (trial * sub.view).sum(-1) > 0
            rt, kbt = problem.residual(trial, sub)
            lt = problem.loss(rt)
            rt = rt.reshape(r0.shape)
            accept = facing & (lt < loss[idx]) & torch.isfinite(lt)
            # Broyden: the Jacobians at the accepted trial, exact along the chord d = trial − n
            d = trial - n  # (A, 3)
            dn = d / (d * d).sum(-1, keepdim=True).clamp_min(1e-30)
            miss = (rt - r0) - (jac3[idx] @ d.unsqueeze(-1)).squeeze(-1)  # (A, M)
            miss_kb = (kbt - k_b[idx]) - (kb3[idx] * d).sum(-1)  # (A,)
            ai = idx[accept]
            jac3[ai] += (miss.unsqueeze(-1) * dn.unsqueeze(1))[accept]
            kb3[ai] += (miss_kb.unsqueeze(-1) * dn)[accept]
            exact_jac[ai] = False
            have_jac[idx] = torch.where(accept, step.norm(dim=-1) <= BROYDEN_MAX_STEP, exact_jac[idx])
            normals[ai] = trial[accept]
            r[ai] = rt[accept]
            k_b[ai] = kbt[accept]
            rel = (loss[idx] - lt) / loss[idx].clamp_min(1e-30)
            loss[ai] = lt[accept]
            lam[idx] = torch.where(accept, (lam[idx] / 3).clamp_min(1e-7), (lam[idx] * 4).clamp_max(1e7))
            # frozen after two iterations without progress (active set)
            tiny_step = (step.norm(dim=-1) < STEP_TOL) | (accept & (rel < 1e-7)) | (~accept & (lam[idx] > 1e6))
            small[idx] = torch.where(tiny_step, small[idx] + 1, torch.zeros_like(small[idx]))
            active[idx] = small[idx] < 2
    return normals, k_b, loss, it


def refine_normals(problem: NormalProblem, normals: Tensor, obs: Observations, *, max_iter: int
                   ) -> tuple[Tensor, Tensor, Tensor, int]:
    """Per-pixel Levenberg–Marquardt from ``normals`` (P, 3), in chunks of :data:`CHUNK_PIXELS`.

    Returns:
        normals (P, 3), k_b (P,), per-pixel loss (P,), and the most iterations any chunk took.
    """
    p = normals.shape[0]
    if p <= CHUNK_PIXELS:
        return _refine_chunk(problem, normals, obs, max_iter=max_iter)
    parts = []
    for start in range(0, p, CHUNK_PIXELS):
        idx = torch.arange(start, min(start + CHUNK_PIXELS, p), device=normals.device)
        parts.append(_refine_chunk(problem, normals[idx], obs.select(idx), max_iter=max_iter))
    return (torch.cat([q[0] for q in parts]), torch.cat([q[1] for q in parts]), torch.cat([q[2] for q in parts]),
            max(q[3] for q in parts))


def neighbour_index(pixels: Tensor) -> Tensor:
    """(P, 8) flat indices (row-major over ``pixels`` (H, W) True) of each pixel's 8 neighbours
    inside ``pixels``; −1 where a neighbour is outside."""
    h, w = pixels.shape
    flat = torch.full((h, w), -1, dtype=torch.int64, device=pixels.device)
    flat[pixels] = torch.arange(int(pixels.sum()), device=pixels.device)
    padded = F.pad(flat, (1, 1, 1, 1), value=-1)
    cols = [padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w][pixels] for dy, dx in NEIGHBOURS_8]
    return torch.stack(cols, -1)


def _try_neighbour(problem: NormalProblem, normals: Tensor, k_b: Tensor, loss: Tensor, obs: Observations,
                   nb: Tensor, switched: Tensor) -> None:
    """Each pixel tries the normal of its neighbour ``nb`` (P,); keeps it where it fits better (in place)."""
    # only neighbours that differ (> 5°) from the pixel's own normal are worth a try
    differs = (normals * normals[nb.clamp_min(0)]).sum(-1) < _COS_5DEG
    cand_idx = torch.nonzero((nb >= 0) & differs).flatten()
    for start in range(0, cand_idx.numel(), CHUNK_PIXELS):
        idx = cand_idx[start:start + CHUNK_PIXELS]
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


def propagate_normals(
    problem: NormalProblem, normals: Tensor, k_b: Tensor, loss: Tensor, obs: Observations, neighbours: Tensor,
    *, passes: int = 3, max_iter: int = 6,
) -> tuple[Tensor, Tensor, Tensor, int]:
    """Escape per-pixel local minima: each pixel tries its neighbours' normals (PatchMatch-style
    propagation) and takes one that fits its own data better, then Levenberg–Marquardt polishes the
    pixels that switched. A smooth surface hands its neighbours a start inside the right basin
    where the initial (Lambertian) normal was outside it (measured: a patch 20–25° off under a
    highlight on a dark checker cell).

    Args:
        problem: the per-pixel problem (fixed material).
        normals, k_b, loss: (P, 3), (P,), (P,) current per-pixel solution and its loss.
        obs: observations of the P pixels.
        neighbours: (P, 8) from :func:`neighbour_index`.
        passes: propagation rounds (each reaches at least one pixel further). Only neighbours whose
            normal differs from the pixel's by > 5° are tried (closer ones are in the same basin).

    Returns:
        normals, k_b, loss (new tensors), and the number of pixels that switched.
    """
    normals, k_b, loss = normals.clone(), k_b.clone(), loss.clone()
    switched_total = 0
    with torch.no_grad():
        for _ in range(passes):
            switched = torch.zeros(normals.shape[0], dtype=torch.bool, device=normals.device)
            for j in range(neighbours.shape[1]):
                _try_neighbour(problem, normals, k_b, loss, obs, neighbours[:, j], switched)
            moved = torch.nonzero(switched).flatten()
            if moved.numel() == 0:
                break
            switched_total += int(moved.numel())
            n_m, kb_m, l_m, _ = _refine_chunk(problem, normals[moved], obs.select(moved), max_iter=max_iter)
            normals[moved], k_b[moved], loss[moved] = n_m, kb_m, l_m
    return normals, k_b, loss, switched_total


def huber_delta(obs: Observations, noise_std: float, residual: Tensor | None = None) -> float:
    """Huber threshold: 3 × the robust (MAD) σ of ``residual`` (P, K, 3) over the usable observations,
    floored at 4 quantisation-noise σ; without a residual, max(4σ, 0.01)."""
    floor = 4.0 * noise_std
    if residual is None:
        return max(floor, 0.01)
    v = residual[obs.weight > 0].abs().flatten()
    if v.numel() == 0:
        return floor
    sigma = float(v.median()) * 1.4826
    return max(3.0 * sigma, floor)


def normal_information(problem: NormalProblem, normals: Tensor, obs: Observations, step_h: float = 2e-3,
                       residual: Tensor | None = None) -> Tensor:
    """Gauss–Newton information (P, 3, 3) of each pixel's normal (P, 3) in the camera frame.

    JᵀWJ of the (Huber-reweighted) residuals in the tangent plane (forward differences, as in
    :func:`refine_normals`), mapped to 3-D: T (JᵀWJ) Tᵀ with T = [t1 t2] (P, 3, 2). Rank 2: the data
    say nothing along N itself. ``residual``: ``problem.residual(normals, obs)[0]`` when the caller has it.
    """
    with torch.no_grad():
        r0 = problem.residual(normals, obs)[0] if residual is None else residual
        r0 = r0.reshape(normals.shape[0], -1)  # (P, M)
        jac, t1, t2 = normal_jacobian(problem, normals, r0, obs, step_h)
        h = (jac * irls_weights(problem, r0).unsqueeze(-1)).transpose(1, 2) @ jac  # (P, 2, 2)
        basis = torch.stack([t1, t2], -1)  # (P, 3, 2)
        return basis @ h @ basis.transpose(1, 2)
