"""The FMBRDF solve: material and normals alternated on an image pyramid, coarsest level first.

On a pyramid (2×2 averaging, :func:`polarshape.recover.observations.downsample_inputs`) whose
coarsest level holds at most ``4 · subsample_pixels`` pixels, the coarsest level alternates

a. *global parameters* (μ, α, β, [κ]; k_s and per-pixel k_b in closed form) on a random subsample
   of ``subsample_pixels`` pixels (:func:`polarshape.recover.reflectometry.fit_reflectance`);
b. *normals*: per-pixel Levenberg–Marquardt (:func:`polarshape.recover.normal_solver.refine_normals`),
   then neighbour propagation (:func:`polarshape.recover.normal_solver.propagate_normals`).

From the third outer iteration on, when the material moved the same way in the last two (a crawl:
shiny lobes, α against the normals under the highlight), the state is over-relaxed along its last
change — material and normals 4× or 2× that change further — and kept only where that lowers the
level's loss (:func:`_extrapolate`; the fixed point and the test below are unchanged).
The alternation stops when the loss changed by ≤ 0.1 % over the last two outer iterations (a
window, not one step) or after ``max_outer_iterations``. Finer levels start from the coarser normals
upsampled bilinearly (:func:`upsample_normals`) and run step b only. With ``fit_kappa`` None, κ is
tested once the coarse level has converged, as a nested fit from that κ = 0 optimum
(:func:`_kappa_decision`, shared with the joint solve below: it cannot raise the loss); kept only if
it lowers the loss by ≥ 25 % on all pixels and by ≥ 1 % without the 2 % that gain most
(:data:`KAPPA_KEEP_GAIN`; else κ = 0, the separable fast path, and the skip recorded). A kept
κ ends the level's alternation: the nested fit moved material and subsample normals together, and
the level's normals then follow the final material once.

A known material (``recovery.material``, :class:`KnownMaterial`) changes step a. ``fixed``: μ, α, β,
κ stay the material's and step a only solves the albedos in closed form on the subsample — no
non-linear search, no κ test, one table build per outer iteration instead of a fit's dozens.
Albedos are in the capture's units (fraction of full scale per unit light intensity) and scale
with the exposure, gain and light power of the rig, so they are not carried over: with per-pixel
k_b, k_s (the rig's scale of the surface term) is solved with the k_b map; with one global k_b, one
scale c of the material's (k_s, k_b) is solved, which keeps its ratio r_k = k_b/k_s (a property of
the material). ``initial``: the material starts the fit — the first outer iteration solves the
albedos only (the normals move to the material first), the later ones fit μ, α, β (and κ when the
material has κ > 0, unless ``fit_kappa`` says otherwise) without the α grid that starts an
unknown material.

``recovery.solver: joint`` replaces the alternation on the coarsest level (an unknown or initial
material): after the first outer iteration (the α grid, the normals of the whole level) normals and
material of the subsample move together in one Levenberg–Marquardt with the Schur complement of
the per-pixel blocks (:func:`polarshape.recover.joint_solve.joint_solve`); κ is then a nested fit
from that κ = 0 optimum (:func:`_kappa_decision`, as above); the level's normals are then refined
for the final material. Finer levels are as above.

Robust loss: Huber on channel-weighted Stokes residuals, δ = 3 × the robust (MAD) residual σ of the
initial fit, floored at 4 quantisation steps (:func:`polarshape.recover.normal_solver.huber_delta`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm.auto import tqdm

from polarshape.brdf.cache import BoundedCache
from polarshape.brdf.fmbrdf import FMBRDFTables, build_tables
from polarshape.brdf.params import FMBRDFParams
from polarshape.recover.joint_solve import (
    JointResult, clearly_below, first_of, joint_solve, loss_floor, nested_kappa, settled, trimmed_gain,
)
from polarshape.recover.normal_solver import (
    NormalProblem, huber_delta, neighbour_index, propagate_normals, refine_normals, unit,
)
from polarshape.recover.observations import Observations, RecoveryInputs, downsample_inputs, flatten_observations
from polarshape.recover.options import RecoveryOptions
from polarshape.recover.reflectometry import (
    ALPHA_GRID, BOUNDS, channel_weights, fit_reflectance, render_parts, solve_albedos,
)

logger = logging.getLogger(__name__)

__all__ = [
    "FMBRDFState", "KnownMaterial", "SolveLog", "TableCache", "build_pyramid", "fit_albedo_scale", "fit_level",
    "profile_alpha", "solve_fmbrdf", "upsample_normals",
]


@dataclass
class SolveLog:
    """What a solve reports besides its result: per-iteration records, seconds per step, what it
    skipped, and how much work the material took (``counts``: ``material_fits`` — calls of the
    non-linear global fit, ``material_fit_iterations`` — their LM iterations, ``kappa_probes``,
    ``albedo_solves`` — closed-form albedo steps of a fixed or initial material)."""

    history: list[dict] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    t_start: float = field(default_factory=time.perf_counter)

    def add_time(self, name: str, since: float) -> None:
        """Add the seconds since ``since`` (a ``time.perf_counter()`` value) to ``timings[name]``."""
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - since

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to ``counts[name]``."""
        self.counts[name] = self.counts.get(name, 0) + n


