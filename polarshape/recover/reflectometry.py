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

from polarshape.brdf.body_fast import body_parts
from polarshape.brdf.fmbrdf import FMBRDFTables, build_tables
from polarshape.brdf.geometry import Vec3, shading_geometry3
from polarshape.brdf.params import FMBRDFParams
from polarshape.brdf.surface import surface_parts
from polarshape.imaging.stokes import dolp
from polarshape.recover.observations import Observations

logger = logging.getLogger(__name__)

__all__ = [
    "ALPHA_GRID",
    "BOUNDS",
    "CHANNEL_WEIGHTS",
    "ReflectanceFit",
    "channel_weights",
    "eq25_loss",
    "eq25_weights",
    "fit_reflectance",
    "huber",
    "objective",
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


#: Lobe widths α of the coarse grid search that starts a fit (where the specular lobe is).
ALPHA_GRID: tuple[float, ...] = (0.03, 0.06, 0.12, 0.25, 0.5, 0.9, 1.5)


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

    params: FMBRDFParams
    k_b: Tensor
    loss: float
    history: list[dict] = field(default_factory=list)
    seconds: float = 0.0


#: Pixel·light evaluations per chunk of :func:`render_parts` on CPU with one thread: the model's few dozen
#: temporaries then stay in the cache (a chunk's float32 temporary is 256 kB) instead of streaming
#: through memory; measured optimum on a 2-core Xeon (benchmarks/render_parts.py). Other devices
#: take the whole batch at once.
RENDER_CHUNK = 1 << 16


def _render_chunk(tables: FMBRDFTables, normals: Tensor, lights: Tensor, view: Tensor, irradiance: Tensor) -> tuple[Vec3, Vec3]:
    """:func:`render_parts` of p pixels as components, each (K, p): light-major, so that what depends
    on the pixel alone (N, V, the Stokes frame, θ_V and its table lookups) is computed once per
    pixel and broadcast along the lights, with the pixels contiguous."""
    n = tuple(normals.t().contiguous())  # 3 × (p,)
    v = tuple(view.t().contiguous())  # 3 × (p,)
    l = tuple(lights.permute(2, 1, 0).contiguous())  # 3 × (K, p)
    e = irradiance.t().to(normals.dtype)  # (K, p)
    # The two terms of polarshape.brdf.fmbrdf_stokes evaluated separately (k_s = k_b = 1), sharing
    # the shading geometry exactly as fmbrdf_stokes does: half the cost of two public calls.
    geo = shading_geometry3(n, l, v)  # type: ignore[arg-type]
    surf = surface_parts(
        geo, ior=tables.ior, scale=e, alpha=tables.alpha, beta=tables.beta, c=tables.c,
        projected_area=tables.smith.projected_area,
    )
    body = body_parts(tables.body, geo, scale=e)
    return surf, body


def render_parts(tables: FMBRDFTables, normals: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
    """Surface and body Stokes of every observation for k_s = k_b = 1, irradiance included.

    Without autograd on CPU with one thread, evaluated in chunks of :data:`RENDER_CHUNK` pixel·lights
    (else in one piece); differentiable in the normals and the tables.

    Args:
        tables: material tables (:func:`polarshape.brdf.build_tables`), may carry autograd history.
        normals: (P, 3) unit normals, camera frame.
        obs: the observations (lights, irradiance, view).

    Returns:
        (surface, body), each (P, K, 3) in the pixels' Stokes frames.
    """
    p, k = obs.lights.shape[:2]
    if torch.is_grad_enabled() or normals.device.type != "cpu" or torch.get_num_threads() > 1 or p == 0:
        # one piece: autograd keeps every intermediate anyway; with several threads every operation is
        # a parallel region whose threads join, and on a busy box each join can wait for a descheduled
        # thread (measured: chunks several times slower at 2 threads and load 8)
        surf, body = _render_chunk(tables, normals, obs.lights, obs.view, obs.irradiance)
        return tuple(torch.stack([c.broadcast_to((k, p)).t() for c in x], dim=-1) for x in (surf, body))  # type: ignore[return-value]
    step = max(1, RENDER_CHUNK // max(k, 1))
    out: Tensor | None = None  # (2, P, K, 3): the chunks are stacked into it
    for p0 in range(0, p, step):
        sl = slice(p0, min(p0 + step, p))
        surf, body = _render_chunk(tables, normals[sl], obs.lights[sl], obs.view[sl], obs.irradiance[sl])
        if out is None:
            out = surf[0].new_empty((2, p, k, 3))
        for x, o in zip((surf, body), out[:, sl]):
            torch.stack([c.broadcast_to((k, sl.stop - sl.start)).t() for c in x], dim=-1, out=o)
    assert out is not None
    return out[0], out[1]


def channel_weights(like: Tensor, polarised: bool) -> Tensor:
    """(3,) residual weights of (s0, s1, s2) (:data:`CHANNEL_WEIGHTS`; intensity only: (1, 0, 0)),
    dtype and device of ``like``."""
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
    w = obs.weight.unsqueeze(-1) * channel_weights(surf, polarised)  # (P, K, 3)
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
    """DoLP of (..., 3) Stokes vectors, s0 floored at 1e-6 (eq. 25's ρ)."""
    return dolp(s, dim=-1, eps=1e-6)


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
        cw = channel_weights(surf, polarised).sqrt()
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
    params: FMBRDFParams, normals: Tensor, obs: Observations, *, per_pixel_albedo: bool = True,
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
    init: FMBRDFParams | None = None,
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
        init: starting parameters (default :class:`FMBRDFParams` ()).
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
    p = FMBRDFParams(**vars(init)) if init is not None else FMBRDFParams()
    names = ["ior", "alpha", "beta"] + (["kappa"] if fit_kappa else [])
    if fit_names is not None:
        names = [n for n in names if n in fit_names]
    if not polarised and "ior" in names:
        names.remove("ior")  # μ only shapes s0 weakly through Fresnel: keep it fixed without polarisation
    if fit_kappa and p.kappa < 1.0:
        p.kappa = 5.0  # start inside the range: σ-reparameterisation is flat at the bound
    obj = _Objective.build(normals, obs, per_pixel_albedo, polarised, objective_kind, delta, n_grid)
    history: list[dict] = []
    with torch.no_grad():
        if grid_search:
            loss, p.alpha = _grid_alpha(obj, p)
            history.append({"stage": "grid", "loss": loss, "seconds": time.perf_counter() - t0, **p.as_dict()})
        r, k_s, k_b = obj.evaluate(_nonlinear(p), None)
        loss = obj.loss_of(r)
        lam = 1e-3
        quiet = 0
        for it in range(max_iter):
            step = _lm_step(obj, p, names, r, loss, lam)
            lam = step.lam
            if step.improved:
                rel = (loss - step.loss) / max(loss, 1e-300)
                for n, v in step.values.items():
                    setattr(p, n, v)
                r, k_s, k_b, loss = step.r, step.k_s, step.k_b, step.loss
            history.append({"stage": "lm", "iteration": it, "loss": loss, "lambda": lam,
                            "seconds": time.perf_counter() - t0, **p.as_dict()})
            if not step.improved:
                break
            quiet = quiet + 1 if rel < tol else 0
            if quiet >= 2:
                break
    p.k_s = float(k_s)
    # median, not mean: a few pixels the model cannot explain (a block straddling a texture edge)
    # get absurd albedos (measured: mean 15.1 where the median is 3.2)
    p.k_b = float(k_b[k_b > 0].median()) if bool((k_b > 0).any()) else 0.0
    # stokes: Σ Huber(raw)/Σw = mean Huber loss, as objective() reports
    logger.debug("reflectometry: loss %.6g after %d LM iterations: %s", loss, len(history), p.as_dict())
    return ReflectanceFit(params=p, k_b=k_b.detach().to(normals.dtype), loss=loss, history=history,
                          seconds=time.perf_counter() - t0)


def _nonlinear(p: FMBRDFParams) -> dict[str, float]:
    """The parameters that need a table build (μ, α, β, κ)."""
    return {"ior": p.ior, "alpha": p.alpha, "beta": p.beta, "kappa": p.kappa}


@dataclass(frozen=True)
class _Objective:
    """The residuals of :func:`fit_reflectance` at given (μ, α, β, κ), normals and observations fixed."""

    normals: Tensor
    obs: Observations
    per_pixel: bool
    polarised: bool
    kind: str
    eqw: Tensor | None
    d_eff: float  # Huber threshold on the scaled residuals
    n_grid: int

    @classmethod
    def build(cls, normals: Tensor, obs: Observations, per_pixel: bool, polarised: bool, kind: str,
              delta: float, n_grid: int) -> _Objective:
        eqw = eq25_weights(_dolp(obs.stokes), obs.weight > 0) if kind == "eq25" else None
        scale = float(obs.weight.sum().clamp_min(1.0).sqrt()) if kind == "stokes" else 1.0
        d_eff = delta / scale if kind == "stokes" else math.inf
        return cls(normals, obs, per_pixel, polarised, kind, eqw, d_eff, n_grid)

    def evaluate(self, values: dict[str, float], layout: tuple[float, float, float] | None,
                 n_grid: int | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Residuals, k_s, k_b at ``values`` (tables on ``layout``: None = their own)."""
        tables = build_tables(
            ior=values["ior"], alpha=values["alpha"], beta=values["beta"], kappa=values["kappa"],
            device=self.normals.device, layout=layout, n_grid=self.n_grid if n_grid is None else n_grid,
        )
        return _residuals(tables, self.normals, self.obs, per_pixel=self.per_pixel, polarised=self.polarised,
                          kind=self.kind, eqw=self.eqw)

    def loss_of(self, r: Tensor) -> float:
        return float(huber(r, self.d_eff).sum()) if self.kind == "stokes" else float((r * r).sum())


def _grid_alpha(obj: _Objective, p: FMBRDFParams) -> tuple[float, float]:
    """(loss, α) of the best :data:`ALPHA_GRID` lobe width: α decides where the specular lobe is,
    and a coarse table (n_grid 33) is enough to rank them."""
    best = (math.inf, p.alpha)
    for a in ALPHA_GRID:
        loss = obj.loss_of(obj.evaluate({**_nonlinear(p), "alpha": a}, None, n_grid=33)[0])
        if loss < best[0]:
            best = (loss, a)
    return best


@dataclass(frozen=True)
class _Step:
    improved: bool
    lam: float
    values: dict[str, float] = field(default_factory=dict)
    r: Tensor | None = None
    k_s: Tensor | None = None
    k_b: Tensor | None = None
    loss: float = math.inf


def _lm_step(obj: _Objective, p: FMBRDFParams, names: list[str], r: Tensor, loss: float, lam: float,
             h_u: float = 1e-3) -> _Step:
    """One Levenberg–Marquardt iteration in the unconstrained parameters u of ``names``."""
    layout = (p.alpha, p.beta, p.kappa)
    u = torch.tensor([_to_u(n, getattr(p, n)) for n in names], dtype=torch.float64)
    # r was evaluated at the current point with its own layout, which is this layout
    # (build_tables' default): it is the base of the forward differences as it stands
    cols = []
    for i, n in enumerate(names):
        vals = _nonlinear(p)
        vals[n] = float(_from_u(n, u[i] + h_u))
        cols.append((obj.evaluate(vals, layout)[0] - r) / h_u)
    jac = torch.stack(cols, -1).to(torch.float64)  # (M, D)
    rb = r.to(torch.float64)
    a = rb.abs()
    irls = torch.where(a <= obj.d_eff, torch.ones_like(a), obj.d_eff / a.clamp_min(1e-300))
    jw = jac * irls.unsqueeze(-1)
    hess = jw.T @ jac
    grad = jw.T @ rb
    for _attempt in range(4):  # a few damping increases, then give up: converged
        damp = hess + lam * torch.diag(hess.diagonal() + 1e-12 * hess.diagonal().max().clamp_min(1e-30))
        try:
            step = -torch.linalg.solve(damp, grad)
        except RuntimeError:
            lam *= 10
            continue
        step_host = step.clamp(-2.0, 2.0).tolist()  # D numbers, one host sync: the tables are built from them
        if max(abs(d) for d in step_host) < 1e-6:
            break
        trial = {n: float(_from_u(n, u[i] + step_host[i])) for i, n in enumerate(names)}
        r_t, k_s_t, k_b_t = obj.evaluate({**_nonlinear(p), **trial}, None)
        loss_t = obj.loss_of(r_t)
        if math.isfinite(loss_t) and loss_t < loss:
            return _Step(True, max(lam / 3, 1e-7), trial, r_t, k_s_t, k_b_t, loss_t)
        lam *= 10
    return _Step(False, lam)
