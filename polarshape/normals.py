"""Normal recovery: the one entry point, :func:`recover_normals`, from preprocessed inputs to normals.

Steps (each timed in ``NormalsResult.timings``, each omission recorded in ``skipped``):

1. **crop** to the mask's bounding box (:func:`polarshape.recover.observations.crop_inputs`);
2. **initial normals** — robust Lambertian photometric stereo on s0, shadows and highlights
   trimmed (:func:`polarshape.recover.photometric.robust_lambertian_ps`), run once: the start of
   the FMBRDF fit, the whole answer of the ``lambertian`` model, and the baseline the report shows;
3. **model choice** — ``auto`` takes ``lambertian`` when Lambertian PS explains s0 and the light is
   unpolarised, else ``fmbrdf``; with a known material (``recovery.material``, an FMBRDF) ``auto``
   is ``fmbrdf``: the material says what the object is;
4. **FMBRDF path** — material and normals coarse to fine
   (:func:`polarshape.recover.coarse_to_fine.solve_fmbrdf`; a known material fixed or as the
   start, :class:`polarshape.recover.coarse_to_fine.KnownMaterial`) — as many materials as the
   object has, each on its own pixels (``recovery.materials``,
   :func:`polarshape.recover.materials.solve_materials`) — then pixels without data filled from
   their neighbours (:func:`polarshape.recover.priors.fill_unsupported`) and, when asked, the
   smoothness prior (:func:`polarshape.recover.priors.smooth_normals`);
   **Lambertian path** — the PS normals and albedo, pixels without data filled the same way,
   rendered with :func:`polarshape.brdf.baselines.lambertian_stokes`; both paths mark the filled
   pixels (``NormalsResult.filled``);
5. **colour** (a colour capture, ``inputs.colour``) — the body albedo per channel R, G, B with the
   normals and material of step 4 held (:func:`polarshape.recover.colour.colour_albedo`);
6. **paste back** into the full super-pixel grid.

:func:`recover_capture` runs :func:`polarshape.recover.preprocess.preprocess_capture` first (directional
lights; point lights need surface points, see ``polarshape run``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor

from polarshape.brdf.baselines import lambertian_stokes
from polarshape.brdf.params import FMBRDF_PARAM_NAMES, FMBRDFParams
from polarshape.checks import wait_for_device
from polarshape.errors import CaptureError
from polarshape.imaging.stokes import dolp
from polarshape.io.capture import Capture
from polarshape.io.material import load_material
from polarshape.recover.coarse_to_fine import FMBRDFState, KnownMaterial, SolveLog, TableCache
from polarshape.recover.colour import colour_albedo
from polarshape.recover.materials import MaterialsState, material_tables, region_inputs, solve_materials
from polarshape.recover.normal_solver import CHUNK_PIXELS
from polarshape.recover.observations import RecoveryInputs, crop_inputs, flatten_observations, paste_crop
from polarshape.recover.options import InitialNormalsOptions, RecoveryOptions
from polarshape.recover.photometric import RobustPSResult, robust_lambertian_ps
from polarshape.recover.preprocess import preprocess_capture
from polarshape.recover.priors import MIN_OBSERVATIONS, fill_unsupported, smooth_normals
from polarshape.recover.reflectometry import render_parts

logger = logging.getLogger(__name__)

__all__ = ["LAMBERTIAN_MAX_NOISE_RATIO", "NormalsResult", "choose_model", "initial_normals", "known_material", "recover_capture", "recover_normals"]


@dataclass
class NormalsResult:
    """What :func:`recover_normals` returns, on the inputs' super-pixel grid (H, W), K lights.

    Attributes:
        normals: (H, W, 3) camera-frame unit normals, NaN outside ``mask``.
        albedo: (H, W) body albedo k_b (FMBRDF) or Lambertian albedo, NaN outside ``mask``.
        params: the material (FMBRDF: ior, alpha, beta, kappa, k_s, k_b (median), r_k; Lambertian:
            albedo_median, valid_fraction).
        model: "fmbrdf" or "lambertian".
        mask: (H, W) bool object mask.
        rendered: (K, 3, H, W) Stokes the fitted model predicts (0 outside the mask).
        observed: (K, 3, H, W) observed Stokes (pixel frames, fraction of full scale).
        initial_normals: (H, W, 3) the robust Lambertian PS normals (NaN outside the mask's box).
        initial_valid: (H, W) bool pixels where PS found a trustworthy normal.
        history: per-iteration records (losses, parameters).
        timings: seconds per step.
        skipped: what was left out, with the reason.
        filled: (H, W) bool mask pixels with < 3 usable observations, whose normal and albedo are
            not their own but their neighbours' (both models; filled.png).
        counts: work of the material step (:class:`polarshape.recover.coarse_to_fine.SolveLog`:
            material_fits, material_fit_iterations, kappa_probes, albedo_solves).
        albedo_rgb: (H, W, 3) body albedo per colour channel R, G, B of a colour capture (same units
            as ``albedo``, their mean), NaN outside ``mask``; None for a mono capture.
        materials: (H, W) int64 material of each pixel (index into ``material_params``), −1 outside
            the mask; None for the Lambertian model. With several materials ``params`` is the one
            with the most pixels (:mod:`polarshape.recover.materials`).
        material_params: every material's parameters (one dict per material, as ``params``).
        mixed: (H, W) bool pixels on a material edge (left out of the material fits), or None; ``polarshape
            run`` adds the pixels on an albedo edge (``RecoveryInputs.albedo_edges``, left out of every fit).
        material_selection: one record per split the model choice tried (gain, penalty, kept).
    """

    normals: Tensor
    albedo: Tensor
    params: dict[str, float]
    model: str
    mask: Tensor
    rendered: Tensor
    observed: Tensor
    initial_normals: Tensor
    initial_valid: Tensor
    history: list[dict[str, Any]] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    filled: Tensor | None = None
    counts: dict[str, int] = field(default_factory=dict)
    albedo_rgb: Tensor | None = None
    materials: Tensor | None = None
    material_params: list[dict[str, float]] = field(default_factory=list)
    mixed: Tensor | None = None
    material_selection: list[dict[str, Any]] = field(default_factory=list)


@dataclass(frozen=True)
class _Solution:
    """A model's answer on the cropped grid."""

    normals: Tensor  # (h, w, 3), NaN outside the mask
    albedo: Tensor  # (h, w)
    rendered: Tensor  # (K, 3, h, w)
    params: dict[str, float]
    filled: Tensor | None = None
    materials: MaterialsState | None = None


def initial_normals(inputs: RecoveryInputs, options: InitialNormalsOptions = InitialNormalsOptions()) -> RobustPSResult:
    """Robust Lambertian PS on s0 of the mask's usable observations, in bands of rows (the pixels are
    independent: less memory traffic on large images).

    Raises:
        CaptureError: fewer than 3 lights. ValueError: coplanar lights (message names the fix).
    """
    if inputs.num_lights < 3:
        raise CaptureError(f"capture: {inputs.num_lights} light(s); recovery needs at least 3 non-coplanar lights "
                           "for the initial normals (add lights)")
    s0 = inputs.stokes[:, 0]  # (K, H, W)
    usable = inputs.valid & inputs.mask.unsqueeze(0)
    noise = max(options.noise_std, inputs.noise_std)
    h, w = inputs.shape
    rows = max(1, CHUNK_PIXELS // max(w, 1))
    bands = []
    for r0 in range(0, h, rows):
        b = slice(r0, min(r0 + rows, h))
        bands.append(robust_lambertian_ps(
            s0[:, b], inputs.lights[:, b], inputs.irradiance[:, b], usable[:, b], view_dirs=inputs.view[b],
            dark_rel=options.dark_rel, outlier_rel=options.outlier_rel, saturation=None, noise_std=noise,
        ))
    return RobustPSResult(**{f: torch.cat([getattr(p, f) for p in bands], dim=_band_dim(f))
                             for f in RobustPSResult.__dataclass_fields__})


def _band_dim(name: str) -> int:
    """The row axis of a :class:`RobustPSResult` field ((K, H, W) observation fields have it second)."""
    return 1 if name == "used" else 0


def _lambertian_stokes(inputs: RecoveryInputs, normals: Tensor, albedo: Tensor) -> Tensor:
    """(K, 3, H, W) Stokes of the Lambertian model with PS albedo ρ (I = ρ E (N·L)₊ = (k_d/π) E (N·L)₊)."""
    s = lambertian_stokes(normals.unsqueeze(0), inputs.lights, inputs.view.unsqueeze(0), k_d=math.pi * albedo)
    return (s * inputs.irradiance.unsqueeze(-1)).permute(0, 3, 1, 2)


#: ``auto`` takes the Lambertian model only when robust PS explains s0 to this many times the noise
#: (the robust σ of the residual over the capture's own noise σ(s0), :class:`NoiseModel` of the four-site
#: redundancy). Measured, 256² sphere × 13 lights (``benchmarks/material_grid.py``) and the matte spheres
#: of the tests: a Lambertian sphere 0.83–0.88 (shot noise, the PS fit absorbing a little of it); the FMBRDF
#: α 0.8 κ 0 sphere 1.89–1.90 — where the old rule (residual ≤ 3 % of the median s0: it read 1.0 %) chose
#: Lambertian and the normals came out at 1.31° (orthographic) and 1.47° (perspective) mean, against
#: ~0.15° with the FMBRDF. 1.3 is the geometric middle (1.5× from both).
LAMBERTIAN_MAX_NOISE_RATIO = 1.3


def choose_model(inputs: RecoveryInputs, ps: RobustPSResult, skipped: list[str]) -> str:
    """``auto``: Lambertian when robust PS explains s0 to the noise and the light is unpolarised
    (median DoLP < 2 %, about the noise level of 12-bit data), else the FMBRDF. "To the noise": the
    robust σ of the residual ≤ :data:`LAMBERTIAN_MAX_NOISE_RATIO` × the capture's noise σ(s0) where
    the noise was measured (``inputs.noise``), else ≤ 3 % of the median intensity (shot noise alone
    gives ≈ 1–2 %)."""
    s0 = inputs.stokes[:, 0]
    pred = _lambertian_stokes(inputs, ps.normals, ps.albedo)[:, 0]
    use = inputs.valid & inputs.mask.unsqueeze(0)
    res = (s0 - pred)[use]
    sigma = float(res.abs().median() * 1.4826) if res.numel() else 0.0
    rho = dolp(inputs.stokes, dim=1, eps=1e-6)[use]
    med_dolp = float(rho.median()) if rho.numel() else 0.0
    scale = float(s0[use].median()) if bool(use.any()) else 0.0
    if inputs.noise is not None and res.numel():
        ratio = float((res / inputs.noise.std(s0[use]).clamp_min(1e-12)).abs().median() * 1.4826)
        explained, said = ratio <= LAMBERTIAN_MAX_NOISE_RATIO, f"{ratio:.2f}× the noise"
    else:
        explained, said = sigma <= 0.03 * scale, f"{sigma:.2e}, no noise estimate"
    if explained and med_dolp < 0.02:
        skipped.append(f"fmbrdf: Lambertian PS explains the data (robust residual σ {said}, median DoLP "
                       f"{med_dolp:.3f}): model 'lambertian' chosen")
        return "lambertian"
    if med_dolp < 0.02:
        logger.info("model choice: the light is unpolarised but Lambertian PS leaves %s: model 'fmbrdf'", said)
    return "fmbrdf"


def _fill(inputs: RecoveryInputs, normals: Tensor, albedo: Tensor, log: SolveLog) -> tuple[Tensor, Tensor, Tensor]:
    """Mask pixels with < :data:`MIN_OBSERVATIONS` usable observations have no normal of their own:
    they take their neighbours' (:func:`polarshape.recover.priors.fill_unsupported`) and are marked
    (the returned (h, w) bool ``filled``: result.filled, filled.png), whatever the model."""
    supported = inputs.valid.sum(0) >= MIN_OBSERVATIONS
    normals, albedo, filled = fill_unsupported(normals, albedo, inputs.mask, supported)
    if bool(filled.any()):
        log.skipped.append(f"fill: {int(filled.sum())} mask pixels with < {MIN_OBSERVATIONS} usable observations "
                           "have no normal of their own: they took their neighbours' normal and albedo (result.filled)")
    return normals, albedo, filled


def _lambertian_solution(inputs: RecoveryInputs, ps: RobustPSResult, log: SolveLog) -> _Solution:
    """The intensity-only answer: PS normals and albedo (pixels without data filled from their
    neighbours and marked); the loss is the RMS s0 residual."""
    mask = inputs.mask
    ps_normals, ps_albedo, filled = _fill(inputs, ps.normals, ps.albedo, log)
    normals = torch.where(mask[..., None], ps_normals, torch.full_like(ps_normals, math.nan))
    albedo = torch.where(mask, ps_albedo, torch.full_like(ps_albedo, math.nan))
    rendered = torch.where(mask, _lambertian_stokes(inputs, ps_normals, ps_albedo),
                           torch.zeros((), dtype=ps_normals.dtype, device=mask.device))
    residual = (rendered[:, 0] - inputs.stokes[:, 0])[inputs.valid & mask]
    rms = float(residual.pow(2).mean().sqrt()) if residual.numel() else math.nan
    n_mask = int(mask.sum())
    params = {
        "albedo_median": float(ps.albedo[mask].median()) if n_mask else math.nan,
        "valid_fraction": float((ps.valid & mask).sum()) / max(n_mask, 1),
    }
    log.history.append({"iteration": 0, "loss": rms, "loss_name": "rms_s0_residual"})
    log.skipped += ["reflectometry: the lambertian model has no material fit", "joint refinement: lambertian model"]
    return _Solution(normals, albedo, rendered, params, filled)


def _render_fmbrdf(inputs: RecoveryInputs, state: FMBRDFState, tables: TableCache | None = None) -> Tensor:
    """(K, 3, H, W) Stokes rendered with the recovered normals, parameters and albedo (0 outside the mask);
    the material's tables from the run's ``tables`` (the solve built them) when given."""
    pixels = inputs.mask
    obs = flatten_observations(inputs, pixels)
    p = state.params
    normals, k_b = state.normals[pixels], state.k_b[pixels]  # (P, 3), (P,)
    parts = []
    with torch.no_grad():
        built = material_tables(p, inputs.stokes.device, tables)
        for start in range(0, normals.shape[0], CHUNK_PIXELS):  # (P, K, 3) temporaries of a chunk only
            idx = torch.arange(start, min(start + CHUNK_PIXELS, normals.shape[0]), device=normals.device)
            surf, body = render_parts(built, normals[idx], obs.select(idx))
            parts.append(p.k_s * surf + k_b[idx][:, None, None] * body)  # (chunk, K, 3)
        s = torch.cat(parts) if parts else normals.new_zeros((0, obs.stokes.shape[1], 3))  # (P, K, 3)
    h, w = inputs.shape
    out = torch.zeros(h, w, *s.shape[1:], dtype=s.dtype, device=s.device)
    out[pixels] = s
    return out.permute(2, 3, 0, 1)


def known_material(options: RecoveryOptions) -> KnownMaterial | None:
    """The material ``recovery.material`` names, read again (validated when the options were), or None.

    Raises:
        MaterialError: the file changed since into something unreadable, or holds another model.
    """
    if options.material is None:
        return None
    return KnownMaterial(load_material(options.material).fmbrdf_params(), options.material_use)


def _fmbrdf_solution(inputs: RecoveryInputs, ps: RobustPSResult, options: RecoveryOptions, *, seed: int,
                     progress: bool, log: SolveLog, material: KnownMaterial | None) -> _Solution:
    """Coarse-to-fine FMBRDF solve from the PS normals, fill, optional smoothness prior, render."""
    if not inputs.has_polarisation:
        log.skipped.append("polarisation: no linear polarisation above the noise (no polariser or an unpolarised "
                           "scene): intensity-only fit")
    tables = TableCache()  # the run's tables: the solve's final material's are the render's
    several = solve_materials(inputs, ps.normals, options, seed=seed, progress=progress, log=log, material=material,
                              tables=tables)
    normals, k_b, filled = _fill(inputs, several.normals, several.k_b, log)
    if not bool(filled.any()):
        normals, k_b = several.normals, several.k_b
    # (a filled pixel's material: the Potts prior gave it its neighbours', its own data being too few)
    several = replace(several, normals=normals, k_b=k_b)
    one = len(several.params) == 1
    if options.smoothness > 0:
        t0 = time.perf_counter()
        for m, p in enumerate(several.params):  # each material's pixels with their own material
            region = inputs if one else region_inputs(inputs, several.labels == m)
            normals, k_b = smooth_normals(region, normals, k_b, p, per_pixel_albedo=options.per_pixel_albedo,
                                          smoothness=options.smoothness)
        several = replace(several, normals=normals, k_b=k_b)
        log.add_time("smoothing", t0)
    else:
        log.skipped.append("smoothness: 0, per-pixel maximum-likelihood normals (no spatial prior)")
    t0 = time.perf_counter()
    if one:
        rendered = _render_fmbrdf(inputs, FMBRDFState(several.params[0], normals, k_b), tables)
    else:  # each material renders its own pixels (zeros elsewhere)
        rendered = torch.stack([_render_fmbrdf(region_inputs(inputs, several.labels == m), several.material_state(m),
                                               tables)
                                for m in range(len(several.params))]).sum(0)
    log.add_time("render", t0)
    if not options.per_pixel_albedo:
        log.skipped.append("per_pixel_albedo: disabled by config (one global k_b)")
    return _Solution(normals, k_b, rendered, several.params[several.largest()].as_dict(), filled, several)


def _colour_albedo(inputs: RecoveryInputs, sol: _Solution, model: str, options: RecoveryOptions, log: SolveLog
                   ) -> Tensor | None:
    """(h, w, 3) albedo per colour channel of a colour capture, normals and material held; None for mono."""
    if inputs.colour is None:
        return None
    t0 = time.perf_counter()
    material = FMBRDFParams(**{k: sol.params[k] for k in FMBRDF_PARAM_NAMES}) if model == "fmbrdf" else None
    rgb = colour_albedo(inputs, sol.normals, model, material, filled=sol.filled,
                        per_pixel=options.per_pixel_albedo or model == "lambertian")
    log.add_time("colour", t0)
    return rgb


def recover_normals(
    inputs: RecoveryInputs,
    options: RecoveryOptions = RecoveryOptions(),
    initial: InitialNormalsOptions = InitialNormalsOptions(),
    *,
    seed: int = 0,
    progress: bool = False,
    material: KnownMaterial | None = None,
) -> NormalsResult:
    """Per-pixel normals and the reflectance of preprocessed inputs (module docstring: the steps).

    Args:
        inputs: :func:`polarshape.recover.preprocess.preprocess_capture`'s output (K ≥ 3 lights).
        options: the recovery's options (model, material fit, priors).
        initial: the initial normals' photometric-stereo thresholds.
        seed: seed of the subsampling. progress: tqdm bars.
        material: an FMBRDF material given in memory, used as ``recovery.material`` is (and instead of it);
            None: ``options.material``.

    Returns:
        :class:`NormalsResult` on the inputs' grid.

    Raises:
        CaptureError: fewer than 3 lights. ValueError: coplanar lights.
    """
    log = SolveLog()
    crop = crop_inputs(inputs)
    if crop.shape != inputs.shape:
        log.skipped.append(f"crop: solved on the mask's bounding box {crop.shape} of {inputs.shape} super-pixels")
    t0 = time.perf_counter()
    ps = initial_normals(crop, initial)
    wait_for_device(ps.normals.device)  # the time of robust PS, not of its queue
    log.timings["init_lambertian"] = time.perf_counter() - t0
    if options.model == "auto" and (options.material is not None or material is not None):
        model = "fmbrdf"
        log.skipped.append("model choice: auto with recovery.material (an FMBRDF material): model 'fmbrdf'")
    else:
        model = choose_model(crop, ps, log.skipped) if options.model == "auto" else options.model
    if model == "lambertian":
        sol = _lambertian_solution(crop, ps, log)
    else:
        sol = _fmbrdf_solution(crop, ps, options, seed=seed, progress=progress, log=log,
                               material=material or known_material(options))
    albedo_rgb = _colour_albedo(crop, sol, model, options, log)
    log.timings["total"] = time.perf_counter() - log.t_start
    return NormalsResult(
        normals=paste_crop(sol.normals, crop, inputs, channels_last=True),
        albedo=paste_crop(sol.albedo, crop, inputs),
        params=sol.params, model=model, mask=inputs.mask.clone(),
        rendered=paste_crop(sol.rendered, crop, inputs, 0.0), observed=inputs.stokes,
        initial_normals=paste_crop(ps.normals, crop, inputs, channels_last=True),
        initial_valid=paste_crop(ps.valid & crop.mask, crop, inputs, False),
        history=log.history, timings=log.timings, skipped=log.skipped,
        filled=None if sol.filled is None else paste_crop(sol.filled, crop, inputs, False), counts=dict(log.counts),
        albedo_rgb=None if albedo_rgb is None else paste_crop(albedo_rgb, crop, inputs, channels_last=True),
        **_material_fields(sol, crop, inputs),
    )


def _material_fields(sol: _Solution, crop: RecoveryInputs, inputs: RecoveryInputs) -> dict[str, Any]:
    """NormalsResult's material map, parameters, edges and selection record on the full grid."""
    several = sol.materials
    if several is None:
        return {}
    return {"materials": paste_crop(several.labels, crop, inputs, -1).to(torch.int64),
            "material_params": [p.as_dict() for p in several.params],
            "mixed": paste_crop(several.mixed, crop, inputs, False), "material_selection": several.selection}


def recover_capture(
    capture: Capture,
    options: RecoveryOptions = RecoveryOptions(),
    initial: InitialNormalsOptions = InitialNormalsOptions(),
    *,
    demosaic: str = "bilinear",
    sample_at: str = "centre",
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    seed: int = 0,
    progress: bool = False,
) -> NormalsResult:
    """Preprocess a capture under directional lights and recover its normals and reflectance.

    Args:
        capture: the capture (frames, lights, mask); directional lights (point lights need surface
            points: see :func:`polarshape.recover.preprocess.preprocess_capture`).
        options, initial: as for :func:`recover_normals`.
        demosaic, sample_at: how and where each block's Stokes vector is estimated.
        device, dtype: of the solve. seed: subsampling seed (torch is seeded with it too).

    Returns:
        :class:`NormalsResult` at the capture's super-pixel resolution (H, W) = frames / 2;
        ``timings["preprocess"]`` included.
    """
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    inputs = preprocess_capture(capture, dtype=dtype, device=device, demosaic=demosaic, sample_at=sample_at)
    t_pre = time.perf_counter() - t0
    result = recover_normals(inputs, options, initial, seed=seed, progress=progress)
    result.timings["preprocess"] = t_pre
    result.timings["total"] += t_pre
    return result