#: Most materials' tables a :class:`TableCache` keeps (a κ > 0 table at ``n_grid`` 65 is ~26 MB, a
#: κ = 0 one 0.2 MB): a split of the model choice scores the material it splits and six new ones.
TABLE_CACHE_SIZE = 12


class TableCache:
    """The fast evaluator's tables of the materials one run has built, for the steps that need the
    same material again (the finer levels, the materials selection, the final render all use the
    final material's): keyed on the exact (μ, α, β, κ, ``n_grid``, device) — a table is a
    deterministic function of these, so a hit is the build it replaces, bit for bit. Bounded: the
    :data:`TABLE_CACHE_SIZE` most recently used are kept. Passed explicitly (no module state): a run
    makes one and hands it to the steps that share it.

    Attributes:
        builds: tables built. hits: tables handed back without a build.
    """

    def __init__(self, most: int = TABLE_CACHE_SIZE) -> None:
        if most < 1:
            raise ValueError(f"TableCache: most must be ≥ 1 (got {most})")
        self.most = most
        self.builds = 0
        self.hits = 0
        self._tables: BoundedCache[FMBRDFTables] = BoundedCache(most)

    def __len__(self) -> int:
        return len(self._tables)

    def get(self, params: FMBRDFParams, device: torch.device | str, n_grid: int = 65) -> FMBRDFTables:
        """The tables of ``params``' (μ, α, β, κ) at ``n_grid`` on ``device`` (built on a miss:
        :meth:`FMBRDFParams.build_tables`; the albedos k_s, k_b are not part of a table)."""
        key = (float(params.ior), float(params.alpha), float(params.beta), float(params.kappa), int(n_grid),
               str(torch.device(device)))
        tables = self._tables.get(key)
        if tables is not None:
            self.hits += 1
            return tables
        self.builds += 1
        return self._tables.put(key, params.build_tables(device=device, n_grid=n_grid))


@dataclass(frozen=True)
class KnownMaterial:
    """A material given to the solve (``recovery.material``, module docstring).

    Attributes:
        params: the material (μ, α, β, κ, and the k_s, k_b it was measured with).
        use: ``fixed`` (μ, α, β, κ kept; albedos solved) or ``initial`` (the fit starts from it).
    """

    params: FMBRDFParams
    use: Literal["fixed", "initial"] = "fixed"


@dataclass(frozen=True)
class FMBRDFState:
    """A solution on one grid: the material, normals (H, W, 3) (NaN outside the mask), k_b (H, W)."""

    params: FMBRDFParams
    normals: Tensor
    k_b: Tensor


def _subsample(p: int, n: int, seed: int, device: torch.device) -> Tensor:
    if p <= n:
        return torch.arange(p, device=device)
    gen = torch.Generator().manual_seed(seed)
    return torch.randperm(p, generator=gen)[:n].sort().values.to(device)


def profile_alpha(normals: Tensor, obs: Observations, params: FMBRDFParams, per_pixel: bool, delta: float) -> FMBRDFParams:
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
        problem = NormalProblem.build(tables, obs.stokes, float(k_s), per_pixel, float(k_b.median()), False, delta)
        _, _, loss, _ = refine_normals(problem, normals, obs, max_iter=4)
        total = float(loss.sum())
        if total < best[0]:
            best = (total, a)
    logger.info("intensity-only: α %.3g from the profiled grid", best[1])
    return FMBRDFParams(**{**vars(params), "alpha": best[1]})


def fit_albedo_scale(normals: Tensor, obs: Observations, params: FMBRDFParams, *, per_pixel_albedo: bool,
                     polarised: bool, tables: FMBRDFTables | None = None) -> FMBRDFParams:
    """The albedos of a known material (μ, α, β, κ kept) for fixed normals, in closed form.

    Per-pixel k_b: weighted least-squares k_s and k_b (P,) (:func:`solve_albedos`); the returned
    ``k_b`` is their median over the pixels with k_b > 0. One global k_b: one scale c ≥ 0 of the
    material's (k_s, k_b), so that r_k = k_b/k_s is kept: c = Σ w m o / Σ w m m with
    m = k_s·S_surf + k_b·S_body (channel-weighted, spec §8's model of observation).

    Args:
        normals: (P, 3) unit normals, camera frame. obs: the P pixels' observations.
        params: the material. per_pixel_albedo, polarised: as for :func:`fit_reflectance`.
        tables: ``params.build_tables()`` when the caller has them.

    Returns:
        ``params`` with the solved k_s and k_b.
    """
    with torch.no_grad():
        tables = params.build_tables(device=normals.device) if tables is None else tables
        surf, body = render_parts(tables, normals, obs)  # (P, K, 3) each
        if per_pixel_albedo:
            k_s, k_b = solve_albedos(surf, body, obs, per_pixel=True, polarised=polarised)
            k_b_med = float(k_b[k_b > 0].median()) if bool((k_b > 0).any()) else 0.0
            return replace(params, k_s=float(k_s), k_b=k_b_med)
        model = params.k_s * surf + params.k_b * body  # (P, K, 3)
        w = obs.weight.unsqueeze(-1) * channel_weights(surf, polarised)  # (P, K, 3)
        den = float((w * model * model).sum())
        c = max(float((w * model * obs.stokes).sum()) / den, 0.0) if den > 0 else 1.0
    return replace(params, k_s=c * params.k_s, k_b=c * params.k_b)


