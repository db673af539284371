"""Held-out-light validation: is this run right, without ground truth? (the paper's Fig. 7, issue 14).

Fit without a light, predict its frame and compare with the photograph: the s0 relative RMSE
‖p − o‖ / ‖o‖ (:func:`polarshape.recover.material_fit.relative_rmse`), the DoLP RMSE (absolute) and
the AoLP mean absolute error (degrees, π-periodic) over the pixels whose observed DoLP is above
3 σ of its noise. The lights of ``holdout: auto`` are spread over the dome (:func:`holdout_lights`,
farthest-point sampling). Errors count the held-out light's valid observations of the pixels with
at least :data:`polarshape.recover.priors.MIN_OBSERVATIONS` training observations (the others have
no normal of their own: the run fills them). Above ``validation.max_pixels`` mask pixels the
validation works on a lattice of them (every s-th row and column; the errors are means, the
lattice keeps them unbiased).

What is fitted, with the same structure for every model as the run's FMBRDF (one global specular
albedo k_s, one body albedo k_b / k_d per pixel, in closed form,
:func:`polarshape.recover.reflectometry.solve_albedos`), normals **re-fitted for each model**:

- *global parameters once*, on the lights no fold predicts (K − N for N held-out lights, so no
  held-out frame ever informs them): FMBRDF — **warm start**, the run's material re-fitted at the
  run's normals (:func:`~polarshape.recover.reflectometry.fit_reflectance`, :data:`WARM_LM_ITERATIONS`
  iterations, no grid; a ``fixed`` known material kept); ``l_ts``, ``baek`` — their shape parameters
  (ior, roughness) by bounded robust least squares on a pixel subsample with the albedos solved
  inside (variable projection), started at the FMBRDF's ior and α, alternated
  :data:`BASELINE_ROUNDS` times with the subsample's normals;
- *per held-out light j*, on the other K − 1 lights: each model's per-pixel normals and body albedo
  (:func:`polarshape.recover.normal_solver.refine_normals`, the FMBRDF solver's Levenberg–Marquardt,
  :data:`FOLD_LM_ITERATIONS` iterations; a baseline's residual is plugged into the same solver),
  from the run's normals (FMBRDF) and from the FMBRDF fold's (baselines); ``lambertian`` is robust
  Lambertian PS on the K − 1 lights (:func:`polarshape.recover.photometric.robust_lambertian_ps`).

``warm_start=False`` instead runs the whole FMBRDF recovery from scratch on each fold's K − 1 lights
(:func:`polarshape.recover.coarse_to_fine.solve_fmbrdf` from PS normals): measured on a 64² sphere at
K = 12, the same held-out error (0.00631 vs 0.00633) in 1/15 of the time (``benchmarks/validation.py``).

The noise floor (``noise_floor_s0_rel``) is what noise alone would give: √(Σ σ²(o)) / ‖o‖ over the
held-out valid observations, σ from the capture's noise model (``inputs.noise``, else the
quantisation σ ``inputs.noise_std``).

:func:`model_evidence` turns the comparison into ``recovery.model: auto``'s evidence: the run's
model is switched only when the other one predicts the held-out lights better by a clear margin
(:data:`SWITCH_MARGIN`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from polarshape.brdf.params import FMBRDFParams
from polarshape.errors import ConfigError
from polarshape.imaging.stokes import aolp, dolp
from polarshape.io.material import load_material
from polarshape.recover.coarse_to_fine import KnownMaterial, _subsample, solve_fmbrdf  # the recovery's subsample
from polarshape.recover.material_fit import model_parameter_bounds, relative_rmse, render_model
from polarshape.recover.noise import noise_or_constant
from polarshape.recover.normal_solver import NormalProblem, huber_delta, refine_normals, unit
from polarshape.recover.observations import Observations, RecoveryInputs, crop_inputs, flatten_observations
from polarshape.recover.options import InitialNormalsOptions, RecoveryOptions, ValidationOptions
from polarshape.recover.photometric import robust_lambertian_ps
from polarshape.recover.priors import MIN_OBSERVATIONS
from polarshape.recover.reflectometry import channel_weights, fit_reflectance, render_parts, solve_albedos

logger = logging.getLogger(__name__)

__all__ = [
    "BASELINE_ROUNDS", "COLD_OUTER_ITERATIONS", "FOLD_LM_ITERATIONS", "ModelValidation", "SWITCH_MARGIN", "Validation",
    "WARM_LM_ITERATIONS",
    "RunResult", "holdout_lights", "model_evidence", "select_input_lights", "unit_parts", "validate_holdout",
]

class RunResult(Protocol):
    """What the validation reads of a run: :class:`polarshape.normals.NormalsResult` (a later stage,
    so named by its fields here)."""

    normals: Tensor  # (H, W, 3), NaN outside the mask
    params: dict[str, float]  # the material (FMBRDF: ior, alpha, beta, kappa, k_s, k_b)
    model: str  # "fmbrdf" or "lambertian"
    # optional (a run of several materials): ``materials`` (H, W) int64, ``material_params`` list[dict]


#: Levenberg–Marquardt iterations of the warm material re-fit (from the run's material).
WARM_LM_ITERATIONS = 2
#: Most outer iterations of the FMBRDF fitted for a run of another model (fit_kappa false unless set).
COLD_OUTER_ITERATIONS = 6
#: Alternations of shape parameters and normals of a baseline's global fit.
BASELINE_ROUNDS = 2
#: Levenberg–Marquardt iterations of a fold's per-pixel normals (from a converged start).
FOLD_LM_ITERATIONS = 4
#: ``recovery.model: auto`` switches model only when the other predicts the held-out s0 with a
#: relative RMSE at least this fraction lower than the run's model AND lower by more than half the
#: noise floor (a difference noise alone would not make).
SWITCH_MARGIN = 0.10
_AOLP_SIGMAS = 3.0


def holdout_lights(directions: Tensor | np.ndarray, n: int) -> list[int]:
    """``n`` light indices spread over the dome: farthest-point sampling on the unit directions.

    Starts from the light closest to the mean direction (the dome's centre), then repeatedly takes
    the light farthest (largest angle) from all those taken; ties go to the lower index. Deterministic.

    Args:
        directions: (K, 3) directions surface → light (any length; normalised here).
        n: how many (at most K).

    Returns:
        Sorted list of ``min(n, K)`` indices.

    Example:
        >>> holdout_lights(torch.tensor([[0., 0, -1], [1, 0, -1], [-1, 0, -1]]), 2)
        [0, 1]
    """
    if isinstance(directions, Tensor):
        d = directions.detach().to("cpu", torch.float64)
    else:
        d = torch.as_tensor(np.asarray(directions), dtype=torch.float64)
    if d.ndim != 2 or d.shape[-1] != 3:
        raise ValueError(f"directions must have shape (K, 3); got {tuple(d.shape)}")
    d = unit(d)
    k = d.shape[0]
    n = min(max(int(n), 0), k)
    if n == 0:
        return []
    centre = unit(d.mean(0, keepdim=True))
    chosen = [int(torch.argmax((d * centre).sum(-1)))]
    nearest = (d @ d[chosen[0]]).clamp(-1, 1).acos()  # (K,) angle to the nearest chosen light
    while len(chosen) < n:
        j = int(torch.argmax(nearest))
        chosen.append(j)
        nearest = torch.minimum(nearest, (d @ d[j]).clamp(-1, 1).acos())
    return sorted(chosen)


def select_input_lights(inputs: RecoveryInputs, index: list[int]) -> RecoveryInputs:
    """The inputs under the lights ``index`` (into K) only, every pixel kept (a fold's training set
    or its held-out frames)."""
    idx = torch.as_tensor(index, dtype=torch.long, device=inputs.stokes.device)
    return replace(inputs, stokes=inputs.stokes[idx], valid=inputs.valid[idx], saturated=inputs.saturated[idx],
                   lights=inputs.lights[idx], irradiance=inputs.irradiance[idx], colour=None)


@dataclass
class ModelValidation:
    """One model's held-out errors: ``per_light`` records and their means (common14 interface 2)."""

    per_light: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0

    def mean(self, key: str) -> float | None:
        values = [r[key] for r in self.per_light if r.get(key) is not None and math.isfinite(r[key])]
        return float(np.mean(values)) if values else None

    def as_dict(self) -> dict[str, Any]:
        return {"per_light": [dict(r) for r in self.per_light], "s0_rel_rmse": self.mean("s0_rel_rmse"),
                "dolp_rmse": self.mean("dolp_rmse"), "aolp_mae_deg": self.mean("aolp_mae_deg"),
                "seconds": self.seconds}


@dataclass
class Validation:
    """What :func:`validate_holdout` returns: ``as_dict()`` is params.json's ``validation``.

    Attributes:
        mode: ``auto``, ``list`` or ``none``. holdout: the held-out light indices ([] when it did not run).
        reason: why it did not run or ran reduced (None when it ran in full).
        models: {name: :class:`ModelValidation`}.
        noise_floor_s0_rel: mean over the held-out lights of the s0 relative RMSE noise alone gives.
        timings_s: seconds per model and in total. warm_start: what the FMBRDF folds reused.
        observed, predicted: (N, 3, H, W) observed Stokes of the held-out frames and the run's
            model's prediction of them from the fits without them (0 outside the mask); None when
            it did not run.
            With more mask pixels than ``validation.max_pixels`` only a lattice of them (every s-th
            row and column) is fitted and predicted: both are 0 between its pixels.
        model_choice: :func:`model_evidence`'s record (set by the caller), or None.
        predictions: {model: (N, 3, H, W)} every model's prediction (``predicted`` is the run model's).
    """

    mode: str
    holdout: list[int]
    reason: str | None = None
    models: dict[str, ModelValidation] = field(default_factory=dict)
    noise_floor_s0_rel: float | None = None
    timings_s: dict[str, float] = field(default_factory=dict)
    warm_start: str = ""
    observed: np.ndarray | None = None
    predicted: np.ndarray | None = None
    model_choice: dict[str, Any] | None = None
    predictions: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def ran(self) -> bool:
        return bool(self.holdout) and bool(self.models)

    @property
    def ranking(self) -> list[str]:
        """Model names, best first, by mean held-out s0 relative RMSE (ties: DoLP RMSE)."""
        def key(name: str) -> tuple[float, float]:
            m = self.models[name]
            s0, d = m.mean("s0_rel_rmse"), m.mean("dolp_rmse")
            return (math.inf if s0 is None else s0, math.inf if d is None else d)

        return sorted(self.models, key=key)

    def as_dict(self) -> dict[str, Any]:
        out = {"holdout": list(self.holdout), "mode": self.mode, "reason": self.reason,
               "models": {name: m.as_dict() for name, m in self.models.items()}, "ranking": self.ranking,
               "noise_floor_s0_rel": self.noise_floor_s0_rel, "timings_s": dict(self.timings_s),
               "warm_start": self.warm_start}
        if self.model_choice is not None:
            out["model_choice"] = dict(self.model_choice)
        return out


# --- which lights ---------------------------------------------------------------------------


def _light_directions(inputs: RecoveryInputs) -> Tensor:
    """(K, 3) mean light direction of each light over the mask (directional: the light itself)."""
    m = inputs.mask
    if not bool(m.any()):
        return unit(inputs.lights.mean((1, 2)))
    return unit(inputs.lights[:, m].mean(1))


def _choose(inputs: RecoveryInputs, vopts: ValidationOptions) -> tuple[str, list[int], str | None]:
    """(mode, held-out lights, reason) — raises ConfigError for a list that cannot be used."""
    k = inputs.num_lights
    if vopts.holdout == "none":
        return "none", [], "validation.holdout is none"
    if vopts.holdout == "auto":
        if k < vopts.min_lights:
            return "auto", [], (f"K = {k} < {vopts.min_lights} lights (validation.min_lights): too few to hold "
                                "one out and still fit")
        # at least 3 lights stay for the global fits, which see none of the held-out ones
        n = min(vopts.lights, k - 3)
        reduced = None if n == vopts.lights else f"{n} of validation.lights = {vopts.lights} held out (K = {k})"
        return "auto", holdout_lights(_light_directions(inputs), n), reduced
    held = list(vopts.holdout)
    bad = [j for j in held if not 0 <= j < k]
    if bad:
        raise ConfigError(f"validation.holdout: light indices {bad} are not frames of this capture (K = {k}, "
                          f"indices 0..{k - 1}); use indices in that range, auto or none")
    if len(set(held)) != len(held):
        raise ConfigError(f"validation.holdout: {held} repeats a light; list each index once")
    if k - len(held) < 3:
        raise ConfigError(f"validation.holdout: {len(held)} of K = {k} lights held out leave fewer than 3 to fit "
                          "the material without them; hold out fewer lights, or set validation.holdout to none")
    return "list", sorted(held), None


# --- errors ---------------------------------------------------------------------------------


def _sigma_s0(inputs: RecoveryInputs, s0: Tensor) -> Tensor:
    """σ of observed s0 values (same shape): the capture's noise model, else its quantisation σ."""
    return noise_or_constant(inputs.noise, inputs.noise_std).std(s0)


def _errors(pred: Tensor, obs: Tensor, valid: Tensor, sigma: Tensor, polarised_model: bool) -> dict[str, float | None]:
    """Errors of a prediction (3, h, w) of observations (3, h, w) over ``valid`` (h, w)."""
    rho_p, rho_o = dolp(pred, dim=0, eps=1e-6), dolp(obs, dim=0, eps=1e-6)
    out: dict[str, float | None] = {"s0_rel_rmse": relative_rmse(pred[0], obs[0], valid)}
    out["dolp_rmse"] = float((rho_p - rho_o)[valid].pow(2).mean().sqrt()) if bool(valid.any()) else None
    # DoLP noise ≈ σ(s1) / s0 = √2 σ(s0) / s0 (NoiseModel.linear_std: s1, s2 are differences of two sites)
    polarised = valid & (rho_o > _AOLP_SIGMAS * math.sqrt(2.0) * sigma / obs[0].clamp_min(1e-6))
    if polarised_model and bool(polarised.any()):
        d = (aolp(pred, dim=0) - aolp(obs, dim=0))[polarised].abs()
        out["aolp_mae_deg"] = float(torch.rad2deg(torch.minimum(d, math.pi - d)).mean())
    else:
        out["aolp_mae_deg"] = None
    out["pixels"] = int(valid.sum())
    out["aolp_pixels"] = int(polarised.sum())
    return out


def _noise_floor(obs_s0: Tensor, valid: Tensor, sigma: Tensor) -> float:
    den = float(obs_s0[valid].pow(2).sum())
    return math.sqrt(float(sigma[valid].pow(2).sum()) / den) if den > 0 else math.nan


# --- rendering on a grid --------------------------------------------------------------------


def _to_image(values: Tensor, pixels: Tensor) -> Tensor:
    """(P, 1, 3) per-pixel Stokes of one light → (3, h, w), 0 elsewhere."""
    h, w = pixels.shape
    out = torch.zeros(3, h, w, dtype=values.dtype, device=values.device)
    out[:, pixels] = values[:, 0].T
    return out


def unit_parts(model: str, shape: dict[str, float], normals: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
    """(specular, body) Stokes (P, K, 3) of a baseline for unit albedos (k_s = 1 or k_d = 1, the
    other 0), irradiance included — the same split as :func:`polarshape.recover.reflectometry.render_parts`,
    so :func:`~polarshape.recover.reflectometry.solve_albedos` solves them (global k_s, per-pixel k_d)."""
    names = model_parameter_bounds(model)
    body = render_model(model, {**shape, "k_s": 0.0, "k_d": 1.0}, normals, obs)
    if "k_s" not in names:
        return torch.zeros_like(body), body
    return render_model(model, {**shape, "k_s": 1.0, "k_d": 0.0}, normals, obs), body


@dataclass(frozen=True)
class _BaselineProblem(NormalProblem):
    """The per-pixel normal problem of :mod:`~polarshape.recover.normal_solver` with a baseline's
    residual (``tables`` unused): ``refine_normals`` solves it unchanged."""

    model: str = ""
    shape: tuple[tuple[str, float], ...] = ()

    def residual(self, normals: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
        surf, body = unit_parts(self.model, dict(self.shape), normals, obs)
        _, k_b = solve_albedos(surf, body, obs, per_pixel=True, polarised=self.polarised, k_s=self.k_s)
        r = (obs.stokes - self.k_s * surf - k_b[:, None, None] * body) * self.cw
        return r * obs.weight.sqrt().unsqueeze(-1), k_b


def _weighted_residual(surf: Tensor, body: Tensor, obs: Observations, polarised: bool) -> Tensor:
    """Channel-weighted Stokes residual (P, K, 3) with the albedos solved (global k_s, per-pixel k_b)."""
    k_s, k_b = solve_albedos(surf, body, obs, per_pixel=True, polarised=polarised)
    r = (obs.stokes - k_s * surf - k_b[:, None, None] * body) * channel_weights(surf, polarised).sqrt()
    return r * obs.weight.sqrt().unsqueeze(-1)


def _fit_shape(model: str, normals: Tensor, obs: Observations, start: dict[str, float], polarised: bool,
               delta: float) -> dict[str, float]:
    """Shape parameters (all but the albedos) of a baseline by bounded robust least squares, albedos
    solved inside; started from the best of three roughness values around ``start``."""
    from scipy.optimize import least_squares  # ~0.6 s to import: only when a baseline is fitted
    bounds = {k: v for k, v in model_parameter_bounds(model).items() if not k.startswith("k_")}
    names = list(bounds)
    lo = np.array([bounds[k][0] for k in names])
    hi = np.array([bounds[k][1] for k in names])

    def residuals(x: np.ndarray) -> np.ndarray:
        surf, body = unit_parts(model, dict(zip(names, (float(v) for v in x))), normals, obs)
        return _weighted_residual(surf, body, obs, polarised).flatten().double().cpu().numpy()

    base = np.clip(np.array([start.get(k, 0.3) for k in names]), lo + 1e-3, hi - 1e-3)
    rough = [i for i, k in enumerate(names) if k in ("alpha", "roughness", "sigma")]
    candidates = []
    for scale in (0.5, 1.0, 2.0) if rough else (1.0,):
        x = base.copy()
        for i in rough:
            x[i] = np.clip(x[i] * scale, lo[i] + 1e-3, hi[i] - 1e-3)
        candidates.append(x)
    x0 = min(candidates, key=lambda x: float(np.sum(residuals(x) ** 2)))
    # relative steps of 1e-3: the residual is float32 (the run's dtype), too coarse for the default 1.5e-8
    sol = least_squares(residuals, x0, bounds=(lo, hi), method="trf", loss="huber", f_scale=max(delta, 1e-6),
                        x_scale="jac", diff_step=1e-3, max_nfev=40)
    return dict(zip(names, (float(v) for v in sol.x)))


# --- the folds ------------------------------------------------------------------------------


def _ps(train: RecoveryInputs, initial: InitialNormalsOptions):  # noqa: ANN202 (RobustPSResult)
    """Robust Lambertian PS on a fold's training lights (as :func:`polarshape.normals.initial_normals`)."""
    usable = train.valid & train.mask.unsqueeze(0)
    return robust_lambertian_ps(train.stokes[:, 0], train.lights, train.irradiance, usable, view_dirs=train.view,
                                dark_rel=initial.dark_rel, outlier_rel=initial.outlier_rel, saturation=None,
                                noise_std=max(initial.noise_std, train.noise_std))


def _known(options: RecoveryOptions) -> KnownMaterial | None:
    """The run's ``recovery.material`` (as :func:`polarshape.normals.known_material`), or None."""
    if options.material is None:
        return None
    return KnownMaterial(load_material(options.material).fmbrdf_params(), options.material_use)


def _fmbrdf_global(obs: Observations, normals: Tensor, params: FMBRDFParams, options: RecoveryOptions, *,
                   noise_std: float, polarised: bool, seed: int) -> FMBRDFParams:
    """The warm material: the run's μ, α, β (κ when it has one) and albedos re-fitted without the
    held-out lights, at the run's normals (:data:`WARM_LM_ITERATIONS` LM iterations, no grid), on
    ``subsample_pixels`` pixels; a ``fixed`` known material is kept."""
    if options.material is not None and options.material_use == "fixed":
        return params
    sub = _subsample(normals.shape[0], options.subsample_pixels, seed, normals.device)
    n, o = normals[sub], obs.select(sub)
    problem = NormalProblem.build(params.build_tables(device=n.device), o.stokes, params.k_s, options.per_pixel_albedo,
                                  params.k_b, polarised, huber_delta(o, noise_std))
    fit = fit_reflectance(n, o, init=params, per_pixel_albedo=options.per_pixel_albedo,
                          fit_kappa=params.kappa > 0 if options.fit_kappa is None else options.fit_kappa,
                          polarised=polarised, delta=huber_delta(o, noise_std, problem.residual(n, o)[0]),
                          grid_search=False, max_iter=WARM_LM_ITERATIONS)
    return fit.params


def _fmbrdf_normals(params: FMBRDFParams, start: Tensor, train: Observations, noise_std: float, polarised: bool,
                    per_pixel: bool) -> tuple[Tensor, Tensor]:
    """Per-pixel normals (P, 3) and k_b (P,) of a fold for a fixed material (LM from ``start``)."""
    tables = params.build_tables(device=start.device)
    problem = NormalProblem.build(tables, train.stokes, params.k_s, per_pixel, params.k_b, polarised,
                                  huber_delta(train, noise_std))
    problem = problem.with_delta(huber_delta(train, noise_std, problem.residual(start, train)[0]))
    n, k_b, _, _ = refine_normals(problem, start, train, max_iter=FOLD_LM_ITERATIONS)
    return n, k_b


def _predict_fmbrdf(normals: Tensor, k_b: Tensor, params: FMBRDFParams, test: Observations) -> Tensor:
    surf, body = render_parts(params.build_tables(device=normals.device), normals, test)
    return params.k_s * surf + k_b[:, None, None] * body  # (P, 1, 3)


def _run_materials(result: RunResult, crop: RecoveryInputs, stride: int, full: RecoveryInputs
                   ) -> tuple[Tensor, list[FMBRDFParams]] | None:
    """A run of several materials (:mod:`polarshape.recover.materials`): the material (P,) of each
    of the lattice's mask pixels and the materials; None for a run of one."""
    materials = getattr(result, "materials", None)
    found = getattr(result, "material_params", None) or []
    if materials is None or len(found) < 2:
        return None
    labels = _crop_like(materials, crop, stride, full)[crop.mask].clamp_min(0)  # (P,)
    keys = ("ior", "alpha", "beta", "kappa", "k_s", "k_b")
    return labels, [FMBRDFParams(**{n: float(p[n]) for n in keys if n in p}) for p in found]


def _fold_materials(several: tuple[Tensor, list[FMBRDFParams]], start: Tensor, train: Observations,
                    test: Observations, noise_std: float, polarised: bool, per_pixel: bool) -> tuple[Tensor, Tensor]:
    """A fold of a run of several materials: each material's pixels' normals (P, 3) and the
    prediction (P, 1, 3) with their own material."""
    labels, materials = several
    normals = start.clone()
    pred = torch.zeros(start.shape[0], 1, 3, dtype=start.dtype, device=start.device)
    for m, p in enumerate(materials):
        sel = labels == m
        if not bool(sel.any()):
            continue
        n_m, kb_m = _fmbrdf_normals(p, start[sel], train.select(sel), noise_std, polarised, per_pixel)
        normals[sel] = n_m
        pred[sel] = _predict_fmbrdf(n_m, kb_m, p, test.select(sel))
    return normals, pred


@dataclass(frozen=True)
class _Baseline:
    """A baseline's global fit: shape parameters and the global specular albedo (0-dim)."""

    model: str
    shape: dict[str, float]
    k_s: Tensor

    def problem(self, train: Observations, noise_std: float, polarised: bool) -> _BaselineProblem:
        delta = huber_delta(train, noise_std)
        return _BaselineProblem(None, self.k_s, True, 0.0, polarised, delta,  # type: ignore[arg-type]
                                channel_weights(train.stokes, polarised).sqrt(), self.model,
                                tuple(sorted(self.shape.items())))


def _fit_baseline(model: str, train: Observations, normals: Tensor, start: dict[str, float], *, noise_std: float,
                  polarised: bool, seed: int, subsample: int) -> _Baseline:
    """A baseline's shape parameters and k_s on a pixel subsample, alternated with the subsample's
    normals (:data:`BASELINE_ROUNDS`), from ``normals`` (P, 3) (the FMBRDF's)."""
    sub = _subsample(normals.shape[0], subsample, seed, normals.device)
    obs, n = train.select(sub), normals[sub]
    delta = huber_delta(obs, noise_std)
    shape = dict(start)
    fit = _Baseline(model, shape, torch.zeros((), dtype=n.dtype, device=n.device))
    for _ in range(BASELINE_ROUNDS):
        shape = _fit_shape(model, n, obs, shape, polarised, delta)
        surf, body = unit_parts(model, shape, n, obs)
        k_s, _ = solve_albedos(surf, body, obs, per_pixel=True, polarised=polarised)
        fit = _Baseline(model, shape, k_s)
        n, _, _, _ = refine_normals(fit.problem(obs, noise_std, polarised), n, obs, max_iter=FOLD_LM_ITERATIONS)
    return fit


def _predict_baseline(fit: _Baseline, start: Tensor, train: Observations, test: Observations, noise_std: float,
                      polarised: bool) -> Tensor:
    """Prediction (P, 1, 3) of the held-out light: the fold's normals and k_d re-fitted from ``start``."""
    problem = fit.problem(train, noise_std, polarised)
    n, k_d, _, _ = refine_normals(problem, start, train, max_iter=FOLD_LM_ITERATIONS)
    surf, body = unit_parts(fit.model, fit.shape, n, test)
    return fit.k_s * surf + k_d[:, None, None] * body


def _predict_lambertian(ps: Any, pixels: Tensor, test: Observations) -> Tensor:
    normals = torch.nan_to_num(ps.normals[pixels])
    k_d = math.pi * torch.nan_to_num(ps.albedo[pixels])  # I = ρ E (N·L)₊ = (k_d/π) E (N·L)₊
    _, body = unit_parts("lambertian", {}, normals, test)
    return k_d[:, None, None] * body


def _lattice(crop: RecoveryInputs, max_pixels: int) -> tuple[RecoveryInputs, int]:
    """The inputs on every s-th row and column, s the smallest stride that leaves at most
    ``max_pixels`` mask pixels (s = 1: unchanged); and s."""
    stride = 1
    while int(crop.mask[::stride, ::stride].sum()) > max_pixels and stride < 64:
        stride += 1
    if stride == 1:
        return crop, 1
    sl = (slice(None, None, stride), slice(None, None, stride))
    return replace(crop, stokes=crop.stokes[(..., *sl)], valid=crop.valid[(slice(None), *sl)],
                   saturated=crop.saturated[(slice(None), *sl)], mask=crop.mask[sl],
                   lights=crop.lights[(slice(None), *sl)],
                   irradiance=crop.irradiance[(slice(None), *sl)], view=crop.view[sl], colour=None), stride


def _paste(part: Tensor, crop: RecoveryInputs, stride: int, full: RecoveryInputs) -> Tensor:
    """(N, 3, h', w') on the lattice of the crop → (N, 3, H, W) on the full grid, 0 elsewhere."""
    h, w = full.shape
    out = torch.zeros((*part.shape[:-2], h, w), dtype=full.stokes.dtype, device=part.device)
    r0, c0 = crop.offset[0] - full.offset[0], crop.offset[1] - full.offset[1]
    hh, ww = part.shape[-2:]
    out[..., r0:r0 + stride * hh:stride, c0:c0 + stride * ww:stride] = part.to(out.dtype)
    return out


def _crop_like(x: Tensor, crop: RecoveryInputs, stride: int, full: RecoveryInputs) -> Tensor:
    """(H, W, ...) on the full grid → the crop's lattice (h', w', ...)."""
    r0, c0 = crop.offset[0] - full.offset[0], crop.offset[1] - full.offset[1]
    h, w = crop.shape
    return x[r0:r0 + stride * h:stride, c0:c0 + stride * w:stride]


def validate_holdout(inputs: RecoveryInputs, result: RunResult, options: RecoveryOptions,
                     initial: InitialNormalsOptions, vopts: ValidationOptions, *, seed: int = 0,
                     warm_start: bool = True) -> Validation:
    """Held-out-light validation of a run (module docstring).

    Args:
        inputs: the run's preprocessed inputs (K lights, grid (H, W)).
        result: the run's :class:`polarshape.normals.NormalsResult` (normals, material, model).
        options, initial: the run's recovery and initial-normals options.
        vopts: ``validation`` options (which lights, which models).
        seed: subsampling seed. warm_start: FMBRDF from the run (False: each fold from scratch).

    Returns:
        :class:`Validation` (``reason`` says why it did not run, when it did not).

    Raises:
        ConfigError: ``validation.holdout`` lists indices outside 0..K−1, repeats one, or leaves < 3 lights.
    """
    t_all = time.perf_counter()
    mode, held, reason = _choose(inputs, vopts)
    if not held:
        return Validation(mode, [], reason)
    crop, stride = _lattice(crop_inputs(inputs), vopts.max_pixels)
    pixels = crop.mask
    k = inputs.num_lights
    polarised = inputs.has_polarisation
    noise_std = inputs.noise_std
    kept = [i for i in range(k) if i not in held]
    fit_all = select_input_lights(crop, kept)  # the lights no fold predicts: the global fits' data
    obs_all = flatten_observations(fit_all, pixels)
    names = list(vopts.models)
    if options.model == "lambertian" and "models" not in vopts.model_fields_set and names != ["lambertian"]:
        names = ["lambertian"]
        reason = ("recovery.model is lambertian: only its own held-out error (the comparison costs an FMBRDF fit: "
                  "set validation.models, or recovery.model auto, to have it)")
    models = {m: ModelValidation() for m in names}
    if result.model not in models:  # the run's own model is always validated (its prediction is the report's)
        models = {result.model: ModelValidation(), **models}
    baselines = [m for m in models if m not in ("fmbrdf", "lambertian")]
    warm = warm_start and result.model == "fmbrdf"  # the run's FMBRDF starts the validation's
    timings: dict[str, float] = {}

    def timed(name: str, t0: float) -> None:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0

    with torch.no_grad():
        t0 = time.perf_counter()
        ps_all = _ps(fit_all, initial)
        run_normals = _crop_like(result.normals, crop, stride, inputs)
        start = torch.where(torch.isfinite(run_normals), run_normals, ps_all.normals) if warm else ps_all.normals
        start = torch.where(torch.isfinite(start), start, crop.view)  # no normal yet: facing the camera (+V)
        fm_start, fm_params = start[pixels], FMBRDFParams()
        several = _run_materials(result, crop, stride, inputs) if warm else None
        if warm:  # the run's material without the held-out lights
            keys = ("ior", "alpha", "beta", "kappa", "k_s", "k_b")
            run_params = FMBRDFParams(**{n: float(result.params[n]) for n in keys if n in result.params})
            fm_params = _fmbrdf_global(obs_all, fm_start, run_params, options, noise_std=noise_std,
                                       polarised=polarised, seed=seed)
        if several is not None:  # several materials: each re-fitted on its own pixels
            labels_p = several[0]
            several = (labels_p, [_fmbrdf_global(obs_all.select(labels_p == m), fm_start[labels_p == m], p, options,
                                                 noise_std=noise_std, polarised=polarised, seed=seed)
                                  if bool((labels_p == m).any()) else p for m, p in enumerate(several[1])])
        elif baselines or ("fmbrdf" in models and warm_start):  # another model's run: the FMBRDF fitted once
            quick = options.model_copy(update={  # a shorter schedule: the comparison, not the run's answer
                "max_outer_iterations": min(options.max_outer_iterations, COLD_OUTER_ITERATIONS), "propagate": False,
                "fit_kappa": bool(options.fit_kappa)})
            state, _ = solve_fmbrdf(fit_all, start, quick, seed=seed, material=_known(options))
            fm_start, fm_params = state.normals[pixels], state.params
        timed("fmbrdf", t0)
        fits = {}
        for m in baselines:
            t0 = time.perf_counter()
            fits[m] = _fit_baseline(m, obs_all, fm_start, {"ior": fm_params.ior, "alpha": fm_params.alpha,
                                                          "roughness": fm_params.alpha},
                                    noise_std=noise_std, polarised=polarised, seed=seed,
                                    subsample=min(options.subsample_pixels, 1024))
            timed(m, t0)
        images: dict[str, list[Tensor]] = {m: [] for m in models}
        floors = []
        for j in held:
            train_in = select_input_lights(crop, [i for i in range(k) if i != j])
            train = flatten_observations(train_in, pixels)
            test = flatten_observations(select_input_lights(crop, [j]), pixels)
            # a pixel with < MIN_OBSERVATIONS training observations has no normal of its own (the run fills it)
            supported = train_in.valid.sum(0) >= MIN_OBSERVATIONS
            obs, valid = crop.stokes[j], crop.valid[j] & pixels & supported  # (3, h, w), (h, w)
            sigma = _sigma_s0(inputs, obs[0])
            floors.append(_noise_floor(obs[0], valid, sigma))
            preds: dict[str, Tensor] = {}
            fold_ps = None  # robust PS on the K - 1 lights: computed once per fold, for whichever model needs it
            t0 = time.perf_counter()
            fold_normals = fm_start if "fmbrdf" not in models else None
            if "fmbrdf" in models:
                if warm_start and several is not None:
                    fold_normals, preds["fmbrdf"] = _fold_materials(several, fm_start, train, test, noise_std,
                                                                    polarised, options.per_pixel_albedo)
                elif warm_start:
                    fold_normals, k_b = _fmbrdf_normals(fm_params, fm_start, train, noise_std, polarised,
                                                        options.per_pixel_albedo)
                    preds["fmbrdf"] = _predict_fmbrdf(fold_normals, k_b, fm_params, test)
                else:  # from scratch: the whole recovery on the K − 1 lights
                    fold_ps = _ps(train_in, initial)
                    state, _ = solve_fmbrdf(train_in, torch.where(torch.isfinite(fold_ps.normals), fold_ps.normals,
                                                                  crop.view),
                                            options, seed=seed + j, material=_known(options))
                    fold_normals = state.normals[pixels]
                    preds["fmbrdf"] = _predict_fmbrdf(fold_normals, state.k_b[pixels], state.params, test)
            timed("fmbrdf", t0)
            if "lambertian" in models:
                t0 = time.perf_counter()
                fold_ps = fold_ps if fold_ps is not None else _ps(train_in, initial)
                preds["lambertian"] = _predict_lambertian(fold_ps, pixels, test)
                timed("lambertian", t0)
            for m in baselines:
                t0 = time.perf_counter()
                preds[m] = _predict_baseline(fits[m], fold_normals, train, test, noise_std, polarised)
                timed(m, t0)
            for m, record in models.items():
                image = _to_image(preds[m], pixels)
                errs = _errors(image, obs, valid, sigma, polarised_model=m != "lambertian")
                record.per_light.append({"light": j, **errs, "noise_floor_s0_rel": floors[-1]})
                images[m].append(image)
            logger.info("validation: light %d: s0 relative RMSE %s (noise floor %.4g)", j,
                        {m: round(r.per_light[-1]["s0_rel_rmse"], 5) for m, r in models.items()}, floors[-1])
    for m, record in models.items():
        record.seconds = timings.get(m, 0.0)
    timings["total"] = time.perf_counter() - t_all
    zero = torch.zeros((), dtype=crop.stokes.dtype, device=crop.stokes.device)
    observed = _paste(torch.where(pixels, crop.stokes[held], zero), crop, stride, inputs)
    predictions = {m: _paste(torch.stack(v), crop, stride, inputs).cpu().numpy() for m, v in images.items()}
    folds = (f"then per held-out light the normals and k_b on the other K - 1 ({FOLD_LM_ITERATIONS} LM iterations); "
             "baselines: shape parameters fitted once without the held-out lights, from the fmbrdf normals, ior and "
             "alpha")
    if warm and several is not None:
        how = (f"fmbrdf: each of the run's {len(several[1])} materials re-fitted once on its own pixels without the "
               f"held-out lights at the run's normals ({WARM_LM_ITERATIONS} LM iterations), {folds}")
    elif warm:
        how = (f"fmbrdf: the run's material re-fitted once without the held-out lights at the run's normals "
               f"({WARM_LM_ITERATIONS} LM iterations), {folds}")
    elif warm_start:
        how = f"fmbrdf (not the run's model): fitted once from scratch without the held-out lights, {folds}"
    else:
        how = "none: the fmbrdf fitted from scratch on each fold's K - 1 lights"
    return Validation(mode, held, reason, models, float(np.nanmean(floors)) if floors else None, timings, how,
                      observed.cpu().numpy(), predictions[result.model], predictions=predictions)


def model_evidence(validation: Validation, run_model: str, requested: str) -> dict[str, Any] | None:
    """``recovery.model: auto``'s evidence from the held-out lights (``model_choice`` in params.json).

    Compares the run's model with the other of fmbrdf / lambertian. The record says which predicts
    the held-out s0 better, whether the difference is within the noise (≤ half the noise floor), and
    ``switch_to``: the other model when ``requested`` is ``auto`` and the other's s0 relative RMSE is
    lower than the run's by at least :data:`SWITCH_MARGIN` (relative) and by more than half the
    noise floor — else None. None when validation did not run or lacks one of the two models.
    """
    other = {"fmbrdf": "lambertian", "lambertian": "fmbrdf"}.get(run_model)
    if not validation.ran or other is None or run_model not in validation.models or other not in validation.models:
        return None
    mine = validation.models[run_model].mean("s0_rel_rmse")
    theirs = validation.models[other].mean("s0_rel_rmse")
    if mine is None or theirs is None:
        return None
    floor = validation.noise_floor_s0_rel or 0.0
    diff = mine - theirs
    clear = theirs <= (1.0 - SWITCH_MARGIN) * mine and diff > 0.5 * floor
    switch = other if (requested == "auto" and clear) else None
    if switch:
        verdict = f"{other} predicts the held-out lights clearly better: switched to {other}"
    elif clear:
        verdict = f"{other} predicts the held-out lights clearly better (recovery.model {requested!r}: kept)"
    elif abs(diff) <= 0.5 * floor or theirs <= mine:
        verdict = f"{other} predicts the held-out lights as well as {run_model} (within the noise or the margin)"
    else:
        verdict = f"{run_model} predicts the held-out lights better than {other}"
    return {"run_model": run_model, "requested": requested, "other": other,
            "s0_rel_rmse": {run_model: mine, other: theirs},
            "noise_floor_s0_rel": floor, "margin": SWITCH_MARGIN, "clear": clear, "switch_to": switch,
            "verdict": verdict}
