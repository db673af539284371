"""Reflectometry with known normals (spec §9, eq. 25): the FMBRDF's global parameters and body albedo.

Model of observation (pixel p, light k), spec §8:

    s[p, k] = E[p, k] · (k_s · S_surf(N_p, L_k, V_p; μ, α, β, κ) + k_b[p] · S_body(N_p, L_k, V_p; μ, α, β, κ))

``s`` is linear in k_s and k_b, so they never enter a non-linear search: for any (μ, α, β, κ) they
are solved in closed form (variable projection): per-pixel k_b[p] = ⟨B_p, O_p − k_s A_p⟩ / ⟨B_p, B_p⟩
(weighted), and substituting it, k_s = Σ_p ⟨A'_p, O'_p⟩ / Σ_p ⟨A'_p, A'_p⟩ with A', O' the parts
orthogonal to B_p (exact joint least squares). With one global k_b the 2 × 2 normal equations are
solved instead. The remaining 3–4 parameters are searched by L-BFGS (strong Wolfe line search) on
an unconstrained reparameterisation — μ = lo + (hi − lo)·σ(u), log α, log β likewise, κ =
κ_max·σ(u) — so that no parameter sits at a clamp with a zero gradient; a coarse grid over (μ, α)
first avoids the local minima of sharp lobes.

Objectives:
- ``"stokes"`` (default, used by the joint solver): Huber loss of the channel-weighted Stokes
  residuals (s0, s1, s2) with weights (1, ½, ½) — the noise variance of s1 = I0 − I90 is twice
  that of s0 = ½ΣI. Huber because shot noise is near Gaussian (quadratic part, efficient) while
  model mismatch — interreflection, cast-shadow edges, demosaicing at edges — produces a few
  large residuals whose influence it bounds (linear part).
- ``"eq25"``: the paper's objective, (1/M) Σ (Ī − I)² + Σ w (ρ̄ − ρ)² / Σ w, with the DoLP outlier
  weights of :func:`eq25_weights`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from polarshape.brdf.body_fast import body_stokes_fast
from polarshape.brdf.fmbrdf import FMBRDFTables, build_tables
from polarshape.brdf.geometry import shading_geometry
from polarshape.brdf.surface import surface_stokes

logger = logging.getLogger(__name__)

__all__ = [
    "CHANNEL_WEIGHTS",
    "GlobalParams",
    "Observations",
    "ReflectanceFit",
    "eq25_loss",
    "eq25_weights",
    "fit_reflectance",
    "huber",
    "render_parts",
    "solve_albedos",
]

#: Residual weights of (s0, s1, s2): inverse noise variance relative to s0.
CHANNEL_WEIGHTS: tuple[float, float, float] = (1.0, 0.5, 0.5)

#: Search bounds of the reparameterised global parameters (inside spec §2's valid ranges).
BOUNDS: dict[str, tuple[float, float]] = {
    "ior": (1.05, 3.0),
    "alpha": (0.01, 2.5),
    "beta": (0.4, 6.0),
    "kappa": (0.0, 100.0),
}


@dataclass(frozen=True)
class Observations:
    """Flattened observations of P pixels under K lights (camera frame).

    Attributes:
        stokes: (P, K, 3) observed Stokes, fraction of full scale, pixel frames.
        weight: (P, K) ≥ 0 observation weights (0 = unusable: dark, saturated, masked).
        lights: (K, 3) or (P, K, 3) unit directions surface → light.
        irradiance: (K,) or (P, K) relative irradiance E.
        view: (P, 3) unit directions surface → camera.
    """

    stokes: Tensor
    weight: Tensor
    lights: Tensor
    irradiance: Tensor
    view: Tensor

    @property
    def num_pixels(self) -> int:
        return int(self.stokes.shape[0])

    def select(self, index: Tensor) -> "Observations":
        """The observations of the pixels ``index`` (1-D long or bool over P)."""
        lights = self.lights if self.lights.ndim == 2 else self.lights[index]
        irr = self.irradiance if self.irradiance.ndim == 1 else self.irradiance[index]
        return Observations(self.stokes[index], self.weight[index], lights, irr, self.view[index])


#: Lobe widths α of the coarse grid search that starts a fit (where the specular lobe is).
ALPHA_GRID: tuple[float, ...] = (0.03, 0.06, 0.12, 0.25, 0.5, 0.9, 1.5)


@dataclass
class GlobalParams:
    """Material parameters shared by all pixels (spec §2). ``k_b`` is the global (or median per-pixel) body albedo."""

    ior: float = 1.5
    alpha: float = 0.3
    beta: float = 2.0
    kappa: float = 0.0
    k_s: float = 1.0
    k_b: float = 0.5

    def as_dict(self) -> dict[str, float]:
        r_k = self.k_b / self.k_s if self.k_s > 0 else math.inf
        return {"ior": self.ior, "alpha": self.alpha, "beta": self.beta, "kappa": self.kappa,
                "k_s": self.k_s, "k_b": self.k_b, "r_k": r_k}


@dataclass
class ReflectanceFit:
    """Result of :func:`fit_reflectance`.

    Attributes:
        params: the fitted global parameters.
        k_b: (P,) per-pixel body albedo (constant when ``per_pixel_albedo`` is False).
        loss: final objective value.
        history: per L-BFGS round: loss, seconds, parameters.
        seconds: wall time.
    """

    params: GlobalParams
    k_b: Tensor
    loss: float
    history: list[dict] = field(default_factory=list)
    seconds: float = 0.0


def render_parts(tables: FMBRDFTables, normals: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
    """Surface and body Stokes of every observation for k_s = k_b = 1, irradiance included.

    Args:
        tables: material tables (:func:`polarshape.brdf.build_tables`), may carry autograd history.
        normals: (P, 3) unit normals, camera frame.
        obs: the observations (lights, irradiance, view).

    Returns:
        (surface, body), each (P, K, 3) in the pixels' Stokes frames.
    """
    n = normals.unsqueeze(1)  # (P, 1, 3)
    lights = obs.lights.unsqueeze(0) if obs.lights.ndim == 2 else obs.lights  # (1|P, K, 3)
    view = obs.view.unsqueeze(1)  # (P, 1, 3)
    n, l, v = torch.broadcast_tensors(n, lights, view)
    # The two terms of polarshape.brdf.fmbrdf_stokes evaluated separately (k_s = k_b = 1), sharing
    # the shading geometry exactly as fmbrdf_stokes does: half the cost of two public calls.
    geo = shading_geometry(n, l, v)
    surf = surface_stokes(
        n, l, v, ior=tables.ior, k_s=1.0, alpha=tables.alpha, beta=tables.beta, c=tables.c,
        projected_area=tables.smith.projected_area, geometry=geo,
    )
    body = body_stokes_fast(tables.body, n, l, v, k_b=1.0, geometry=geo)
    e = obs.irradiance.unsqueeze(0) if obs.irradiance.ndim == 1 else obs.irradiance  # (1|P, K)
    e = e.unsqueeze(-1).to(surf.dtype)
    return surf * e, body * e


def _channel_weights(like: Tensor, polarised: bool) -> Tensor:
    cw = list(CHANNEL_WEIGHTS) if polarised else [1.0, 0.0, 0.0]
    return like.new_tensor(cw)  # (3,)


def solve_albedos(
    surf: Tensor, body: Tensor, obs: Observations, *, per_pixel: bool, polarised: bool = True,
    robust_weight: Tensor | None = None, k_s: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Closed-form weighted least-squares k_s (global) and k_b (per pixel or global), both ≥ 0.

    Args:
        surf, body: (P, K, 3) parts from :func:`render_parts`.
        obs: observations (stokes, weight).
        per_pixel: solve one k_b per pixel (else one global k_b).
        polarised: use s1, s2 (else intensity only).
        robust_weight: optional (P, K, 3) IRLS weights of a robust loss.
        k_s: keep this k_s (0-dim) fixed and only solve k_b.

    Returns:
        k_s (0-dim), k_b (P,) (constant when not per pixel).
    """
    w = obs.weight.unsqueeze(-1) * _channel_weights(surf, polarised)  # (P, K, 3)
    if robust_weight is not None:
        w = w * robust_weight
    o = obs.stokes
    tiny = torch.finfo(surf.dtype).tiny ** 0.5
    if per_pixel:
        bb = (w * body * body).sum((1, 2))  # (P,)
        ab = (w * surf * body).sum((1, 2))
        ob = (w * o * body).sum((1, 2))
        safe = bb.clamp_min(tiny)
        if k_s is None:
            # surf and obs with their projection on body removed, per pixel
            a_perp = surf - (ab / safe)[:, None, None] * body
            o_perp = o - (ob / safe)[:, None, None] * body
            num = (w * a_perp * o_perp).sum()
            den = (w * a_perp * a_perp).sum().clamp_min(tiny)
            k_s = (num / den).clamp_min(0.0)
        k_b = ((ob - k_s * ab) / safe).clamp_min(0.0)
        k_b = torch.where(bb > tiny, k_b, torch.zeros_like(k_b))
        return k_s, k_b
    aa = (w * surf * surf).sum()
    bb = (w * body * body).sum()
    ab = (w * surf * body).sum()
    ao = (w * surf * o).sum()
    bo = (w * body * o).sum()
    if k_s is not None:
        k_b = ((bo - k_s * ab) / bb.clamp_min(tiny)).clamp_min(0.0)
    else:
        det = aa * bb - ab * ab
        k_s = (bb * ao - ab * bo) / det.clamp_min(tiny)
        k_b = (aa * bo - ab * ao) / det.clamp_min(tiny)
        if bool(k_s < 0) or bool(k_b < 0):  # active bound: refit the other alone
            if bool(k_s < 0):
                k_s = torch.zeros_like(k_s)
                k_b = (bo / bb.clamp_min(tiny)).clamp_min(0.0)
            else:
                k_b = torch.zeros_like(k_b)
                k_s = (ao / aa.clamp_min(tiny)).clamp_min(0.0)
    return k_s, k_b.expand(surf.shape[0])