def _global_step(n_sub: Tensor, obs_sub: Observations, params: FMBRDFParams, options: RecoveryOptions, *, it: int,
                 fit_kappa: bool, polarised: bool, delta: float, use: Literal["fit", "fixed", "initial"],
                 log: SolveLog) -> FMBRDFParams:
    """Step a: the material on the subsample, for fixed normals (schedule by outer iteration ``it``;
    ``use``: an unknown material, a fixed one or an initial one, module docstring)."""
    if use == "fixed" or (use == "initial" and it == 0):
        log.count("albedo_solves")
        return fit_albedo_scale(n_sub, obs_sub, params, per_pixel_albedo=options.per_pixel_albedo, polarised=polarised)
    if use == "initial":  # a known start: no α grid, no staged lobe-first schedule
        grid, max_iter, fit_names = False, 4 if it == 1 else 2, None
    else:
        grid = it == 0  # the coarse α grid starts the first fit only
        if grid and not polarised:
            params = profile_alpha(n_sub, obs_sub, params, options.per_pixel_albedo, delta)
            grid = False
        max_iter = 12 if it == 0 else 4 if it == 1 else 2
        # the initial (Lambertian) normals are biased by highlights: fit the lobe width first,
        # free μ and β once the normals have moved to the model
        fit_names = ("alpha",) if it == 0 else ("alpha", "beta") if it == 1 else None
    fit = fit_reflectance(
        n_sub, obs_sub, init=params, per_pixel_albedo=options.per_pixel_albedo, fit_kappa=fit_kappa,
        polarised=polarised, delta=delta, grid_search=grid, max_iter=max_iter, fit_names=fit_names,
    )
    log.count("material_fits")
    log.count("material_fit_iterations", sum(1 for h in fit.history if h.get("stage") == "lm"))
    return fit.params


@dataclass
class _Level:
    """The working state of :func:`fit_level` on one pyramid level."""

    pixels: Tensor  # (H, W) bool
    obs: Observations
    n: Tensor  # (P, 3)
    k_b: Tensor  # (P,)
    params: FMBRDFParams
    delta: float
    neighbours: Tensor | None


def _level_problem(lv: _Level, params: FMBRDFParams, options: RecoveryOptions, polarised: bool,
                   tables: TableCache | None = None) -> NormalProblem:
    """The per-pixel normal problem of the level's observations under material ``params`` (its tables
    built, or taken from ``tables`` when the run already built them)."""
    built = params.build_tables(device=lv.n.device) if tables is None else tables.get(params, lv.n.device)
    return NormalProblem.build(built, lv.obs.stokes, params.k_s,
                               options.per_pixel_albedo, params.k_b, polarised, lv.delta)


def _normal_step(lv: _Level, options: RecoveryOptions, polarised: bool, *, max_iter: int, level: int, it: int,
                 tables: TableCache | None = None) -> tuple[NormalProblem, Tensor, int]:
    """Step b: per-pixel normals for the level's material (updates ``lv.n``, ``lv.k_b``); returns the
    problem, the per-pixel loss and the LM iterations. ``tables``: the run's tables (:class:`TableCache`)."""
    problem = _level_problem(lv, lv.params, options, polarised, tables)
    lv.n, lv.k_b, loss_pp, n_iter = refine_normals(problem, lv.n, lv.obs, max_iter=max_iter)
    if lv.neighbours is not None:
        lv.n, lv.k_b, loss_pp, moved = propagate_normals(problem, lv.n, lv.k_b, loss_pp, lv.obs, lv.neighbours)
        if moved:
            logger.info("level %d outer %d: %d pixels took a neighbour's normal", level, it, moved)
    return problem, loss_pp, n_iter


def _mean_loss(loss_pp: Tensor, obs: Observations) -> float:
    return float(loss_pp.sum() / obs.weight.sum().clamp_min(1.0))


#: Material parameters the alternation extrapolates (:func:`_extrapolate`), each with its coordinate:
#: log for the positive scale parameters, the value itself for μ (κ only when it is fitted).
_EXTRAPOLATED: tuple[tuple[str, bool], ...] = (("ior", False), ("alpha", True), ("beta", True), ("k_s", True),
                                               ("kappa", False))
#: Extrapolation lengths tried, in units of the last outer iteration's change (longest first).
EXTRAPOLATION_STEPS: tuple[float, ...] = (4.0, 2.0)
#: The last two outer iterations' material changes must point this much the same way (cosine)
#: for an extrapolation to be tried: a crawl, not an oscillation.
EXTRAPOLATION_MIN_COSINE = 0.9


def _material_coords(params: FMBRDFParams, kappa: bool) -> list[float]:
    """The coordinates of :data:`_EXTRAPOLATED` (κ only when ``kappa``)."""
    return [math.log(max(getattr(params, n), 1e-12)) if log else getattr(params, n)
            for n, log in _EXTRAPOLATED if n != "kappa" or kappa]


