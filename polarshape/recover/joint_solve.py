"""The joint solve: per-pixel normals and the global material in one Levenberg–Marquardt.

The FMBRDF fit has the structure of bundle adjustment: P small per-pixel blocks (a normal, 2 DoF in
its tangent plane; the body albedo k_b[p] in closed form inside the residual, as in
:class:`polarshape.recover.normal_solver.NormalProblem`) coupled through G ≤ 6 shared parameters
(μ, log α, log β, [κ], k_s, [one global k_b]). Alternating between the two converges slowly exactly
when they are correlated (a shiny lobe: α against the normals under the highlight). Here both move
together: each iteration forms the Gauss–Newton system of the Huber-reweighted (IRLS) residuals

    [H_nn  H_ng] [δn]     [b_n]        H_nn: P blocks 2 × 2,  H_ng: P blocks 2 × G,
    [H_gn  H_gg] [δg] = − [b_g]        H_gg: G × G

and eliminates the per-pixel blocks by the Schur complement (:func:`schur_step`): the reduced system
S δg = −(b_g − Σ H_gnᵀ H_nn⁻¹ b_n), S = H_gg − Σ H_gn H_nn⁻¹ H_ng, is only G × G; then
δn_p = −H_nn,p⁻¹ (b_n,p + H_ng,p δg), all pixels batched on the device. Damping is Levenberg–
Marquardt's λ·diag(H) with one λ for the globals and one per pixel.

Jacobians: w.r.t. a normal by forward differences of the full model (as the per-pixel solver);
w.r.t. μ, α, β, κ by forward differences through coarse tables (body grid 33 instead of 65, a
quarter of the build) — G + 1 table builds per iteration (:func:`polarshape.brdf.build_tables`),
all on the iteration's table layout so that the differences are smooth; the loss itself always
uses the full tables; w.r.t. k_s (and a global k_b) from the rendered
parts, without a table build.

Bounds: a global at its bound whose step points outward is held for that step (its coupling
removed and the system solved again), so the others do not move as if it had.

Highlight candidates: under a narrow lobe a normal off its highlight by more than the lobe's width
sees no gradient towards it, and the material then widens the lobe to reach it (measured on the 40²
α 0.03 sphere: 2 of 1052 pixels 18° and 35° off carried all of the loss difference to the truth, and
dragged α to 0.085, β to its bound 6). So before the first iteration and after every accepted step
each pixel also tries the half vector of the view and its brightest light (irradiance-relative) and
keeps it where its loss is lower (:func:`_try_highlights`): one render, no table build.

Acceptance: the trial globals are evaluated with each pixel's old and new normal, and each pixel
keeps the better (for fixed globals the loss is a sum of per-pixel terms), so a pixel whose
normal step overshoots does not veto the globals' step; the step is taken when the total loss
falls, else the globals' λ grows tenfold. Stops when the relative loss change of an accepted
step is below ``tol`` (relative to max(loss, δ²/100): below that the loss is far under the
noise's) or no damping finds a descent. The loss never rises, so a fit that adds κ to a κ = 0
optimum (:func:`nested_kappa`, which also tries from the κ = 0 solve's start when κ does not grow
from the optimum, and keeps the lower) can only lower it: a proper nested fit. Whether the gain is
the data's or a few pixels' is :func:`trimmed_gain`'s question.

Host syncs: per iteration the globals' step (G numbers, the tables are built from them) and the
total loss (the acceptance and convergence test) come to the host; every per-pixel operation stays
batched on the device.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from polarshape.brdf.fmbrdf import FMBRDFTables, build_tables
from polarshape.brdf.params import FMBRDFParams
from polarshape.recover.normal_solver import NormalProblem, irls_weights, normal_jacobian, unit
from polarshape.recover.observations import Observations
from polarshape.recover.reflectometry import BOUNDS, render_parts, solve_albedos

logger = logging.getLogger(__name__)

__all__ = ["JointResult", "TABLE_PARAMS", "clearly_below", "first_of", "joint_solve", "loss_floor", "nested_kappa",
           "schur_step", "settled", "trimmed_gain"]

#: The global parameters that need a table build, in the order of the global vector.
TABLE_PARAMS: tuple[str, ...] = ("ior", "alpha", "beta", "kappa")

_LOG_PARAMS = ("alpha", "beta")  # searched in log: a step is a relative change
#: κ is searched in u = log(1 + κ/κ₀), κ₀ = _KAPPA_SHIFT: 0 at κ = 0 (where the nested fit starts), a
#: relative change of κ + κ₀ per unit. The kernel's width goes as 1/√κ, so the loss is far from quadratic
#: in κ itself: searched in κ, the polish on the 256² α 0.8 κ 50 perspective sphere climbed from κ 15 to 50
#: in 6 Gauss–Newton steps of 3, 6, 10, 10, 4.5 (each accepted, ρ 0.4–1), the test before it from 0 to 15 in 6.
_KAPPA_SHIFT = 5.0
#: Forward-difference steps in the search coordinate (log for α, β; κ: :func:`_fd_step`).
_FD_STEP = {"ior": 1e-3, "alpha": 1e-3, "beta": 1e-3}
#: Largest step of one iteration in the search coordinate (a trust region on top of the damping; κ:
#: a factor e in κ + κ₀, from κ = 0 up to 8.6).
_MAX_STEP = {"ior": 0.5, "alpha": 1.0, "beta": 1.0, "kappa": 1.0}
#: With κ fitted the tables are laid out for at least this κ, so that ∂/∂κ at κ = 0 sees the
#: azimuthal modes (a κ = 0 layout is separable and blind to κ).
_KAPPA_LAYOUT_MIN = 2.0


@dataclass
class JointResult:
    """Result of :func:`joint_solve`.

    Attributes:
        params: the fitted material (k_b: median of the per-pixel k_b > 0, or the global k_b).
        normals: (P, 3) unit normals. k_b: (P,) body albedo.
        loss: final mean Huber loss per unit observation weight. initial_loss: the same at the start.
        iterations: LM iterations taken. rel_change: relative loss change of the last iteration
            (0 when no damping found a descent). converged: ``rel_change < tol``.
        history: per iteration: loss, relative change, λ of the globals, whether a step was taken, the
            share of pixels whose normal step was kept (``moved``), seconds, parameters; and what the LM
            did: ``attempts`` (damping tries), ``rho`` (each try's gain ratio, actual over the
            Gauss–Newton model's predicted loss decrease; None where it predicted none), ``step`` (the
            accepted step of the globals in the search coordinate: log α, log β), ``pinned`` (globals
            held at a bound), ``jumped`` (pixels that took their highlight candidate).
        seconds: wall time.
        start_normals, start_params: where the solve started ((P, 3) and the material), for a restart.
        pixel_loss: (P,) each pixel's final Huber loss (unnormalised: ``loss`` is their sum over the
            observation weight). initial_pixel_loss: (P,) the same at the start.
    """

    params: FMBRDFParams
    normals: Tensor
    k_b: Tensor
    loss: float
    initial_loss: float
    iterations: int
    rel_change: float
    converged: bool
    history: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    start_normals: Tensor | None = None
    start_params: FMBRDFParams | None = None
    pixel_loss: Tensor | None = None
    initial_pixel_loss: Tensor | None = None


def schur_step(h_nn: Tensor, h_ng: Tensor, h_gg: Tensor, b_n: Tensor, b_g: Tensor, lam_n: Tensor, lam_g: float,
               eps: float = 1e-12) -> tuple[Tensor, Tensor]:
    """Damped Gauss–Newton step of the block system by the Schur complement of the per-pixel blocks.

    Solves (H + diag(λ ⊙ (diag H + ε))) [δn; δg] = −[b_n; b_g] with H = [[blockdiag(H_nn), H_ng],
    [H_ngᵀ, H_gg]], λ = λ_n[p] on pixel p's rows and λ_g on the globals' (module docstring).

    Args:
        h_nn: (P, 2, 2) per-pixel blocks. h_ng: (P, 2, G) couplings. h_gg: (G, G).
        b_n: (P, 2), b_g: (G,) gradients. lam_n: (P,) per-pixel damping. lam_g: the globals' damping.
        eps: added to the diagonal before scaling by λ (keeps empty blocks invertible).

    Returns:
        δn (P, 2), δg (G,), dtype and device of the inputs.
    """
    g = h_gg.shape[0]
    d = torch.diagonal(h_nn, dim1=1, dim2=2)  # (P, 2)
    a = h_nn[:, 0, 0] + lam_n * (d[:, 0] + eps)
    b, c = h_nn[:, 0, 1], h_nn[:, 1, 0]
    e = h_nn[:, 1, 1] + lam_n * (d[:, 1] + eps)
    det = a * e - b * c
    det = torch.where(det.abs() > 1e-300, det, torch.ones_like(det))
    inv = torch.stack([torch.stack([e, -b], -1), torch.stack([-c, a], -1)], -2) / det[:, None, None]  # (P, 2, 2)
    x = inv @ torch.cat([h_ng, b_n.unsqueeze(-1)], -1)  # (P, 2, G + 1): H_nn⁻¹ [H_ng | b_n]
    hgt = h_ng.transpose(1, 2)  # (P, G, 2)
    s = h_gg + torch.diag(lam_g * (torch.diagonal(h_gg) + eps)) - (hgt @ x[..., :g]).sum(0)  # (G, G)
    rhs = b_g - (hgt @ x[..., g:]).sum(0).squeeze(-1)  # (G,)
    dg = -torch.linalg.solve(s, rhs)
    dn = -(x[..., g] + (x[..., :g] @ dg.unsqueeze(-1)).squeeze(-1))
    return dn, dg


def _bounds(name: str) -> tuple[float, float]:
    return BOUNDS.get(name, (0.0, math.inf))


def _to_u(name: str, value: float) -> float:
    """The search coordinate of a global (log for α, β; log(1 + κ/κ₀) for κ; the value otherwise)."""
    if name == "kappa":
        return math.log1p(max(value, 0.0) / _KAPPA_SHIFT)
    return math.log(value) if name in _LOG_PARAMS else value


def _from_u(name: str, u: float) -> float:
    """The value of search coordinate ``u`` (:func:`_to_u`), clamped to the global's bounds."""
    lo, hi = _bounds(name)
    if name == "kappa":
        v = _KAPPA_SHIFT * math.expm1(min(u, 50.0))
    else:
        v = math.exp(min(u, 50.0)) if name in _LOG_PARAMS else u
    return min(max(v, lo), hi)


