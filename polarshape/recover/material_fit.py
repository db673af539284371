"""One material, many models: fit a reflectance model to observations of known geometry (spec §9, §10).

The models (:data:`FIT_MODELS`), all fitted with **one global set of parameters** (no per-pixel
albedo: the object is assumed to be of one material, as a reflectometry target is):

- ``fmbrdf`` — the Fresnel Microfacet BRDF, fitted by
  :func:`polarshape.recover.reflectometry.fit_reflectance` with the paper's eq. 25 objective
  (``objective_kind="eq25"``, DoLP outlier weights of
  :func:`~polarshape.recover.reflectometry.eq25_weights`), κ searched on the σ-reparameterisation
  κ = κ_max·σ(u) started at κ = 5, so that it does not stick at the bound 0 with a zero gradient.
- ``baek`` — Baek et al. 2018 pBRDF (GGX specular + Fresnel-transmitted Lambertian body).
- ``l_ts`` — **L+TS**: Lambertian body + Torrance–Sparrow specular, their Stokes vectors summed
  (parameters k_d; ior, k_s, roughness). The body is unpolarised; all the polarisation comes from
  the specular Fresnel reflection.
- ``on_ts`` — **ON+TS**: Oren–Nayar body + Torrance–Sparrow specular, likewise (k_d, sigma; ior,
  k_s, roughness).
- any single model of :data:`polarshape.brdf.MODELS` by its own name (``lambertian``, ...).

The baselines minimise the same eq. 25 objective, (1/M) Σ (Ī − I)² + Σ w (ρ̄ − ρ)² / Σ w, with the
same weights, by :func:`scipy.optimize.least_squares` (trust-region reflective, the models' bounds),
started from the best point of a small grid over the roughness parameter with the albedos solved
there by non-negative least squares on s0 (every model is linear in its albedos ``k_*``).

Errors (:class:`ModelFit`, :func:`held_out_errors`): the **relative RMSE** of a prediction p of
observations o over the valid observations, ‖p − o‖₂ / ‖o‖₂, of the intensity s0 and of the DoLP —
the metric we use for the paper's Fig. 7 (prediction of each held-out light from a fit to the
others). The paper's exact normalisation could not be checked here; this one is scale-free and 0
for a perfect prediction.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from polarshape.brdf import MODELS
from polarshape.brdf.params import FMBRDFParams
from polarshape.imaging.stokes import dolp
from polarshape.recover.observations import Observations
from polarshape.recover.reflectometry import eq25_weights, fit_reflectance

logger = logging.getLogger(__name__)

__all__ = [
    "COMPOSITE_MODELS", "FIT_MODELS", "HeldOutErrors", "ModelFit", "fit_model", "held_out_errors",
    "model_parameter_bounds", "model_parts", "rank_models", "relative_rmse", "render_model", "select_lights",
]

#: Composite baselines of the paper's comparison: body model + specular model, Stokes summed.
COMPOSITE_MODELS: dict[str, tuple[str, ...]] = {
    "l_ts": ("lambertian", "torrance_sparrow"),
    "on_ts": ("oren_nayar", "torrance_sparrow"),
}

#: The models ``polarshape material`` fits by default, ours first.
FIT_MODELS: tuple[str, ...] = ("fmbrdf", "baek", "on_ts", "l_ts")

#: Starting values of the non-linear parameters of the baselines (the roughness one is gridded).
_START: dict[str, float] = {"ior": 1.5, "roughness": 0.3, "sigma": 0.3, "alpha": 0.3}
_ROUGHNESS_NAMES: tuple[str, ...] = ("roughness", "alpha")
_ROUGHNESS_GRID: tuple[float, ...] = (0.05, 0.1, 0.2, 0.35, 0.6, 1.0)


def model_parts(name: str) -> tuple[str, ...]:
    """The :data:`polarshape.brdf.MODELS` a fit model sums (one for a plain model).

    Raises:
        ValueError: an unknown name (the message lists the known ones).
    """
    if name in COMPOSITE_MODELS:
        return COMPOSITE_MODELS[name]
    if name in MODELS:
        return (name,)
    known = sorted([*COMPOSITE_MODELS, *MODELS])
    raise ValueError(f"unknown reflectance model {name!r}; choose from {', '.join(known)}")


def model_parameter_bounds(name: str) -> dict[str, tuple[float, float]]:
    """(lower, upper) bounds of every parameter of a fit model, its parts' merged (no name clashes)."""
    out: dict[str, tuple[float, float]] = {}
    for part in model_parts(name):
        out.update(MODELS[part].params)
    return out