def _extrapolate(lv: _Level, previous: tuple[Tensor, FMBRDFParams], direction: list[float], loss_pp: Tensor,
                 options: RecoveryOptions, polarised: bool, kappa: bool, log: SolveLog,
                 tables: TableCache | None = None) -> tuple[Tensor, float] | None:
    """Over-relax a crawling alternation (updates ``lv`` and returns its per-pixel loss and the step
    taken, or None when no step lowers the loss).

    Where material and normals are correlated (a shiny lobe: α against the normals under the
    highlight) each outer iteration moves both a little in the same direction (measured: α
    0.141 → 0.111 over 17 iterations at 1–2 % each, the loss still falling). From the current
    state x_k and the previous one x_{k−1} (``previous``: the level's normals and material),
    x_k + t·(x_k − x_{k−1}) is evaluated for t in :data:`EXTRAPOLATION_STEPS` — the material in the
    coordinates of :data:`_EXTRAPOLATED`, clamped to the fit's bounds, each pixel's normal along
    its own chord — and the first that lowers the level's loss is taken (one table build and one
    residual evaluation of the level per t). The alternation then goes on from there: its fixed
    point and its convergence test are unchanged; a rejected try costs only its evaluation."""
    t0 = time.perf_counter()
    names = [n for n, _ in _EXTRAPOLATED if n != "kappa" or kappa]
    logs = dict(_EXTRAPOLATED)
    here = _material_coords(lv.params, kappa)
    base = float(loss_pp.sum())
    n_prev, _ = previous
    try:
        for t in EXTRAPOLATION_STEPS:
            values = {}
            for n, x, d in zip(names, here, direction):
                v = math.exp(x + t * d) if logs[n] else x + t * d
                lo, hi = BOUNDS.get(n, (0.0, math.inf))
                values[n] = min(max(v, lo), hi)
            trial = replace(lv.params, **values)
            normals = unit(lv.n + t * (lv.n - n_prev))
            facing = (normals * lv.obs.view).sum(-1) > 0
            normals = torch.where(facing.unsqueeze(-1), normals, lv.n)
            problem = _level_problem(lv, trial, options, polarised, tables)  # if taken: the next normal step's
            with torch.no_grad():
                r, k_b = problem.residual(normals, lv.obs)
                trial_pp = problem.loss(r)
            log.count("extrapolations_tried")
            if float(trial_pp.sum()) < base:
                log.count("extrapolations_taken")
                lv.params, lv.n, lv.k_b = trial, normals, k_b
                return trial_pp, t
        return None
    finally:
        log.add_time("extrapolation", t0)


#: Smallest relative loss gain on all but the 2 % of pixels that gain most that keeps κ > 0
#: (:func:`polarshape.recover.joint_solve.trimmed_gain`: a κ that only trades with α on a few
#: highlight pixels is dropped).
KAPPA_MIN_GAIN = 0.01
#: Smallest relative loss gain on all pixels that keeps κ > 0. The loss cannot tell correlation
#: from model mismatch: on the Baek-model Mitsuba capture (``../shared/data/mitsuba_sphere_a020``,
#: κ undefined) the nested fit gains 14.9 % with κ 67 and the normals get worse (0.36° → 1.32°); on
#: the 64² sphere rendered with the Baek pBRDF, Beckmann lobe (``tests/test_normals.py``), 20.5 % with
#: κ 45 (0.52° → 1.77°); while true κ 50 gains 30–78 % on the 40² sphere (α 0.3, 0.8) and blob (α 0.8)
#: but 7.3 % on the α 0.3 blob. 25 % keeps κ where it dominates the fit and never on the mismatch
#: measured — a thin margin on both sides: the loss alone cannot decide κ. Held-out data do not decide
#: it either (the κ fit on half the lights or half the pixels, its loss on the other half against the
#: κ = 0 fit's on the same half, 2 folds): the mismatch's κ predicts unseen lights and pixels as well
#: as it fits the seen ones — held-out lights: Baek Beckmann 22.5 %, GGX 17.1 %, Mitsuba 6.1 %, true κ 50
#: α 0.3 blob 3.1 % (sphere α 0.3 36 %, blob α 0.8 73 %); held-out pixels: Baek Beckmann 20.3 %, α 0.3
#: blob 8.4 % (``benchmarks/kappa_heldout.py``).
KAPPA_KEEP_GAIN = 0.25
#: Body-table grids (θ_V, θ_L) of the κ test: its loss (the full tables' is 65) and the Jacobians of the
#: test and of the polish. Grid 17 for the loss too measured 0.4–0.6 points more gain on the mismatch
#: cases (Baek Beckmann 20.9 %: the coarse tables' own error, which κ absorbs), 0.15 % instead of 0.01 %
#: on the κ-free 256² sphere (a second iteration) and 10.5 % on a noise-free κ-free sphere.
KAPPA_TEST_GRID = 33
KAPPA_JAC_GRID = 17
#: A kept κ's polish on full tables ends once an iteration changed the loss by < KAPPA_POLISH_TOL
#: (the alternation's own convergence test, 0.1 %) and by < KAPPA_POLISH_RATE × the change before
#: (a fast rate: the rest of the descent is ≤ 1.1e-4 of the loss), or once its first iteration changed it
#: by < KAPPA_POLISH_RATE × KAPPA_POLISH_TOL (the test had settled on its tables: 256² α 0.3 κ 50, 2e-5),
#: else at 1e-5 as before; its last full-table iterations moved κ by < 0.2 % on the 256² κ 50 spheres and
#: cost 1–1.5 s each.
KAPPA_POLISH_TOL = 1e-3
KAPPA_POLISH_RATE = 0.1


def _table_names(polarised: bool) -> tuple[str, ...]:
    """The table parameters fitted besides κ: μ only with polarisation."""
    return tuple(n for n in ("ior", "alpha", "beta") if polarised or n != "ior")