def huber(residual: Tensor, delta: float | Tensor) -> Tensor:
    """Huber ρ(r) = ½r² for |r| ≤ δ, δ(|r| − ½δ) beyond (elementwise)."""
    a = residual.abs()
    return torch.where(a <= delta, 0.5 * residual * residual, delta * (a - 0.5 * delta))


def eq25_weights(dolp: Tensor, valid: Tensor, *, n_mad: float = 3.0) -> Tensor:
    """DoLP outlier weights of eq. 25 (spec §9).

    Observations whose observed DoLP exceeds median + ``n_mad`` · 1.4826 · MAD of the valid DoLPs
    are surface-reflection dominated ("outliers": specular highlights are few but strongly
    polarised). Each outlier gets weight = (#inliers / #outliers) so that both groups count equally
    in the DoLP term; inliers get 1; invalid observations 0.

    Args:
        dolp: (*) observed DoLP.
        valid: (*) bool.

    Returns:
        (*) weights ≥ 0, dtype of ``dolp``.
    """
    v = dolp[valid]
    w = valid.to(dolp.dtype)
    if v.numel() < 3:
        return w
    med = v.median()
    mad = (v - med).abs().median() * 1.4826
    outlier = valid & (dolp > med + n_mad * mad.clamp_min(1e-6))
    n_out = int(outlier.sum())
    n_in = int(valid.sum()) - n_out
    if n_out == 0 or n_in == 0:
        return w
    return torch.where(outlier, torch.full_like(w, n_in / n_out), w)