@dataclass(frozen=True)
class ModelFit:
    """One model fitted to observations with known normals.

    Attributes:
        model: its name (:data:`FIT_MODELS` or a :data:`polarshape.brdf.MODELS` name).
        params: fitted parameters by name (the model's own names and units).
        loss: eq. 25 objective at ``params``.
        residual_rms: RMS of the s0 residual over valid observations, fraction of full scale.
        relative_rmse: ‖I_fit − Ī‖ / ‖Ī‖ of s0 over valid observations.
        dolp_relative_rmse: the same of the DoLP.
        observations: number of valid observations fitted.
        seconds: wall time of the fit.
    """

    model: str
    params: dict[str, float]
    loss: float
    residual_rms: float
    relative_rmse: float
    dolp_relative_rmse: float
    observations: int
    seconds: float

    def as_dict(self) -> dict[str, object]:
        """Plain-JSON record of the fit."""
        return {"model": self.model, "parameters": dict(self.params), "loss": self.loss,
                "residual_rms": self.residual_rms, "relative_rmse": self.relative_rmse,
                "dolp_relative_rmse": self.dolp_relative_rmse, "observations": self.observations,
                "seconds": self.seconds}


@dataclass(frozen=True)
class HeldOutErrors:
    """Leave-one-light-out prediction errors of one model (the paper's Fig. 7).

    Attributes:
        model: its name.
        relative_rmse: (K,) s0 relative RMSE of each held-out frame predicted from the others.
        dolp_relative_rmse: (K,) the same of the DoLP.
        frames: the frame index of each entry (indices into the observations' K lights).
    """

    model: str
    relative_rmse: list[float]
    dolp_relative_rmse: list[float]
    frames: list[int] = field(default_factory=list)

    @property
    def mean_relative_rmse(self) -> float:
        return float(np.mean(self.relative_rmse))

    @property
    def mean_dolp_relative_rmse(self) -> float:
        return float(np.mean(self.dolp_relative_rmse))

    def as_dict(self) -> dict[str, object]:
        return {"model": self.model, "frames": list(self.frames), "relative_rmse": list(self.relative_rmse),
                "dolp_relative_rmse": list(self.dolp_relative_rmse), "mean_relative_rmse": self.mean_relative_rmse,
                "mean_dolp_relative_rmse": self.mean_dolp_relative_rmse}


def select_lights(obs: Observations, index: list[int] | Tensor) -> Observations:
    """The observations under the lights ``index`` (into K), every pixel kept."""
    idx = torch.as_tensor(index, dtype=torch.long, device=obs.stokes.device)
    return Observations(obs.stokes[:, idx], obs.weight[:, idx], obs.lights[:, idx], obs.irradiance[:, idx], obs.view)


def render_model(name: str, params: dict[str, float], normals: Tensor, obs: Observations) -> Tensor:
    """Rendered Stokes (P, K, 3) of a fit model at the observations' lights, view and irradiance.

    Args:
        name: fit model name. params: all its parameters. normals: (P, 3) unit normals, camera frame.
        obs: the observations (their stokes are not used).
    """
    n, l, v = torch.broadcast_tensors(normals.unsqueeze(1), obs.lights, obs.view.unsqueeze(1))  # (P, K, 3)
    out = torch.zeros_like(n)
    for part in model_parts(name):
        spec = MODELS[part]
        out = out + spec.stokes(n, l, v, **{k: float(params[k]) for k in spec.params})
    return out * obs.irradiance.unsqueeze(-1).to(out.dtype)


def _dolp(s: Tensor) -> Tensor:
    return dolp(s, dim=-1, eps=1e-6)


def relative_rmse(predicted: Tensor, observed: Tensor, valid: Tensor) -> float:
    """‖p − o‖₂ / ‖o‖₂ over ``valid`` (any matching shapes); NaN when nothing is valid."""
    vf = valid.to(predicted.dtype)
    den = float((vf * observed * observed).sum())
    if not bool(valid.any()) or den <= 0:
        return math.nan
    return math.sqrt(float((vf * (predicted - observed) ** 2).sum()) / den)