def _kappa_decision(fit: JointResult, obs_sub: Observations, names: tuple[str, ...], kwargs: dict[str, object], *,
                    level: int, log: SolveLog) -> JointResult:
    """κ decided from a κ = 0 optimum ``fit`` (full tables) of the subsample: the nested κ fit on coarse
    tables (:func:`polarshape.recover.joint_solve.nested_kappa`: it cannot raise the loss), polished on
    full tables when it gains enough; κ is kept when the full-table loss falls by
    ≥ :data:`KAPPA_KEEP_GAIN` on all pixels and by ≥ :data:`KAPPA_MIN_GAIN` without the 2 % that gain
    most. Returns the κ fit when kept, else ``fit`` (its skip recorded)."""
    t1 = time.perf_counter()
    log.count("kappa_probes")
    # gains relative to max(loss, loss_floor(δ)), as the alternation's window: noise-free κ-free data
    # have losses of 1e-34, whose ratios are rounding noise (they read as ±1e4 % gains)
    floor = loss_floor(float(kwargs["delta"]))  # type: ignore[arg-type]
    floor_sum = floor * float(obs_sub.weight.sum())  # the same floor for sums of per-pixel losses
    # the test on coarse tables (κ tables cost 0.1–0.6 s a build), to a tenth of the decision's 1 % (tol
    # 1e-3: κ-free data stop after one iteration), each of its starts stopped once its gain over the κ = 0
    # optimum clearly ends below KAPPA_KEEP_GAIN; a kept κ is polished on full tables (KAPPA_POLISH_TOL)
    trial, gain = nested_kappa(fit, obs_sub, names=names, decide_gain=KAPPA_KEEP_GAIN,
                               **{**kwargs, "n_grid": KAPPA_TEST_GRID, "jac_grid": KAPPA_JAC_GRID, "tol": 1e-3})
    _joint_record(trial, level, "joint_kappa", log)
    robust = trimmed_gain(trial.initial_pixel_loss, trial.pixel_loss, floor=floor_sum)
    logger.info("level %d nested κ (coarse tables): κ %.3g, gain %.2f%%, without the top 2%% %.2f%%", level,
                trial.params.kappa, 100 * gain, 100 * robust)
    if gain >= KAPPA_KEEP_GAIN and robust >= KAPPA_MIN_GAIN:
        # full tables for the loss; the Jacobian (a step direction) on the test's grid: on the 40² κ 50
        # spheres and blob the same iterations and material (κ within 0.05) as on grid 33, 30–40 % faster
        # to 1e-5, or stopped once the loss change fell below the alternation's own 0.1 % at a fast
        # rate (:func:`polarshape.recover.joint_solve.settled`: the α 0.8 κ 50 sphere at 256² stops
        # after 5 of 7 full-table iterations, κ 50.19 instead of 50.27, the loss 1e-5 above — with κ searched in
        # κ itself; in log(1 + κ/5) the polish there takes 2 of the test's iterations); or once its gain
        # over the κ = 0 optimum clearly ends below KAPPA_KEEP_GAIN (:func:`clearly_below`, the test's own
        # rule: on the 256² α 0.03 sphere exposed not to clip, κ 100 from the coarse test gained 22.6 % on full
        # tables and crawled to 23.6 % in 20 iterations, 5.9 s, before κ was dropped; now 3 iterations)
        polished = joint_solve(trial.normals, obs_sub, trial.params, names=names + ("kappa",),
                               stop=first_of(settled(KAPPA_POLISH_TOL, KAPPA_POLISH_RATE),
                                             clearly_below(KAPPA_KEEP_GAIN, floor, reference=fit.loss)),
                               **{**kwargs, "jac_grid": KAPPA_JAC_GRID})
        _joint_record(polished, level, "joint_kappa", log)
        gain = (fit.loss - polished.loss) / max(fit.loss, floor)  # both on full tables
        robust = trimmed_gain(fit.pixel_loss, polished.pixel_loss, floor=floor_sum)
        trial = polished
    log.timings["kappa_test"] = log.timings.get("kappa_test", 0.0) + time.perf_counter() - t1
    if gain >= KAPPA_KEEP_GAIN and robust >= KAPPA_MIN_GAIN:
        return trial
    # a nested fit keeps the κ = 0 optimum when κ does not help: it never reports a rise
    said = f"lowered the loss by {100 * gain:.2f}%" if gain > 0 else "did not lower the loss"
    log.skipped.append(f"kappa: the nested κ fit (from the κ = 0 optimum) {said}, {100 * robust:+.2f}% without the "
                       f"2% of pixels that gained most (needs ≥ {100 * KAPPA_KEEP_GAIN:.0f}% and ≥ "
                       f"{100 * KAPPA_MIN_GAIN:.0f}%; κ would be "
                       f"{trial.params.kappa:.3g}): κ = 0, separable fast path (fit_kappa: true forces κ)")
    return fit