def _dolp(s: Tensor) -> Tensor:
    lin = torch.sqrt(s[..., 1] ** 2 + s[..., 2] ** 2 + 1e-12)
    return lin / s[..., 0].clamp_min(1e-6)


def eq25_loss(rendered: Tensor, observed: Tensor, valid: Tensor, weights: Tensor) -> Tensor:
    """Eq. 25: (1/M) Σ (Ī − I)² + Σ w (ρ̄ − ρ)² / Σ w over valid observations (0-dim).

    Args:
        rendered, observed: (*, 3) Stokes. valid: (*) bool. weights: (*) from :func:`eq25_weights`.
    """
    vf = valid.to(rendered.dtype)
    m = vf.sum().clamp_min(1.0)
    intensity = (vf * (observed[..., 0] - rendered[..., 0]) ** 2).sum() / m
    w = weights * vf
    dolp = (w * (_dolp(observed) - _dolp(rendered)) ** 2).sum() / w.sum().clamp_min(1e-12)
    return intensity + dolp


# --------------------------------------------------------------------------------------------
# Reparameterisation
# --------------------------------------------------------------------------------------------


def _to_u(name: str, value: float) -> float:
    lo, hi = BOUNDS[name]
    if name in ("alpha", "beta"):
        lo, hi, value = math.log(lo), math.log(hi), math.log(value)
    t = min(max((value - lo) / (hi - lo), 1e-4), 1 - 1e-4)
    return math.log(t / (1 - t))