def _errors(rendered: Tensor, obs: Observations) -> tuple[float, float, float]:
    """(s0 residual RMS, s0 relative RMSE, DoLP relative RMSE) over valid observations."""
    valid = obs.weight > 0
    r0 = (rendered[..., 0] - obs.stokes[..., 0])[valid]
    rms = float(r0.pow(2).mean().sqrt()) if r0.numel() else math.nan
    return (rms, relative_rmse(rendered[..., 0], obs.stokes[..., 0], valid),
            relative_rmse(_dolp(rendered), _dolp(obs.stokes), valid))


def _eq25_residuals(rendered: Tensor, obs: Observations, eqw: Tensor) -> Tensor:
    """Residual vector whose squared sum is eq. 25 (as :func:`polarshape.recover.reflectometry.eq25_loss`)."""
    vf = (obs.weight > 0).to(rendered.dtype)
    r_i = (obs.stokes[..., 0] - rendered[..., 0]) * (vf / vf.sum().clamp_min(1.0)).sqrt()
    w = eqw * vf
    r_d = (_dolp(obs.stokes) - _dolp(rendered)) * (w / w.sum().clamp_min(1e-12)).sqrt()
    return torch.cat([r_i.flatten(), r_d.flatten()])


def _albedos_nnls(name: str, values: dict[str, float], albedos: list[str], normals: Tensor, obs: Observations
                  ) -> dict[str, float]:
    """Non-negative least-squares albedos on s0 with the other parameters at ``values``."""
    from scipy.optimize import nnls  # ~0.6 s to import: only when a model is fitted
    valid = (obs.weight > 0).flatten()
    cols = []
    for a in albedos:
        unit = {**values, **{b: (1.0 if b == a else 0.0) for b in albedos}}
        cols.append(render_model(name, unit, normals, obs)[..., 0].flatten()[valid])
    design = torch.stack(cols, -1).double().cpu().numpy()  # (M, A)
    target = obs.stokes[..., 0].flatten()[valid].double().cpu().numpy()
    coef, _ = nnls(design, target)
    return dict(zip(albedos, (float(c) for c in coef)))


def _fit_baseline(name: str, normals: Tensor, obs: Observations, eqw: Tensor, max_nfev: int
                  ) -> tuple[dict[str, float], float]:
    """(parameters, eq. 25 loss) of a baseline by bounded least squares (module docstring)."""
    from scipy.optimize import least_squares
    bounds = model_parameter_bounds(name)
    names = list(bounds)
    albedos = [n for n in names if n.startswith("k_")]
    start = {n: _START.get(n, 0.5) for n in names if n not in albedos}
    rough = [n for n in start if n in _ROUGHNESS_NAMES]

    def loss_at(values: dict[str, float]) -> float:
        r = _eq25_residuals(render_model(name, values, normals, obs), obs, eqw)
        return float((r * r).sum())

    best: tuple[float, dict[str, float]] = (math.inf, {})
    for g in (_ROUGHNESS_GRID if rough else (None,)):
        values = dict(start)
        if g is not None:
            values[rough[0]] = g
        values.update(_albedos_nnls(name, values, albedos, normals, obs))
        loss = loss_at(values)
        if loss < best[0]:
            best = (loss, values)
    x0 = np.array([best[1][n] for n in names])
    lo = np.array([bounds[n][0] for n in names])
    hi = np.array([bounds[n][1] for n in names])
    x0 = np.clip(x0, lo + 1e-9 * np.maximum(1.0, np.abs(lo)), np.where(np.isfinite(hi), hi - 1e-9, np.inf))

    def residuals(x: np.ndarray) -> np.ndarray:
        values = dict(zip(names, (float(v) for v in x)))
        return _eq25_residuals(render_model(name, values, normals, obs), obs, eqw).double().cpu().numpy()

    sol = least_squares(residuals, x0, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=max_nfev)
    params = dict(zip(names, (float(v) for v in sol.x)))
    return params, float(2.0 * sol.cost)