def _decide_kappa(lv: _Level, sub_idx: Tensor, start: tuple[Tensor, FMBRDFParams], options: RecoveryOptions,
                  polarised: bool, *, level: int, log: SolveLog) -> bool:
    """Test κ once the κ = 0 alternation converged (:func:`_kappa_decision` from its optimum; ``start``:
    the subsample's normals and material after the first outer iteration, where the nested fit also
    starts); True when κ was kept (``lv.params`` and the subsample's normals updated)."""
    obs_sub = lv.obs.select(sub_idx)
    kwargs = {"per_pixel_albedo": options.per_pixel_albedo, "polarised": polarised, "delta": lv.delta,
              "max_iter": options.max_outer_iterations}
    names = _table_names(polarised)
    t0 = time.perf_counter()
    # the alternation's κ = 0 optimum as a joint result: no iteration, only its loss on full tables
    base = joint_solve(lv.n[sub_idx], obs_sub, lv.params, names=names, **{**kwargs, "max_iter": 0})
    base = replace(base, start_normals=start[0], start_params=start[1])
    log.add_time("kappa_test", t0)
    fit = _kappa_decision(base, obs_sub, names, kwargs, level=level, log=log)
    if fit is base:
        return False
    lv.params = fit.params
    lv.n[sub_idx] = fit.normals
    return True


def fit_level(inputs: RecoveryInputs, normals: Tensor, params: FMBRDFParams, options: RecoveryOptions, *,
              fit_globals: bool, level: int, seed: int = 0, progress: bool = False, log: SolveLog,
              material_use: Literal["fit", "fixed", "initial"] = "fit", tables: TableCache | None = None
              ) -> FMBRDFState:
    """Alternate global parameters and normals on one pyramid level (normals only unless ``fit_globals``).

    Args:
        inputs: the level's inputs; normals: (H, W, 3) start; params: the current material.
        options: recovery options; level: pyramid level (0 = finest); seed: subsample seed.
        log: history, timings, skips and counts are appended to it.
        material_use: ``fit`` (``params`` is a guess), ``fixed`` (μ, α, β, κ of ``params`` kept,
            albedos solved) or ``initial`` (``params`` starts the fit), module docstring.
        tables: the run's tables (:class:`TableCache`): the normal steps' materials are taken from it
            (a finer level's material is the coarser level's last one) and added to it.
    """
    pixels = inputs.mask
    obs = flatten_observations(inputs, pixels)
    n = normals[pixels]
    polarised = inputs.has_polarisation
    lv = _Level(pixels, obs, n, torch.zeros(n.shape[0], dtype=n.dtype, device=n.device), params,
                huber_delta(obs, inputs.noise_std), neighbour_index(pixels) if options.propagate else None)
    sub_idx = _subsample(n.shape[0], options.subsample_pixels, seed + level, n.device)
    fit_kappa = options.fit_kappa
    if material_use == "initial" and fit_kappa is None and params.kappa > 0:
        fit_kappa = True  # the material has a correlation: fit it from there, no probe
    kappa_decided = fit_kappa is not None or material_use == "fixed"
    if fit_globals and options.solver == "joint" and material_use != "fixed":
        _joint_level(lv, inputs, sub_idx, options, fit_kappa=fit_kappa, material_use=material_use, level=level,
                     log=log, tables=tables)
        return _state_of(lv, normals)
    window: list[float] = []
    start: tuple[Tensor, FMBRDFParams] | None = None  # the subsample after the first outer iteration
    outer = options.max_outer_iterations if fit_globals else 1
    # the level after the previous outer iteration and that iteration's material change (_extrapolate)
    previous: tuple[Tensor, FMBRDFParams] | None = None
    change: list[float] | None = None
    extrapolate = fit_globals and material_use != "fixed"
    for it in tqdm(range(outer), desc=f"level {level}", unit="iteration", disable=not progress):
        if extrapolate and it >= 2:  # after the lobe-first schedule of the first two
            previous = (lv.n.clone(), replace(lv.params))
        if fit_globals:
            t0 = time.perf_counter()
            lv.params = _global_step(lv.n[sub_idx], obs.select(sub_idx), lv.params, options, it=it,
                                     fit_kappa=bool(fit_kappa), polarised=polarised, delta=lv.delta,
                                     use=material_use, log=log)
            log.add_time("global_params", t0)
        t0 = time.perf_counter()
        problem, loss_pp, n_iter = _normal_step(lv, options, polarised, max_iter=6 if fit_globals else 10,
                                                level=level, it=it, tables=tables)
        log.add_time("normals", t0)
        if it == 0 and fit_globals:  # δ from the first fit's residuals
            new_delta = huber_delta(obs, inputs.noise_std, problem.residual(lv.n, obs)[0])
            if abs(new_delta - lv.delta) > 0.25 * lv.delta:
                lv.delta = new_delta
                loss_pp = problem.with_delta(new_delta).pixel_loss(lv.n, obs)
        if it == 0 and fit_globals:
            start = (lv.n[sub_idx].clone(), replace(lv.params))
        extrapolated = None
        if previous is not None:
            kappa = bool(fit_kappa)
            step = [a - b for a, b in zip(_material_coords(lv.params, kappa), _material_coords(previous[1], kappa))]
            if change is not None and _cosine(step, change) >= EXTRAPOLATION_MIN_COSINE:
                done = _extrapolate(lv, previous, step, loss_pp, options, polarised, kappa, log, tables)
                if done is not None:
                    loss_pp, extrapolated = done
            change = step
        loss = _mean_loss(loss_pp, obs)
        log.history.append({"stage": f"level{level}", "iteration": it, "loss": loss, "lm_iterations": n_iter,
                            "seconds": time.perf_counter() - log.t_start, **lv.params.as_dict(),
                            **({} if extrapolated is None else {"extrapolated": extrapolated})})
        logger.info("level %d outer %d: loss %.6g, %s", level, it, loss, lv.params.as_dict())
        window.append(loss)
        # converged: the loss changed by ≤ 0.1 % over the last two outer iterations (a window), relative to
        # the loss or, far under the noise, to loss_floor(δ)
        if len(window) >= 3 and abs(window[-3] - window[-1]) <= 1e-3 * max(abs(window[-3]), loss_floor(lv.delta)):
            if not kappa_decided and fit_globals and start is not None:
                kappa_decided = True
                if _decide_kappa(lv, sub_idx, start, options, polarised, level=level, log=log):
                    # the nested fit moved material and subsample normals together: the level's
                    # normals follow the final material once (as the joint solve's level does)
                    t0 = time.perf_counter()
                    _, loss_pp, n_iter = _normal_step(lv, options, polarised, max_iter=10, level=level, it=it + 1,
                                                      tables=tables)
                    log.add_time("normals", t0)
                    log.history.append({"stage": f"level{level}", "solver": "final_normals", "iteration": it + 1,
                                        "loss": _mean_loss(loss_pp, obs), "lm_iterations": n_iter,
                                        "seconds": time.perf_counter() - log.t_start, **lv.params.as_dict()})
            break
    else:
        if fit_globals:
            logger.info("level %d: reached max_outer_iterations=%d", level, outer)
    if not kappa_decided and fit_globals and not fit_kappa:
        log.skipped.append("kappa: not tested (alternation did not converge within max_outer_iterations): κ kept at 0")
    return _state_of(lv, normals)