def _from_u(name: str, u: Tensor) -> Tensor:
    lo, hi = BOUNDS[name]
    if name in ("alpha", "beta"):
        return torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * torch.sigmoid(u))
    return lo + (hi - lo) * torch.sigmoid(u)


def _residuals(
    tables: FMBRDFTables, normals: Tensor, obs: Observations, *, per_pixel: bool, polarised: bool,
    kind: str, eqw: Tensor | None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Residual vector whose (Huber or squared) sum is the objective; plus the closed-form k_s, k_b."""
    surf, body = render_parts(tables, normals, obs)
    k_s, k_b = solve_albedos(surf, body, obs, per_pixel=per_pixel, polarised=polarised)
    model = k_s * surf + k_b[:, None, None] * body  # (P, K, 3)
    if kind == "stokes":
        cw = _channel_weights(surf, polarised).sqrt()
        w = obs.weight.unsqueeze(-1)
        r = (obs.stokes - model) * cw * (w / w.sum().clamp_min(1.0)).sqrt()
        return r.flatten(), k_s, k_b
    assert eqw is not None
    valid = obs.weight > 0
    vf = valid.to(model.dtype)
    r_i = (obs.stokes[..., 0] - model[..., 0]) * (vf / vf.sum().clamp_min(1.0)).sqrt()
    w = eqw * vf
    r_d = (_dolp(obs.stokes) - _dolp(model)) * (w / w.sum().clamp_min(1e-12)).sqrt()
    return torch.cat([r_i.flatten(), r_d.flatten()]), k_s, k_b


def objective(
    params: GlobalParams, normals: Tensor, obs: Observations, *, per_pixel_albedo: bool = True,
    polarised: bool = True, delta: float = 0.01, kind: Literal["stokes", "eq25"] = "stokes", n_grid: int = 65,
) -> float:
    """Objective value of ``params`` for fixed normals: Σ Huber(r, δ') (``"stokes"``) or eq. 25 (``"eq25"``).

    The Stokes residuals are scaled by 1/√(Σ weights), so δ' = δ/√(Σ weights) and the value is the
    mean Huber loss of the channel-weighted Stokes residuals. ``n_grid``: body-table grid (33 is
    enough to rank materials, at half the cost).
    """
    valid = obs.weight > 0
    eqw = eq25_weights(_dolp(obs.stokes), valid) if kind == "eq25" else None
    with torch.no_grad():
        tables = build_tables(ior=params.ior, alpha=params.alpha, beta=params.beta, kappa=params.kappa, device=normals.device,
                              n_grid=n_grid)
        r, _, _ = _residuals(tables, normals, obs, per_pixel=per_pixel_albedo, polarised=polarised, kind=kind, eqw=eqw)
        if kind == "stokes":
            scale = obs.weight.sum().clamp_min(1.0).sqrt()
            return float(huber(r * scale, delta).sum() / scale**2)
        return float((r * r).sum())


def fit_reflectance(
    normals: Tensor,
    obs: Observations,
    *,
    init: GlobalParams | None = None,
    per_pixel_albedo: bool = True,
    fit_kappa: bool = False,
    polarised: bool = True,
    objective_kind: Literal["stokes", "eq25"] = "stokes",
    delta: float = 0.01,
    grid_search: bool = True,
    max_iter: int = 12,
    tol: float = 1e-5,
    fit_names: tuple[str, ...] | None = None,
    n_grid: int = 65,
) -> ReflectanceFit:
    """Fit the global FMBRDF parameters (and k_b) to observations with known normals.

    Solver: Levenberg–Marquardt on the unconstrained parameters u (module docstring), Jacobian by
    forward differences (step 1e-3 in u; the table layout is frozen at the current point during
    each iteration so that the differences are smooth), Huber loss by IRLS. No autograd through the
    table construction, so an iteration costs 2 + (number of parameters) table builds and forward
    passes over the subsample. Stops when the relative decrease stays below ``tol`` for two
    consecutive iterations (a window) or the damping blows up.

    Args:
        normals: (P, 3) unit normals, camera frame.
        obs: :class:`Observations` of the P pixels.
        init: starting parameters (default :class:`GlobalParams` ()).
        per_pixel_albedo: one k_b per pixel (else global).
        fit_kappa: search κ too (else κ stays at ``init.kappa``).
        polarised: use s1, s2 (False: intensity only; μ is then weakly determined).
        objective_kind: ``"stokes"`` (Huber on Stokes) or ``"eq25"`` (eq. 25 with DoLP outlier weights).
        delta: Huber threshold on the channel-weighted Stokes residual, fraction of full scale.
        grid_search: start from the best point of a coarse (μ, α) grid.
        max_iter: most LM iterations.
        tol: relative-decrease convergence threshold.
        fit_names: restrict the searched parameters to these (of ior, alpha, beta, kappa); the
            others stay at ``init``.
        n_grid: body-table grid of the LM iterations (33: a quick, coarser fit).

    Returns:
        :class:`ReflectanceFit`; k_b is (P,).
    """
    t0 = time.perf_counter()
    p = GlobalParams(**vars(init)) if init is not None else GlobalParams()
    dev, dt = normals.device, normals.dtype
    names = ["ior", "alpha", "beta"] + (["kappa"] if fit_kappa else [])
    if fit_names is not None:
        names = [n for n in names if n in fit_names]
    if not polarised and "ior" in names:
        names.remove("ior")  # μ only shapes s0 weakly through Fresnel: keep it fixed without polarisation
    if fit_kappa and p.kappa < 1.0:
        p.kappa = 5.0  # start inside the range: σ-reparameterisation is flat at the bound
    valid = obs.weight > 0
    eqw = eq25_weights(_dolp(obs.stokes), valid) if objective_kind == "eq25" else None
    scale = float(obs.weight.sum().clamp_min(1.0).sqrt()) if objective_kind == "stokes" else 1.0
    d_eff = delta / scale if objective_kind == "stokes" else math.inf
    history: list[dict] = []

    table_grid = n_grid

    def evaluate(
        values: dict[str, float], layout: tuple[float, float, float] | None, n_grid: int = table_grid
    ) -> tuple[Tensor, Tensor, Tensor]:
        tables = build_tables(
            ior=values["ior"], alpha=values["alpha"], beta=values["beta"], kappa=values["kappa"], device=dev,
            layout=layout, n_grid=n_grid,
        )
        return _residuals(tables, normals, obs, per_pixel=per_pixel_albedo, polarised=polarised, kind=objective_kind, eqw=eqw)

    def loss_of(r: Tensor) -> float:
        return float(huber(r, d_eff).sum()) if objective_kind == "stokes" else float((r * r).sum())

    def current() -> dict[str, float]:
        return {"ior": p.ior, "alpha": p.alpha, "beta": p.beta, "kappa": p.kappa}

    with torch.no_grad():
        if grid_search:
            # α decides where the specular lobe is; a coarse table (n_grid 33) is enough to rank them
            best = (math.inf, p.alpha)
            for a in ALPHA_GRID:
                loss = loss_of(evaluate({**current(), "alpha": a}, None, n_grid=33)[0])
                if loss < best[0]:
                    best = (loss, a)
            p.alpha = best[1]
            history.append({"stage": "grid", "loss": best[0], "seconds": time.perf_counter() - t0, **p.as_dict()})

        r, k_s, k_b = evaluate(current(), None)
        loss = loss_of(r)
        lam = 1e-3
        quiet = 0
        h_u = 1e-3
        for it in range(max_iter):
            layout = (p.alpha, p.beta, p.kappa)
            u = torch.tensor([_to_u(n, getattr(p, n)) for n in names], dtype=torch.float64)
            # r was evaluated at the current point with its own layout, which is this layout
            # (build_tables' default): it is the base of the forward differences as it stands
            r_base = r
            cols = []
            for i, n in enumerate(names):
                vals = current()
                vals[n] = float(_from_u(n, u[i] + h_u))
                cols.append((evaluate(vals, layout)[0] - r_base) / h_u)
            jac = torch.stack(cols, -1).to(torch.float64)  # (M, D)
            rb = r_base.to(torch.float64)
            a = rb.abs()
            irls = torch.where(a <= d_eff, torch.ones_like(a), d_eff / a.clamp_min(1e-300))
            jw = jac * irls.unsqueeze(-1)
            hess = jw.T @ jac
            grad = jw.T @ rb
            improved = False
            for _attempt in range(4):  # a few damping increases, then give up: converged
                damp = hess + lam * torch.diag(hess.diagonal() + 1e-12 * hess.diagonal().max().clamp_min(1e-30))
                try:
                    step = -torch.linalg.solve(damp, grad)
                except RuntimeError:
                    lam *= 10
                    continue
                step = step.clamp(-2.0, 2.0)
                if float(step.abs().max()) < 1e-6:
                    break
                trial = {n: float(_from_u(n, u[i] + step[i])) for i, n in enumerate(names)}
                vals = {**current(), **trial}
                r_t, k_s_t, k_b_t = evaluate(vals, None)
                loss_t = loss_of(r_t)
                if math.isfinite(loss_t) and loss_t < loss:
                    rel = (loss - loss_t) / max(loss, 1e-300)
                    for n, v in trial.items():
                        setattr(p, n, v)
                    r, k_s, k_b, loss = r_t, k_s_t, k_b_t, loss_t
                    lam = max(lam / 3, 1e-7)
                    improved = True
                    break
                lam *= 10
            history.append({"stage": "lm", "iteration": it, "loss": loss, "lambda": lam,
                            "seconds": time.perf_counter() - t0, **p.as_dict()})
            if not improved:
                break
            quiet = quiet + 1 if rel < tol else 0
            if quiet >= 2:
                break
    p.k_s = float(k_s)
    # median, not mean: a few pixels the model cannot explain (a block straddling a texture edge)
    # get absurd albedos (measured: mean 15.1 where the median is 3.2)
    p.k_b = float(k_b[k_b > 0].median()) if bool((k_b > 0).any()) else 0.0
    loss_val = loss  # stokes: Σ Huber(raw)/Σw = mean Huber loss, as objective() reports
    logger.debug("reflectometry: loss %.6g after %d LM iterations: %s", loss_val, len(history), p.as_dict())
    return ReflectanceFit(params=p, k_b=k_b.detach().to(dt), loss=loss_val, history=history,
                          seconds=time.perf_counter() - t0)