def _fd_step(name: str, value: float) -> float:
    """Signed forward-difference step in the search coordinate (backward at an upper bound)."""
    if name == "kappa":  # κ + max(2 %, 0.5) in the coordinate log(1 + κ/κ₀)
        h = math.log1p(max(0.02 * value, 0.5) / (value + _KAPPA_SHIFT))
    elif name in _FD_STEP:
        h = _FD_STEP[name]
    else:  # albedos, linear
        h = 1e-3 * max(abs(value), 1e-3)
    _, hi = _bounds(name)
    return -h if _from_u(name, _to_u(name, value) + h) >= hi else h


def _pinned(names: tuple[str, ...], vals: dict[str, float], step: list[float]) -> list[int]:
    """Indices of the globals that sit at a bound and whose step points outward (an active bound)."""
    out = []
    for i, (name, d) in enumerate(zip(names, step)):
        lo, hi = _bounds(name)
        v = vals[name]
        if (d < 0 and v <= lo * (1 + 1e-9) + 1e-12) or (d > 0 and v >= hi * (1 - 1e-9)):
            out.append(i)
    return out


def _hold(pinned: list[int], h_ng: Tensor, h_gg: Tensor, b_g: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(H_ng, H_gg, b_g) with the ``pinned`` globals decoupled and given a zero step."""
    h_ng, h_gg, b_g = h_ng.clone(), h_gg.clone(), b_g.clone()
    idx = torch.tensor(pinned, device=h_gg.device)
    h_ng[..., idx] = 0.0
    h_gg[idx, :] = 0.0
    h_gg[:, idx] = 0.0
    h_gg[idx, idx] = 1.0
    b_g[idx] = 0.0
    return h_ng, h_gg, b_g


def _max_step(name: str, value: float) -> float:
    return _MAX_STEP.get(name, 0.5 * max(abs(value), 1e-3))


@dataclass(frozen=True)
class _Model:
    """What stays fixed during a solve: observations, the fitted names and the loss settings."""

    obs: Observations
    table_names: tuple[str, ...]
    linear_names: tuple[str, ...]
    per_pixel: bool
    polarised: bool
    delta: float
    n_grid: int
    jac_grid: int

    def tables(self, vals: dict[str, float], layout_of: dict[str, float] | None = None) -> FMBRDFTables:
        """Tables of ``vals`` laid out at ``layout_of`` (default: ``vals`` themselves)."""
        lay = vals if layout_of is None else layout_of
        kap_layout = max(lay["kappa"], _KAPPA_LAYOUT_MIN) if "kappa" in self.table_names else lay["kappa"]
        return build_tables(ior=vals["ior"], alpha=vals["alpha"], beta=vals["beta"], kappa=vals["kappa"],
                            device=self.obs.stokes.device, n_grid=self.n_grid,
                            layout=(lay["alpha"], lay["beta"], kap_layout))

    def problem(self, tables: FMBRDFTables, vals: dict[str, float]) -> NormalProblem:
        return NormalProblem.build(tables, self.obs.stokes, vals["k_s"], self.per_pixel, vals["k_b"],
                                   self.polarised, self.delta)


@dataclass
class _State:
    """The current point: globals, tables, normals, their rendered parts, residuals and loss."""

    vals: dict[str, float]
    problem: NormalProblem
    n: Tensor  # (P, 3)
    surf: Tensor  # (P, K, 3)
    body: Tensor  # (P, K, 3)
    r: Tensor  # (P, K, 3)
    k_b: Tensor  # (P,)
    loss_pp: Tensor  # (P,)


def _state(model: _Model, vals: dict[str, float], n: Tensor, problem: NormalProblem | None = None) -> _State:
    """The point (``vals``, ``n``); ``problem``: the tables of ``vals`` when already built."""
    problem = model.problem(model.tables(vals), vals) if problem is None else problem
    surf, body = render_parts(problem.tables, n, model.obs)
    r, k_b = problem.residual_of_parts(surf, body, model.obs)
    return _State(vals, problem, n, surf, body, r, k_b, problem.loss(r))


def _highlight_normals(obs: Observations) -> Tensor:
    """(P, 3) each pixel's specular candidate: the half vector of the view and the light that makes the
    pixel brightest relative to its irradiance (the normal that puts that light's mirror direction on the
    camera). Pixels with no usable observation get their view direction (an always-rejected candidate
    is harmless: see :func:`_try_highlights`)."""
    radiance = obs.stokes[..., 0] / obs.irradiance.clamp_min(1e-12)  # (P, K)
    radiance = torch.where(obs.weight > 0, radiance, torch.full_like(radiance, -math.inf))
    k = radiance.argmax(-1)  # (P,)
    light = obs.lights.gather(1, k[:, None, None].expand(-1, 1, 3))[:, 0]  # (P, 3)
    return unit(light.to(obs.view.dtype) + obs.view)


def _try_highlights(model: _Model, st: _State, cand: Tensor) -> tuple[_State, Tensor]:
    """Each pixel takes its highlight candidate ``cand`` (P, 3) when that lowers its loss under the
    current globals (a per-pixel move the local steps cannot make: under a narrow lobe a normal off by
    more than the lobe's width sees no gradient towards the highlight). Returns the state and the
    (P,) bool of the pixels that moved."""
    trial = _state(model, st.vals, cand.to(st.n.dtype), st.problem)
    take = ((trial.n * model.obs.view).sum(-1) > 0) & torch.isfinite(trial.loss_pp) & (trial.loss_pp < st.loss_pp)
    return _where(take, trial, st), take


def _where(take: Tensor, a: _State, b: _State) -> _State:
    """Per pixel ``a`` where ``take`` (P,) else ``b`` (same globals and tables)."""
    t1, t3 = take[:, None], take[:, None, None]
    return _State(a.vals, a.problem, torch.where(t1, a.n, b.n), torch.where(t3, a.surf, b.surf),
                  torch.where(t3, a.body, b.body), torch.where(t3, a.r, b.r), torch.where(take, a.k_b, b.k_b),
                  torch.where(take, a.loss_pp, b.loss_pp))


def _linear_optimum(model: _Model, st: _State, robust_weight: Tensor | None = None) -> _State:
    """``st`` with the linear globals (k_s; a global k_b) at their closed-form optimum (weighted by
    ``robust_weight`` (P, K, 3) when given), from its rendered parts: the albedos need no table build
    and no render."""
    k_s, k_b = solve_albedos(st.surf, st.body, model.obs, per_pixel=model.per_pixel, polarised=model.polarised,
                             robust_weight=robust_weight)
    if model.per_pixel:
        vals = {**st.vals, "k_s": float(k_s)}
    else:
        k_s_host, k_b_host = torch.stack([k_s.reshape(()), k_b[0]]).tolist()  # two numbers: one host sync
        vals = {**st.vals, "k_s": k_s_host, "k_b": k_b_host}
    problem = model.problem(st.problem.tables, vals)
    r, k_b_pp = problem.residual_of_parts(st.surf, st.body, model.obs)
    return _State(vals, problem, st.n, st.surf, st.body, r, k_b_pp, problem.loss(r))


def _start(model: _Model, vals: dict[str, float], n: Tensor) -> _State:
    """The point (``vals``, ``n``) with the linear globals (k_s; a global k_b) at their closed-form optimum."""
    return _linear_optimum(model, _state(model, vals, n))


def _project_linear(model: _Model, st: _State) -> _State:
    """The state with the linear globals (k_s; a global k_b) moved to their closed-form optimum under the
    current IRLS weights (variable projection), kept only where that lowers the loss.

    The LM step of a linear global is capped relative to its value (:func:`_max_step`): from the α grid's
    k_s = 0 start it grows only ×1.5 per iteration, and on the 256² α 0.03 spheres it took 17 of 20
    iterations to reach the k_s of the data. The closed form reuses the rendered parts (no table build,
    no render): one reduction per accepted step."""
    trial = _linear_optimum(model, st, irls_weights(st.problem, st.r))
    return trial if bool(trial.loss_pp.sum() < st.loss_pp.sum()) else st


def _jacobians(model: _Model, st: _State, step_h: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Forward-difference Jacobians of the flat residuals (P, M): normals (P, M, 2), globals (P, M, G),
    and the tangent basis (t1, t2) of the normal steps."""
    obs, p = model.obs, st.n.shape[0]
    r0 = st.r.reshape(p, -1)
    jn, t1, t2 = normal_jacobian(st.problem, st.n, r0, obs, step_h)
    cols = []
    if model.table_names:
        # coarse tables (``jac_grid``) on the base point's layout: cheap, and smooth in the parameter
        coarse = replace(model, n_grid=model.jac_grid)
        r_c = coarse.problem(coarse.tables(st.vals), st.vals).residual(st.n, obs)[0].reshape(p, -1)
        for name in model.table_names:
            h = _fd_step(name, st.vals[name])
            vals = {**st.vals, name: _from_u(name, _to_u(name, st.vals[name]) + h)}
            r_i = coarse.problem(coarse.tables(vals, layout_of=st.vals), vals).residual(st.n, obs)[0].reshape(p, -1)
            cols.append((r_i - r_c) / h)
    for name in model.linear_names:
        h = _fd_step(name, st.vals[name])
        vals = {**st.vals, name: st.vals[name] + h}
        r_i = model.problem(st.problem.tables, vals).residual_of_parts(st.surf, st.body, obs)[0].reshape(p, -1)
        cols.append((r_i - r0) / h)
    return jn, torch.stack(cols, -1), t1, t2


def _mean(loss_pp: Tensor, obs: Observations) -> Tensor:
    return loss_pp.sum() / obs.weight.sum().clamp_min(1.0)


def loss_floor(delta: float) -> float:
    """The loss scale below which relative changes no longer mean progress: a hundredth of δ² (the
    mean Huber loss of residuals a tenth of δ, far under the noise). Convergence tests take changes
    relative to max(loss, this): noise-free data would otherwise run to machine precision (30+
    κ-table iterations) or compare rounding noise (losses of 1e-34)."""
    return max(1e-2 * float(delta) ** 2, 1e-300)


def joint_solve(normals: Tensor, obs: Observations, params: FMBRDFParams, *, names: tuple[str, ...] | list[str],
                per_pixel_albedo: bool = True, polarised: bool = True, delta: float = 0.01, max_iter: int = 20,
                tol: float = 1e-5, step_h: float = 2e-3, max_step: float = 0.25, n_grid: int = 65,
                jac_grid: int = 33, stop: Callable[[float, list[dict]], bool] | None = None) -> JointResult:
    """Normals and material by one Levenberg–Marquardt with the Schur complement (module docstring).

    Args:
        normals: (P, 3) unit start normals, camera frame. obs: the P pixels' observations.
        params: the start material (its k_s starts the linear search; κ is kept unless fitted).
        names: the table parameters to fit (of :data:`TABLE_PARAMS`); k_s is always fitted, and one
            global k_b when not ``per_pixel_albedo``.
        per_pixel_albedo: k_b per pixel in closed form (else one global k_b, fitted).
        polarised: fit s1, s2 too (else intensity only).
        delta: Huber threshold on the channel-weighted Stokes residual.
        max_iter: most LM iterations. tol: relative loss change that ends the solve.
        step_h: normal forward-difference step; max_step: largest normal step (tangent units).
        n_grid: body-table grid of the loss; jac_grid: the (coarser, cheaper) one of the globals' Jacobian.
        stop: called after each iteration with the initial loss and the history so far; True ends the
            solve (a caller's test that is already decided, :func:`nested_kappa`).

    Returns:
        :class:`JointResult`.
    """
    t0 = time.perf_counter()
    unknown = [n for n in names if n not in TABLE_PARAMS]
    if unknown:
        raise ValueError(f"joint_solve names must be among {TABLE_PARAMS}; got {unknown}")
    model = _Model(obs, tuple(n for n in TABLE_PARAMS if n in names), ("k_s",) if per_pixel_albedo else ("k_s", "k_b"),
                   per_pixel_albedo, polarised, float(delta), n_grid, jac_grid)
    fitted = model.table_names + model.linear_names
    dev, p = normals.device, normals.shape[0]
    history: list[dict] = []
    with torch.no_grad():
        vals0 = {k: float(getattr(params, k)) for k in (*TABLE_PARAMS, "k_s", "k_b")}
        st = _start(model, vals0, unit(normals))
        initial, initial_pp = float(_mean(st.loss_pp, obs)), st.loss_pp
        cand = _highlight_normals(obs)
        st, _ = _try_highlights(model, st, cand)
        total = float(_mean(st.loss_pp, obs))
        floor = loss_floor(delta)
        lam_g = 1e-3
        lam_n = torch.full((p,), 1e-3, dtype=torch.float64, device=dev)
        rel, it = 0.0, 0
        for it in range(1, max_iter + 1):
            jn, jg, t1, t2 = _jacobians(model, st, step_h)
            r0 = st.r.reshape(p, -1).double()
            w = irls_weights(st.problem, r0)  # (P, M)
            jn, jg = jn.double(), jg.double()
            jnw, jgw = jn * w.unsqueeze(-1), jg * w.unsqueeze(-1)
            h_nn, h_ng = jnw.transpose(1, 2) @ jn, jnw.transpose(1, 2) @ jg  # (P, 2, 2), (P, 2, G)
            h_gg = torch.einsum("pmi,pmj->ij", jgw, jg)
            b_n, b_g = (jnw * r0.unsqueeze(-1)).sum(1), (jgw * r0.unsqueeze(-1)).sum((0, 1))
            rel, accepted, moved = 0.0, False, 0.0
            attempts, pinned_names, rhos, n_jumped = 0, [], [], 0.0
            for _attempt in range(6):
                attempts += 1
                dn, dg = schur_step(h_nn, h_ng, h_gg, b_n, b_g, lam_n, lam_g)
                dg_host = dg.tolist()  # the tables are built from the globals: G numbers to the host
                pinned = _pinned(fitted, st.vals, dg_host)
                if pinned:  # a global at its bound pushed outward: solve again with it held
                    h_ng_p, h_gg_p, b_g_p = _hold(pinned, h_ng, h_gg, b_g)
                    dn, dg = schur_step(h_nn, h_ng_p, h_gg_p, b_n, b_g_p, lam_n, lam_g)
                    dg_host = dg.tolist()
                dn = dn * (max_step / dn.norm(dim=-1).clamp_min(max_step)).unsqueeze(-1)
                vals = dict(st.vals)
                for name, d in zip(fitted, dg_host):
                    lim = _max_step(name, st.vals[name])
                    vals[name] = _from_u(name, _to_u(name, st.vals[name]) + max(min(d, lim), -lim))
                # the Gauss–Newton model's predicted loss decrease of the step as taken (clipped, bounded)
                dg_taken = [_to_u(k, vals[k]) - _to_u(k, st.vals[k]) for k in fitted]
                dgt = torch.tensor(dg_taken, dtype=h_gg.dtype, device=dev)
                pred = -((b_n * dn).sum() + b_g @ dgt + 0.5 * (
                    (dn.unsqueeze(1) @ h_nn @ dn.unsqueeze(-1)).sum() + 2 * (dn.unsqueeze(1) @ h_ng @ dgt).sum()
                    + dgt @ h_gg @ dgt))
                dn = dn.to(st.n.dtype)
                n_new = unit(st.n + dn[:, :1] * t1 + dn[:, 1:] * t2)
                trial_new = _state(model, vals, n_new)
                trial_old = _state(model, vals, st.n, trial_new.problem)  # the same tables: one build
                keep_new = ((n_new * obs.view).sum(-1) > 0) & torch.isfinite(trial_new.loss_pp) & (
                    trial_new.loss_pp < trial_old.loss_pp)
                loss_pp = torch.where(keep_new, trial_new.loss_pp, trial_old.loss_pp)
                # the one convergence / acceptance check (with the share of pixels that took their step)
                total_t, moved_t, pred_mean = torch.stack([_mean(loss_pp, obs).double(), keep_new.double().mean(),
                                                           _mean(pred, obs).double()]).tolist()
                better = keep_new | (trial_new.loss_pp < st.loss_pp)
                # the gain ratio ρ: actual / predicted decrease (None where the model predicted none)
                ok = pred_mean > 0 and math.isfinite(total_t)
                rhos.append(round((total - total_t) / pred_mean, 3) if ok else None)
                if math.isfinite(total_t) and total_t < total:
                    rel = (total - total_t) / max(total, floor)
                    st = _where(keep_new, trial_new, trial_old)
                    total, accepted = total_t, True
                    moved = moved_t
                    pinned_names = [fitted[i] for i in pinned]
                    lam_g = max(lam_g / 3, 1e-7)
                    lam_n = torch.where(keep_new, (lam_n / 3).clamp_min(1e-7), (lam_n * 4).clamp_max(1e7))
                    st = _project_linear(model, st)
                    st, jumped = _try_highlights(model, st, cand)
                    lam_n = torch.where(jumped, torch.full_like(lam_n, 1e-3), lam_n)
                    total_j, n_jumped = torch.stack([_mean(st.loss_pp, obs).double(), jumped.double().sum()]).tolist()
                    rel = (total - total_j) / max(total, floor) + rel
                    total = total_j
                    break
                lam_g = min(lam_g * 10, 1e10)
                lam_n = torch.where(better, lam_n, (lam_n * 4).clamp_max(1e7))
            history.append({"iteration": it, "loss": total, "rel_change": rel, "lambda": lam_g,
                            "accepted": accepted, "moved": moved, "attempts": attempts, "rho": rhos,
                            "step": dg_taken if accepted else [], "pinned": pinned_names, "jumped": int(n_jumped),
                            "seconds": time.perf_counter() - t0,
                            **{k: st.vals[k] for k in fitted}})
            logger.debug("joint %d: loss %.6g (rel %.2e) %s", it, total, rel, {k: st.vals[k] for k in fitted})
            if not accepted or rel < tol or (stop is not None and stop(initial, history)):
                break
    k_b = st.k_b
    out = FMBRDFParams(**{k: st.vals[k] for k in (*TABLE_PARAMS, "k_s", "k_b")})
    if per_pixel_albedo:
        pos = k_b > 0
        out.k_b = float(k_b[pos].median()) if bool(pos.any()) else 0.0
    return JointResult(out, st.n, k_b, total, initial, it, rel, rel < tol, history, time.perf_counter() - t0,
                       unit(normals), replace(params), st.loss_pp, initial_pp)


def clearly_below(target: float, floor: float, reference: float | None = None) -> Callable[[float, list[dict]], bool]:
    """A :func:`joint_solve` ``stop`` test: True once the solve's relative gain over ``reference`` (default:
    its initial loss; relative to max(reference, ``floor``)) will clearly end below ``target``. From the
    third iteration on, with the last two relative changes c₋₁, c (geometric rate ρ = c / c₋₁ < ½), the
    rest of the descent is at most c·ρ / (1 − ρ) of the current loss; stop when the gain so far plus twice
    that is below ``target``. (Not earlier, and not on a small gain alone: a solve stopped under
    :func:`nested_kappa`'s ``min_gain`` would count as stuck and start again from the κ = 0 solve's start —
    on the 40² α 0.03 spheres that cost 39–42 table builds instead of 12–21.) With a ``reference`` the
    solve may still be above it (:func:`nested_kappa`'s second start: its gain is over the κ = 0 optimum,
    not over its own start), so the rest of the descent is scaled by the current loss over the reference
    when that exceeds 1."""

    def stop(initial: float, history: list[dict]) -> bool:
        if len(history) < 3:
            return False
        prev, last = history[-2]["rel_change"], history[-1]["rel_change"]
        if not (0.0 < last < 0.5 * prev):
            return False
        rho = last / prev
        ref = initial if reference is None else reference
        loss, scale = history[-1]["loss"], max(ref, floor)
        rest = 2.0 * last * rho / (1.0 - rho) * max(1.0, max(loss, floor) / scale)  # 1 without a reference
        return (ref - loss) / scale + rest < target

    return stop


def settled(tol: float, rate: float) -> Callable[[float, list[dict]], bool]:
    """A :func:`joint_solve` ``stop`` test: True once the last iteration's relative loss change c is
    below ``tol`` and below ``rate`` × the change c₋₁ before it (a fast rate ρ = c / c₋₁: the rest of
    the descent is at most c·ρ / (1 − ρ)). A solve that crawls (ρ near 1) runs on to its own ``tol``.
    After one iteration (no rate yet) only a change below ``rate`` × ``tol`` stops it: a solve that
    started where it had settled (a polish from the optimum of a test on coarser tables: on the 256²
    α 0.3 κ 50 spheres its first iteration changes the loss by 2e-5 and κ by 0.03, its second by 1e-6)."""

    def stop(initial: float, history: list[dict]) -> bool:
        last = history[-1]["rel_change"]
        if len(history) < 2:
            return 0.0 <= last < rate * tol
        prev = history[-2]["rel_change"]
        return 0.0 <= last < tol and last < rate * prev

    return stop


def first_of(*tests: Callable[[float, list[dict]], bool]) -> Callable[[float, list[dict]], bool]:
    """A :func:`joint_solve` ``stop`` test: True once any of ``tests`` is (e.g. :func:`settled` or
    :func:`clearly_below`)."""

    def stop(initial: float, history: list[dict]) -> bool:
        return any(test(initial, history) for test in tests)

    return stop


def nested_kappa(start: JointResult, obs: Observations, *, fresh_max_iter: int = 6, min_gain: float = 0.01,
                 corner_ratio: float = 2.0, decide_gain: float | None = None,
                 **kwargs: object) -> tuple[JointResult, float]:
    """Add κ to a κ = 0 optimum: the joint solve from ``start`` (its normals and material, κ = 0)
    with κ among the fitted names; the loss can only fall from the start (module docstring).

    The κ = 0 optimum need not be a point from which κ can grow: on a κ = 50 matte sphere the κ = 0
    model explains the body's correlation with a narrow lobe (α at its bound 0.01, β at 6; on the
    blob α 0.07) and the κ solve from there stays at κ = 0 (gain 0.01 %), while from the κ = 0
    solve's own start it finds κ 17–24 and 2–6 × lower loss. So when the κ solve from the optimum
    gains less than ``min_gain`` or ends with κ < 1, and the κ = 0 solve ended far from its start
    (α or β changed by a factor ≥ ``corner_ratio``: on those corners by 11–80 in α; on κ-free data
    the lobe moves little from the α grid's start, and the second solve would only find the optimum
    again), it runs again from ``start.start_normals``, ``start.start_params`` (κ = 0) and the lower
    is returned — never above the κ = 0 optimum's loss, so still a nested fit. The second solve runs
    at most ``fresh_max_iter`` iterations (a test: a kept κ is polished anyway; on the 40² α 0.8
    κ 50 sphere and blob κ was 4.8 and 15.9 after 3 with κ searched in κ itself; searched in log(1 + κ/5)
    the 256² α 0.8 κ 50 spheres reach κ 37–49 in the 6).

    Args:
        start: the κ = 0 solve. obs: its observations. fresh_max_iter: the most iterations from
            ``start``'s own start. min_gain: the relative gain from the optimum (with κ ≥ 1) that makes
            the second start unnecessary. corner_ratio: how far (a factor in α or β) the κ = 0 solve must have
            moved from its start for the second start. decide_gain: the gain a caller's decision needs; the
            solve from the optimum, and the second start, stop once their gain over the κ = 0 optimum
            clearly ends below it (:func:`clearly_below`: a test, not a fit). kwargs: :func:`joint_solve`'s
            keywords (``names`` gets ``kappa`` added).

    Returns:
        The κ solve (its ``initial_loss`` and ``initial_pixel_loss``: the κ = 0 optimum's, on the κ
        solve's tables) and its relative gain (κ = 0 optimum's loss − final loss) / max(that loss,
        :func:`loss_floor`) ≥ 0 (noise-free κ-free data: losses of 1e-34 compare rounding, the floor
        makes that gain 0).
    """
    base = tuple(kwargs.pop("names", ()))  # type: ignore[arg-type]
    names = base + ("kappa",)
    floor = loss_floor(float(kwargs.get("delta", 0.01)))  # type: ignore[arg-type]
    stop = None if decide_gain is None else clearly_below(decide_gain, floor)
    fit = joint_solve(start.normals, obs, replace(start.params, kappa=0.0), names=names, stop=stop,
                      **kwargs)  # type: ignore[arg-type]
    ref = fit.initial_loss  # the κ = 0 optimum on these tables
    stuck = (ref - fit.loss) < min_gain * max(ref, floor) or fit.params.kappa < 1.0  # κ did not grow, or did not pay
    s0 = start.start_params
    # a corner: the κ = 0 solve moved the lobe far (×2 or more in α or β) from where it started
    cornered = s0 is not None and any(abs(math.log(getattr(start.params, n) / max(getattr(s0, n), 1e-12))) >=
                                      math.log(corner_ratio) for n in ("alpha", "beta"))
    if start.start_normals is not None and s0 is not None and stuck and cornered:
        # a test, not the final fit (a kept κ is polished by the caller): a few iterations show a gain
        most = min(int(kwargs.get("max_iter", 20)), fresh_max_iter)  # type: ignore[call-overload]
        fresh_kw = {**kwargs, "max_iter": most}
        # stopped once its gain over the κ = 0 optimum clearly ends below the decision's (on the 256² α 0.03
        # spheres it stays above the optimum's loss: 4 iterations instead of 6)
        fresh_stop = None if decide_gain is None else clearly_below(decide_gain, floor, reference=ref)
        fresh = joint_solve(start.start_normals, obs, replace(s0, kappa=0.0), names=names, stop=fresh_stop,
                            **fresh_kw)  # type: ignore[arg-type]
        logger.info("nested κ: from the κ = 0 optimum loss %.6g (κ %.3g), from its start %.6g (κ %.3g)", fit.loss,
                    fit.params.kappa, fresh.loss, fresh.params.kappa)
        if fresh.loss < fit.loss:
            fit = replace(fresh, initial_loss=ref, initial_pixel_loss=fit.initial_pixel_loss)
    gain = (ref - fit.loss) / max(ref, floor)
    return fit, max(gain, 0.0)


def trimmed_gain(base_loss: Tensor, trial_loss: Tensor, trim: float = 0.02, floor: float = 0.0) -> float:
    """Relative loss gain of a trial fit over a base fit on the same pixels, without the pixels that
    gained most: Σ' (base − trial) / Σ' base over all but the ``ceil(trim · P)`` (at least one) pixels
    with the largest gain base − trial.

    A parameter the data need lowers the loss broadly; one that trades against another on a few
    pixels (κ against α on the two highlight pixels of a 40² α 0.03 sphere) gains there only, and
    its gain vanishes (or turns negative) once they are left out.

    Args:
        base_loss, trial_loss: (P,) per-pixel losses (:attr:`JointResult.pixel_loss`) of the two fits.
        trim: share of the pixels left out.
        floor: least denominator, in the units of the summed losses (a caller's :func:`loss_floor` × the
            observation weight: on noise-free data Σ' base is rounding noise, 1e-34).

    Returns:
        The trimmed relative gain (negative where the trial fits the rest worse).
    """
    d = base_loss - trial_loss  # (P,)
    k = min(max(1, math.ceil(trim * d.numel())), d.numel() - 1)
    keep = torch.ones_like(d, dtype=torch.bool)
    if k > 0:
        keep[d.topk(k).indices] = False
    return float(d[keep].sum() / base_loss[keep].sum().clamp_min(max(floor, 1e-300)))