def _cosine(a: list[float], b: list[float]) -> float:
    """Cosine of the angle between two vectors (0 when either is 0)."""
    na, nb = math.sqrt(sum(x * x for x in a)), math.sqrt(sum(x * x for x in b))
    return sum(x * y for x, y in zip(a, b)) / (na * nb) if na > 0 and nb > 0 else 0.0


def _state_of(lv: _Level, normals: Tensor) -> FMBRDFState:
    """The level's solution on its grid (``normals``: any (H, W, 3) of the grid, for shape and dtype)."""
    pixels, n = lv.pixels, lv.n
    normals_img = torch.full_like(normals, math.nan)
    normals_img[pixels] = lv.n
    kb_img = torch.full(pixels.shape, math.nan, dtype=n.dtype, device=n.device)
    kb_img[pixels] = lv.k_b
    return FMBRDFState(lv.params, normals_img, kb_img)


def _joint_record(fit: JointResult, level: int, stage: str, log: SolveLog) -> None:
    """Append the joint solve's iterations to the log's history and counts."""
    log.count("joint_iterations", fit.iterations)
    for h in fit.history:
        log.history.append({"stage": f"level{level}", "solver": stage, "iteration": h["iteration"], "loss": h["loss"],
                            "rel_change": h["rel_change"], "seconds": time.perf_counter() - log.t_start,
                            **fit.params.as_dict(), **{k: v for k, v in h.items() if k in (
                                "ior", "alpha", "beta", "kappa", "k_s", "lambda", "accepted", "moved", "attempts",
                                "pinned", "step", "rho", "jumped")}})


def _joint_level(lv: _Level, inputs: RecoveryInputs, sub_idx: Tensor, options: RecoveryOptions, *,
                 fit_kappa: bool | None, material_use: Literal["fit", "initial"], level: int, log: SolveLog,
                 tables: TableCache | None = None) -> None:
    """The coarsest level with the joint solve (updates ``lv``): the alternation's first outer
    iteration as the start (α grid, or a known material's albedos; normals of the whole level),
    then :func:`polarshape.recover.joint_solve.joint_solve` of normals and material on the subsample,
    κ as a nested fit from the κ = 0 optimum (``fit_kappa`` None: :func:`_kappa_decision`), and the
    level's normals for the final material."""
    obs, polarised = lv.obs, inputs.has_polarisation
    t0 = time.perf_counter()
    lv.params = _global_step(lv.n[sub_idx], obs.select(sub_idx), lv.params, options, it=0, fit_kappa=bool(fit_kappa),
                             polarised=polarised, delta=lv.delta, use=material_use, log=log)
    log.add_time("global_params", t0)
    t0 = time.perf_counter()
    problem, loss_pp, n_iter = _normal_step(lv, options, polarised, max_iter=6, level=level, it=0, tables=tables)
    new_delta = huber_delta(obs, inputs.noise_std, problem.residual(lv.n, obs)[0])
    if abs(new_delta - lv.delta) > 0.25 * lv.delta:
        lv.delta = new_delta
        loss_pp = problem.with_delta(new_delta).pixel_loss(lv.n, obs)
    log.add_time("normals", t0)
    log.history.append({"stage": f"level{level}", "solver": "start", "iteration": 0, "loss": _mean_loss(loss_pp, obs),
                        "lm_iterations": n_iter, "seconds": time.perf_counter() - log.t_start, **lv.params.as_dict()})
    t0 = time.perf_counter()
    names = _table_names(polarised)
    obs_sub = obs.select(sub_idx)
    kwargs = {"per_pixel_albedo": options.per_pixel_albedo, "polarised": polarised, "delta": lv.delta,
              "max_iter": options.max_outer_iterations}
    fit = joint_solve(lv.n[sub_idx], obs_sub, lv.params, names=names + (("kappa",) if fit_kappa else ()), **kwargs)
    _joint_record(fit, level, "joint", log)
    logger.info("level %d joint: %d iterations, loss %.6g, rel change %.2e, %s", level, fit.iterations, fit.loss,
                fit.rel_change, fit.params.as_dict())
    if not fit.converged:
        log.skipped.append(f"joint: not converged within max_outer_iterations={options.max_outer_iterations} "
                           f"(last relative loss change {fit.rel_change:.2e})")
    if fit_kappa is None:
        fit = _kappa_decision(fit, obs_sub, names, kwargs, level=level, log=log)
    log.add_time("joint", t0)
    lv.params = fit.params
    lv.n[sub_idx] = fit.normals
    t0 = time.perf_counter()
    _, loss_pp, n_iter = _normal_step(lv, options, polarised, max_iter=10, level=level, it=1, tables=tables)
    log.add_time("normals", t0)
    log.history.append({"stage": f"level{level}", "solver": "final_normals", "iteration": 1,
                        "loss": _mean_loss(loss_pp, obs), "lm_iterations": n_iter,
                        "seconds": time.perf_counter() - log.t_start, **lv.params.as_dict()})