def fit_model(name: str, normals: Tensor, obs: Observations, *, fit_kappa: bool = True, max_nfev: int = 200,
              fmbrdf_init: FMBRDFParams | None = None, fmbrdf_max_iter: int = 20) -> ModelFit:
    """Fit one model's global parameters to observations of known normals by eq. 25.

    Args:
        name: :data:`FIT_MODELS` or a :data:`polarshape.brdf.MODELS` name.
        normals: (P, 3) unit normals, camera frame (N·V > 0).
        obs: :class:`Observations` of the P pixels under K lights; weight 0 = unusable.
        fit_kappa: FMBRDF: search κ too (else κ stays at the start value, 0).
        max_nfev: baselines: most residual evaluations of the least-squares solver.
        fmbrdf_init: FMBRDF: starting parameters (default :class:`FMBRDFParams` ()).
        fmbrdf_max_iter: FMBRDF: most Levenberg–Marquardt iterations.

    Returns:
        :class:`ModelFit`.

    Raises:
        ValueError: unknown model; shapes that do not match; no valid observation.
    """
    parts = model_parts(name)
    if normals.ndim != 2 or normals.shape[-1] != 3 or normals.shape[0] != obs.num_pixels:
        raise ValueError(f"normals must have shape (P, 3) with P = {obs.num_pixels} observations; got {tuple(normals.shape)}")
    n_valid = int((obs.weight > 0).sum())
    if n_valid == 0:
        raise ValueError("no valid observation to fit a material to (all dark, saturated or outside the mask)")
    t0 = time.perf_counter()
    eqw = eq25_weights(_dolp(obs.stokes), obs.weight > 0)
    if parts == ("fmbrdf",):
        fit = fit_reflectance(normals, obs, init=fmbrdf_init, per_pixel_albedo=False, fit_kappa=fit_kappa,
                              objective_kind="eq25", max_iter=fmbrdf_max_iter)
        params = {k: float(v) for k, v in fit.params.as_dict().items()}
        params["k_b"] = float(fit.k_b[0]) if fit.k_b.numel() else params["k_b"]
        rendered = render_model(name, params, normals, obs)
        r = _eq25_residuals(rendered, obs, eqw)
        loss = float((r * r).sum())
    else:
        params, loss = _fit_baseline(name, normals, obs, eqw, max_nfev)
        rendered = render_model(name, params, normals, obs)
    rms, rel, rel_d = _errors(rendered, obs)
    seconds = time.perf_counter() - t0
    logger.info("material fit %s: loss %.4g, s0 relative RMSE %.4f in %.1f s: %s", name, loss, rel, seconds, params)
    return ModelFit(name, params, loss, rms, rel, rel_d, n_valid, seconds)


def rank_models(fits: dict[str, ModelFit], held_out: dict[str, HeldOutErrors] | None = None) -> list[str]:
    """Model names, best first: by mean held-out s0 relative RMSE when given, else by the eq. 25 loss."""
    if held_out:
        return sorted(held_out, key=lambda m: held_out[m].mean_relative_rmse)
    return sorted(fits, key=lambda m: fits[m].loss)


def held_out_errors(normals: Tensor, obs: Observations, models: tuple[str, ...] = FIT_MODELS, **fit_kw: object
                    ) -> dict[str, HeldOutErrors]:
    """Leave-one-light-out: for each of the K ≥ 2 lights, fit each model to the other K − 1 and
    predict it (the paper's Fig. 7). Frames with no valid observation are skipped.

    Args:
        normals: (P, 3). obs: K ≥ 2 lights. models: fit model names. fit_kw: passed to :func:`fit_model`.

    Returns:
        {model: :class:`HeldOutErrors`}.

    Raises:
        ValueError: fewer than two lights.
    """
    k = int(obs.stokes.shape[1])
    if k < 2:
        raise ValueError(f"held-out errors need at least 2 frames (one to predict, one to fit); got {k}")
    out = {m: HeldOutErrors(m, [], [], []) for m in models}
    for held in range(k):
        test = select_lights(obs, [held])
        if not bool((test.weight > 0).any()):
            continue
        train = select_lights(obs, [i for i in range(k) if i != held])
        for m in models:
            fit = fit_model(m, normals, train, **fit_kw)  # type: ignore[arg-type]
            _, rel, rel_d = _errors(render_model(m, fit.params, normals, test), test)
            out[m].relative_rmse.append(rel)
            out[m].dolp_relative_rmse.append(rel_d)
            out[m].frames.append(held)
    return out