def build_pyramid(inputs: RecoveryInputs, options: RecoveryOptions) -> list[RecoveryInputs]:
    """[finest, …, coarsest]: halve while the mask holds more than 4 · ``subsample_pixels`` pixels
    and the grid is at least 32 across (one level without ``coarse_to_fine``)."""
    levels = [inputs]
    if options.coarse_to_fine:
        while int(levels[-1].mask.sum()) > 4 * options.subsample_pixels and min(levels[-1].shape) >= 32:
            levels.append(downsample_inputs(levels[-1]))
    return levels


def upsample_normals(coarser: Tensor, fallback: Tensor) -> Tensor:
    """Normals (H, W, 3) of the next finer level from a coarser level's normals ``coarser`` (h, w, 3),
    NaN where it has none (h = H // 2, w = W // 2): upsampled bilinearly on the
    sphere of normals (the 2×2 pooling's geometry, weighted by where the coarser level has a normal,
    then made unit), the ``fallback`` (Lambertian normals of this level) where no coarser normal is
    near. Bilinear, not nearest: the start is off by the surface's curvature squared instead of half
    a coarse pixel's turn, so most pixels of a smooth surface converge in one step."""
    has = coarser.isfinite().all(-1)  # (h, w)
    up = torch.nan_to_num(coarser, nan=0.0).permute(2, 0, 1).unsqueeze(0)
    up = torch.cat([up, has.to(up.dtype)[None, None]], 1)  # (1, 4, h, w): weighted normals and weights
    up = F.interpolate(up, scale_factor=2, mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
    h, w = fallback.shape[:2]
    full = fallback.clone()
    hh, ww = min(h, up.shape[0]), min(w, up.shape[1])
    up = up[:hh, :ww]
    ok = (up[..., 3] > 1e-3) & (up[..., :3].norm(dim=-1) > 1e-3 * up[..., 3])
    full[:hh, :ww][ok] = unit(up[..., :3][ok])
    return full


def solve_fmbrdf(inputs: RecoveryInputs, initial_normals: Tensor, options: RecoveryOptions, *, seed: int = 0,
                 progress: bool = False, log: SolveLog | None = None,
                 material: KnownMaterial | None = None, tables: TableCache | None = None
                 ) -> tuple[FMBRDFState, SolveLog]:
    """Material and normals of ``inputs`` from ``initial_normals`` (H, W, 3), coarse to fine (module docstring).

    Args:
        material: a known material, fixed or initial (None: fitted from the default guess).
        tables: the run's tables (:class:`TableCache`), shared with the steps after the solve (the
            final material's tables are in it); None: a cache of this solve's own.

    Returns:
        The finest level's :class:`FMBRDFState` and the :class:`SolveLog`.
    """
    log = SolveLog() if log is None else log
    tables = TableCache() if tables is None else tables
    levels = build_pyramid(inputs, options)
    if len(levels) == 1:
        log.skipped.append("coarse_to_fine: single level (image small enough or disabled)")
    t0 = time.perf_counter()
    initial = [initial_normals]  # Lambertian normals at every level (fallback where the coarser level has none)
    for _ in range(len(levels) - 1):
        initial.append(unit(F.avg_pool2d(initial[-1].permute(2, 0, 1).unsqueeze(0), 2)[0].permute(1, 2, 0)))
    log.timings["pyramid"] = time.perf_counter() - t0
    state: FMBRDFState | None = None
    first = FMBRDFParams() if material is None else replace(material.params)
    use: Literal["fit", "fixed", "initial"] = "fit" if material is None else material.use
    if use == "fixed":
        log.skipped.append("material: fixed by recovery.material (ior, alpha, beta, kappa not fitted; albedos "
                           "solved in closed form; no kappa test)")
    for depth in range(len(levels) - 1, -1, -1):
        start = initial[depth] if state is None else upsample_normals(state.normals, initial[depth])
        state = fit_level(levels[depth], start, first if state is None else state.params, options,
                          fit_globals=state is None, level=depth, seed=seed, progress=progress, log=log,
                          material_use=use, tables=tables)
    assert state is not None  # at least one level
    return state, log
