"""Near-field lights (LED rings and domes): per-pixel light vectors and irradiance at the recovered surface,
and the object's absolute distance from the shading.

A lab rig's LEDs sit a few object sizes away, so the light direction L and the 1/r² fall-off E change
across the object (:meth:`polarshape.lights.Lights.illuminate`): they depend on where each surface point
is, which is what recovery is after. :func:`refine_near_field` starts from the lights placed on the plane
at ``integration.reference_depth_m`` (preprocessing), then

0. finds the distance of a fronto-parallel plane from the shading (normals from far-off L would
   integrate to a wild shape) and moves L, E there;
1. **photometric-stereo rounds** (cheap, milliseconds per fit — :func:`polarshape.normals.initial_normals`):
   normals from the current L and E → depth (the normals integrated with the run's camera,
   orthographic or perspective) → its absolute placement from the shading (an offset orthographic, a
   scale in perspective: normals fix the shape, not where it is; :func:`estimate_depth_placement`) →
   L and E at every pixel's 3-D point; until the mean normal change is below ``tolerance_deg`` and the
   RMS depth change below ``depth_tolerance`` of the distance (or ``max_iterations``);
2. **model rounds** (``full_model_rounds``): the run's model (FMBRDF) fitted at the settled lights; then,
   each further round, cheap rounds with the material's shape (μ, α, β, κ) held: normals integrated, the
   placement searched again with the model's non-Lambertian part taken out of the shading and its k_s
   re-fitted at every candidate (:class:`ModelShading`: gloss and the body term's Fresnel factors
   otherwise bias a Lambertian search — the glossy sphere 5 % too near; a k_s fitted at another placement
   biases it too), L and E moved, normals re-solved — the move to the distance found under-relaxed once it
   overshoots (:func:`_model_rounds`: distance and normals feed back with a gain beyond −1 on a glossy
   sphere, and undamped the distance swung ever wider); then the model refitted at those lights. The
   pipeline's recovery stage gives only a Lambertian start when this stage runs (its fit, at lights
   placed from the reference plane, would be discarded).

The final normals are integrated once more with the last placed depth as the gauge: the depth and mesh
the run writes are the near-field ones. Each round is recorded (:class:`NearFieldIteration`;
params.json ``nearfield`` and the report).

**Why the depth is observable.** Under point lights, moving the surface changes each pixel's L_k and the
relative irradiance E_k of the K lights in a way no normal and albedo can absorb: for each candidate
placement the K ≥ 4 observations of a pixel over-determine its 3 Lambertian unknowns (b = ρN), and the
least-squares residual over the usable observations (robust PS's: shadows and highlights left out) is
smallest where L and E are right. The placement is found by a log-spaced scan of the median object
distance followed by a bounded Brent refinement (:func:`scipy.optimize.minimize_scalar`); the starting
guess (``integration.reference_depth_m``) only centres the first scan (× / ÷ ``search_factor``). With
fewer than 4 point lights every placement fits exactly: the depth is not estimated
(:class:`~polarshape.errors.NearFieldDepthWarning`) and stays at the reference depth.

**Bad rigs.** A point light inside the bounding box of the recovered surface points is refused
(:class:`~polarshape.errors.CaptureError`); one behind the camera plane (z < 0) is suspicious
(:class:`~polarshape.errors.LightPlacementWarning`: usually a sign slip).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import math
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from polarshape.brdf.baselines import lambertian_stokes
from polarshape.brdf.fmbrdf import FMBRDFTables, build_tables
from polarshape.brdf.params import FMBRDF_PARAM_NAMES, FMBRDFParams
from polarshape.cameras import Camera
from polarshape.checks import to_numpy
from polarshape.errors import CaptureError, LightPlacementWarning, NearFieldDepthWarning
from polarshape.lights import Lights, PointLight
from polarshape.metrics import angular_error_deg
from polarshape.normals import NormalsResult, initial_normals
from polarshape.recover.coarse_to_fine import KnownMaterial
from polarshape.recover.observations import Observations, RecoveryInputs
from polarshape.recover.reflectometry import render_parts
from polarshape.recover.options import InitialNormalsOptions
from polarshape.recover.photometric import lambertian_ps

logger = logging.getLogger(__name__)

__all__ = [
    "MIN_LIGHTS_FOR_DEPTH", "ModelShading", "NearFieldIteration", "NearFieldOptions", "NearFieldResult",
    "check_near_field_lights", "corrected_normals", "estimate_depth_placement", "near_field_active", "place_depth",
    "pixel_lights", "refine_near_field",
]

#: Point lights needed to estimate the absolute depth: 3 fit any placement exactly (3 unknowns per pixel).
MIN_LIGHTS_FOR_DEPTH = 4

#: Most pixels the depth search evaluates (a regular subsample beyond that: the placement is one number).
_SEARCH_PIXELS = 20000

#: Candidates of the log-spaced scan of the median depth before the Brent refinement (~1.7 % apart over
#: the default span ÷/× 8: narrow enough for the sharp basin of a rig 15 radii away).
_SCAN_POINTS = 240

#: Local minima of the scan refined by Brent's method (the lowest first).
_REFINED_MINIMA = 3

#: The textured detector's bright cells: mask pixels whose albedo is above this share of the 90th percentile.
_BRIGHT_SHARE = 0.5

#: Least share of the mask the bright cells must cover, and least share the dark ones must, for a capture with
#: albedo steps to count as textured (fewer dark pixels: an untextured object's shading errors, not a texture).
_MIN_BRIGHT_FRACTION = 0.2
_MIN_DARK_FRACTION = 0.1

#: Least share of the mask a textured object's material is fitted on (:func:`_fit_model`: the pixels with the
#: most usable observations, widened one observation at a time until they cover this share).
_MIN_FIT_FRACTION = 0.2

#: Least share of the mask on albedo steps for a capture to count as textured (the untextured bumpy blob at 64²
#: has 1 of 2314 pixels flagged; the checker-textured sphere 5.5 % at 128²).
_MIN_EDGE_FRACTION = 0.01

#: Smallest share of the searched move the model rounds take (:func:`_model_rounds`: halved at every overshoot).
_MIN_RELAXATION = 0.125


class NearFieldOptions(BaseModel):
    """``nearfield:`` section of the run configuration (:func:`refine_near_field`)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    enabled: bool | Literal["auto"] = Field(
        "auto", description="auto = on when any light is a point light; true = on (point lights needed); false = off "
        "(point lights placed from the plane at integration.reference_depth_m)"
    )
    estimate_depth: bool = Field(
        True, description="estimate the object's absolute distance from the shading (needs >= 4 point lights); false = "
        "keep integration.reference_depth_m as the median depth"
    )
    max_iterations: int = Field(
        8, ge=1, le=100, description="most photometric-stereo rounds (normals -> depth -> lights) while the geometry "
        "settles"
    )
    tolerance_deg: float = Field(0.05, gt=0, description="settled: the mean normal change is below this (degrees)")
    depth_tolerance: float = Field(
        1e-3, gt=0, description="and the RMS depth change is below this fraction of the median depth"
    )
    search_factor: float = Field(
        8.0, gt=1, le=1000, description="the depth search spans the reference depth divided and multiplied by this"
    )
    full_model_rounds: int = Field(
        3, ge=1, le=10, description="fits of the run's model (FMBRDF) once the geometry settled: the first at the "
        "settled lights, each further one after damped depth searches on the shading with the model's "
        "non-Lambertian part taken out (its k_s re-fitted per candidate)"
    )


def near_field_active(options: NearFieldOptions, lights: Lights) -> bool:
    """Whether near-field recovery runs: ``enabled`` true, or ``auto`` with a point light.

    Raises:
        CaptureError: ``enabled: true`` without any point light.
    """
    if options.enabled == "auto":
        return lights.has_point_lights
    if options.enabled and not lights.has_point_lights:
        raise CaptureError("nearfield.enabled is true but the capture has no point light (lights[*].position): "
                           "near-field recovery needs light positions; set nearfield.enabled: auto or false")
    return bool(options.enabled)


@dataclass(frozen=True)
class NearFieldIteration:
    """One round of :func:`refine_near_field`.

    Attributes:
        iteration: 0 (the plane's distance, before any normals moved), 1, 2, ...
        normals: "plane" (round 0), "ps" (robust Lambertian PS) or "model" (the run's model).
        median_depth_m: median depth of the mask's surface after this round, metres.
        placement: perspective: scale of the integrated shape against the reference depth; orthographic:
            offset in metres from it.
        normal_change_deg: mean angle between this round's normals and the previous round's (NaN first).
        depth_change: RMS depth change over the mask against the previous round, fraction of the median
            depth (NaN first).
        residual: the depth search's relative Lambertian residual at the chosen placement (NaN without a search).
        seconds: the round's time.
        relaxation: the model rounds' share of the searched move taken (1: all of it; NaN in other rounds).
    """

    iteration: int
    normals: str
    median_depth_m: float
    placement: float
    normal_change_deg: float
    depth_change: float
    residual: float
    seconds: float
    relaxation: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in dataclasses.asdict(self).items()}


@dataclass
class NearFieldResult:
    """What :func:`refine_near_field` returns.

    Attributes:
        inputs: the recovery inputs with L and E at the final surface points.
        result: the run's model fitted to them.
        depth: (H, W) final depth (camera z, metres), NaN outside the surface.
        iterations: the rounds, in order.
        converged: whether the tolerances were met before ``max_iterations``.
        estimated: whether the absolute depth came from the shading (False: the reference depth).
        projection: the camera's projection ("perspective": ``placement`` is a scale, else an offset).
        reference_depth_m: the starting guess.
        skipped: what was left out and why.
    """

    inputs: RecoveryInputs
    result: NormalsResult
    depth: np.ndarray
    iterations: list[NearFieldIteration]
    converged: bool
    estimated: bool
    projection: str
    reference_depth_m: float
    skipped: list[str] = field(default_factory=list)

    @property
    def median_depth_m(self) -> float:
        return float(np.nanmedian(self.depth)) if np.isfinite(self.depth).any() else math.nan

    def as_dict(self) -> dict[str, Any]:
        """params.json's ``nearfield`` section."""
        last = self.iterations[-1] if self.iterations else None
        kind = "scale" if self.projection == "perspective" else "offset_m"
        return {
            "enabled": True, "converged": self.converged, "depth_estimated": self.estimated,
            "reference_depth_m": self.reference_depth_m, "median_depth_m": self.median_depth_m,
            "placement": {"kind": kind, "value": None if last is None else last.placement},
            "iterations": [it.as_dict() for it in self.iterations],
        }


# --- lights at surface points ------------------------------------------------------------------


def pixel_lights(lights: Lights, points: np.ndarray, *, like: Tensor) -> tuple[Tensor, Tensor]:
    """L (K, H, W, 3) and E (K, H, W) of ``lights`` at the surface ``points`` (H, W, 3) (metres, camera
    frame; NaN points — outside the surface — are fine: only the mask's pixels are used), in the
    dtype and on the device of ``like``."""
    pts = torch.from_numpy(np.nan_to_num(np.asarray(points, dtype=np.float64), nan=0.0))
    l_pix, e_pix = lights.illuminate(pts)
    return l_pix.to(device=like.device, dtype=like.dtype), e_pix.to(device=like.device, dtype=like.dtype)


def _filled_points(camera: Camera, depth: np.ndarray, fallback_depth: float) -> np.ndarray:
    """(H, W, 3) points of ``depth``, pixels without depth on the plane at ``fallback_depth``."""
    z = np.where(np.isfinite(depth), depth, fallback_depth)
    return camera.unproject(z)


def place_depth(shape: np.ndarray, median_depth: float, projection: str) -> np.ndarray:
    """The integrated ``shape`` (H, W) depth (NaN outside) placed at ``median_depth``: scaled in
    perspective (normals fix the shape up to a scale), shifted orthographic (up to an offset)."""
    med = float(np.nanmedian(shape))
    if projection == "perspective":
        return shape * (median_depth / med)
    return shape + (median_depth - med)


# --- checks ------------------------------------------------------------------------------------


def check_near_field_lights(lights: Lights, points: np.ndarray | None = None) -> None:
    """Refuse or flag a rig near-field recovery cannot use.

    Args:
        lights: the capture's lights.
        points: (N, 3) surface points (metres, camera frame), or None before any depth exists.

    Raises:
        CaptureError: a point light inside the bounding box of ``points``.

    Warns:
        LightPlacementWarning: a point light behind the camera plane (z < 0).
    """
    point_lights = [(k, light) for k, light in enumerate(lights) if isinstance(light, PointLight)]
    behind = [f"lights[{k}].position z = {light.position[2]:.4g} m" for k, light in point_lights if light.position[2] < 0]
    if behind:
        warnings.warn(LightPlacementWarning(
            f"{', '.join(behind)}: behind the camera plane (z < 0; z is forward, into the scene): the camera body "
            "would block such a light — check the sign of z (+z must point from the camera to the object)"
        ), stacklevel=2)
    if points is None or not len(points):
        return
    lo, hi = np.nanmin(points, axis=0), np.nanmax(points, axis=0)
    inside = [f"lights[{k}].position {[round(c, 4) for c in light.position]}" for k, light in point_lights
              if np.all(np.asarray(light.position) >= lo) and np.all(np.asarray(light.position) <= hi)]
    if inside:
        raise CaptureError(
            f"capture.yaml: {', '.join(inside)} is inside the object's bounding box (x {lo[0]:.4g}..{hi[0]:.4g}, "
            f"y {lo[1]:.4g}..{hi[1]:.4g}, z {lo[2]:.4g}..{hi[2]:.4g} m, camera frame): a light inside the object "
            "cannot light its visible surface — check the light positions' units (metres) and axes"
        )


def _light_inside(lights: Lights, points: np.ndarray) -> bool:
    lo, hi = points.min(axis=0), points.max(axis=0)
    return any(isinstance(light, PointLight) and np.all(np.asarray(light.position) >= lo)
               and np.all(np.asarray(light.position) <= hi) for light in lights)


@contextlib.contextmanager
def _quiet(log: logging.Logger) -> Iterator[None]:
    """``log`` at ERROR inside (the scan visits placements where PS is degenerate on purpose)."""
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)


def _equivalent_irradiance(body: Tensor, cos: Tensor, min_cos: float) -> Tensor:
    """Ẽ = B / max(N·L, ``min_cos``) (K, P) of the body term B and N·L (K, P); 0 where N·L ≤ 0
    (:class:`ModelShading`)."""
    return torch.where(cos > 0, body / cos.clamp_min(min_cos), torch.zeros_like(body))


@dataclass(frozen=True)
class ModelShading:
    """The run's fitted FMBRDF, to take its non-Lambertian part out of the shading during the depth search.

    For a candidate placement with per-pixel L and E, the model's surface term S and body term B (k_s = k_b = 1,
    irradiance included: :func:`polarshape.recover.reflectometry.render_parts`) at the fitted normals N give a
    linear Lambertian problem in the pixel's b = ρN, in the units of s0:

        s0 − k_s S  ≈  Ẽ (b·L),   Ẽ = B / (N·L)

    (Ẽ: the irradiance times the body term's non-cosine factors — Fresnel transmissions, shadowing — which
    vary slowly with the normal). The normals enter only through the specular lobe and those factors, not
    through the Lambertian cosine, so the K lights' consistency still measures the placement; without it,
    gloss and the body's Fresnel factors pull the estimate (a glossy FMBRDF sphere: 5 % too near).

    The observations it holds for (N·L and N·V above ``min_cos``, a body term above 1 % of the pixel's
    brightest) are chosen once, at the starting placement (:meth:`usable`), and kept for every candidate:
    an observation set that changed with the candidate would make the objective jump, and zeroing at each
    candidate the shading of the observations whose N·L fell below the threshold there (while still fitting
    them) pulled the bumpy blob's distance 1.8 % too far even with the true shape and material. Ẽ stays
    continuous where a candidate's N·L falls below the threshold (the cosine is floored there; 0 behind the
    surface).

    Attributes:
        tables: the fitted material's tables (:func:`polarshape.brdf.fmbrdf.build_tables`).
        k_s: the fitted surface albedo.
        normals: (H, W, 3) the fitted normals (NaN outside the mask).
    """

    tables: FMBRDFTables
    k_s: float
    normals: Tensor

    @classmethod
    def of(cls, result: NormalsResult) -> ModelShading | None:
        """The shading model of an FMBRDF ``result`` (None for a Lambertian one: nothing to divide out)."""
        if result.model != "fmbrdf":
            return None
        p = result.params
        tables = build_tables(ior=p["ior"], alpha=p["alpha"], beta=p["beta"], kappa=p["kappa"],
                              device=result.normals.device)
        return cls(tables, float(p["k_s"]), result.normals)

    def _terms(self, lights: Tensor, irradiance: Tensor, view: Tensor, pixels: Tensor
               ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Surface S, body B (K, P) (irradiance included), N·L (K, P) and N·V (P,) at the fitted normals."""
        normals = torch.nan_to_num(self.normals[pixels].to(lights), nan=0.0)  # (P, 3)
        obs = Observations(torch.zeros(lights.shape[1], lights.shape[0], 3, dtype=lights.dtype, device=lights.device),
                           torch.ones_like(irradiance.T), lights.transpose(0, 1), irradiance.T, view)
        surf, body = render_parts(self.tables, normals, obs)  # (P, K, 3) each, irradiance included
        cos = (lights * normals.unsqueeze(0)).sum(-1)  # (K, P)
        return surf[..., 0].T.to(lights), body[..., 0].T.to(lights), cos, (normals * view).sum(-1)

    def usable(self, lights: Tensor, irradiance: Tensor, view: Tensor, pixels: Tensor, min_cos: float = 0.1) -> Tensor:
        """(K, P) bool: the observations under ``lights`` (K, P, 3), ``irradiance`` (K, P) at the ``pixels``
        (H, W) bool (``view`` (P, 3)) that the correction holds for: N·L and N·V above ``min_cos``, a body term
        above 1 % of the pixel's brightest."""
        _, body, cos, facing = self._terms(lights, irradiance, view, pixels)
        return (facing > min_cos) & (cos > min_cos) & (body > 0.01 * body.amax(0, keepdim=True).clamp_min(1e-30))

    def lambertian(self, s0: Tensor, lights: Tensor, irradiance: Tensor, view: Tensor, pixels: Tensor,
                   min_cos: float = 0.1) -> tuple[Tensor, Tensor]:
        """The Lambertian problem of ``s0`` (K, P) under ``lights`` (K, P, 3), ``irradiance`` (K, P) at the
        ``pixels`` (H, W) bool (``view`` (P, 3)): (shading s0 − k_s S, equivalent irradiance Ẽ = B / max(N·L,
        ``min_cos``), 0 where N·L ≤ 0), each (K, P), to fit as ``shading ≈ Ẽ (b·L)``."""
        surf, body, cos, _ = self._terms(lights, irradiance, view, pixels)
        return s0 - self.k_s * surf, _equivalent_irradiance(body, cos, min_cos)

    def at(self, inputs: RecoveryInputs) -> ModelShading:
        """This model with k_s re-fitted (:meth:`profiled`) to the inputs' s0 at their L and E over the mask's
        usable observations: k_s fitted at another placement is off by that placement's fall-off error."""
        pixels = inputs.mask
        lights = inputs.lights[:, pixels].to(torch.float64)  # (K, P, 3)
        irradiance = inputs.irradiance[:, pixels].to(torch.float64)  # (K, P)
        view = inputs.view[pixels].to(torch.float64)  # (P, 3)
        obs = self.usable(lights, irradiance, view, pixels) & inputs.valid[:, pixels]
        _, k_s = self.profiled(inputs.stokes[:, 0][:, pixels].to(torch.float64), lights, irradiance, view, pixels, obs)
        return dataclasses.replace(self, k_s=float(k_s))

    def profiled(self, s0: Tensor, lights: Tensor, irradiance: Tensor, view: Tensor, pixels: Tensor, obs: Tensor
                 ) -> tuple[Tensor, Tensor]:
        """Residuals (K, P) of ``s0 ≈ k_s S + Ẽ (b·L)`` over the ``obs`` (K, P) bool, with every pixel's b and the
        one k_s ≥ 0 fitted by least squares (variable projection: b projected out per pixel, then k_s in closed
        form), and that k_s (a 0-d tensor). The material's shape (μ, α, β, κ) stays; k_s, linear, follows the
        candidate placement — held at the value fitted at another placement, it biases the search (a blob whose
        material was fitted 4.6 % too near: 1.6 % too near, against 0.5 % far with k_s re-fitted)."""
        surf, body, cos, _ = self._terms(lights, irradiance, view, pixels)
        equivalent = _equivalent_irradiance(body, cos, 0.1)
        w = obs.to(s0)
        design = (equivalent * w).unsqueeze(-1) * lights  # (K, P, 3)
        design = design.transpose(0, 1)  # (P, K, 3)
        solve = torch.linalg.pinv(design.mT @ design) @ design.mT  # (P, 3, K)

        def perp(v: Tensor) -> Tensor:  # (K, P) → (K, P): the part of w·v no b·L explains
            wv = (v * w).T.unsqueeze(-1)  # (P, K, 1)
            return (wv - design @ (solve @ wv)).squeeze(-1).T

        p_s0, p_surf = perp(s0), perp(surf)
        k_s = ((p_surf * p_s0).sum() / (p_surf * p_surf).sum().clamp_min(torch.finfo(s0.dtype).tiny)).clamp_min(0.0)
        return p_s0 - k_s * p_surf, k_s


def corrected_normals(inputs: RecoveryInputs, model: ModelShading) -> np.ndarray:
    """(H, W, 3) normals of Lambertian PS on the shading with ``model``'s non-Lambertian part taken out
    (:meth:`ModelShading.lambertian` at the inputs' L and E): the model's normals with its material held
    fixed, in milliseconds; mask pixels with fewer than 3 usable observations keep the model's normal."""
    pixels = inputs.mask
    s0 = inputs.stokes[:, 0][:, pixels].to(torch.float64)  # (K, P)
    lights = inputs.lights[:, pixels].to(torch.float64)  # (K, P, 3)
    irradiance = inputs.irradiance[:, pixels].to(torch.float64)  # (K, P)
    view = inputs.view[pixels].to(torch.float64)  # (P, 3)
    ok = model.usable(lights, irradiance, view, pixels) & inputs.valid[:, pixels]
    shading, equivalent = model.lambertian(s0, lights, irradiance, view, pixels)
    with _quiet(logging.getLogger("polarshape.recover.photometric")):
        normals, _ = lambertian_ps(shading, lights, equivalent, ok, view_dirs=view, allow_degenerate=True)
    before = model.normals[pixels].to(normals)
    normals = torch.where((ok.sum(0) >= 3)[:, None], normals, before)
    out = torch.full((*inputs.shape, 3), math.nan, dtype=torch.float64, device=normals.device)
    out[pixels] = normals
    return to_numpy(out)


# --- the depth from the shading ----------------------------------------------------------------


def _search_pixels(mask: np.ndarray, limit: int = _SEARCH_PIXELS) -> np.ndarray:
    """(H, W) bool: the mask, or a regular subsample of it with at most ``limit`` pixels."""
    n = int(mask.sum())
    if n <= limit:
        return mask
    keep = np.zeros(n, dtype=bool)
    keep[np.linspace(0, n - 1, limit).astype(np.int64)] = True
    out = np.zeros_like(mask)
    out[mask] = keep
    return out


def estimate_depth_placement(
    inputs: RecoveryInputs, used: Tensor, shape: np.ndarray, camera: Camera, lights: Lights, *,
    reference_depth: float, search_factor: float = 8.0, scan_points: int = _SCAN_POINTS,
    model: ModelShading | None = None,
) -> tuple[float, float]:
    """The median depth that makes the shading of ``shape`` most consistent with the point lights.

    For a candidate median depth d the integrated ``shape`` is placed there (:func:`place_depth`), L and E
    are recomputed at its points, each pixel's Lambertian b = ρN is fitted by least squares over its
    ``used`` observations (:func:`polarshape.recover.photometric.lambertian_ps`), and the objective is
    Σ r² / Σ I² over them. A log-spaced scan over [reference / f, reference · f] (f = ``search_factor``;
    placements that put a light inside the object's bounding box are excluded) finds the basin, a
    bounded Brent search refines it.

    Args:
        inputs: recovery inputs (s0 and view directions are read; L, E are recomputed).
        used: (K, H, W) bool observations to fit (robust PS's: no shadows or highlights).
        shape: (H, W) integrated depth (any placement), NaN outside the surface.
        camera: the super-pixel camera of ``shape``.
        lights: the capture's lights.
        reference_depth: the starting guess, metres (centres the scan).
        search_factor: the scan's span. scan_points: its candidates.
        model: the run's fitted FMBRDF: at every candidate the residual is that of ``s0 ≈ k_s S + Ẽ (b·L)``
            with b per pixel and k_s fitted (:meth:`ModelShading.profiled`) over the observations the model
            holds for at ``reference_depth`` (kept for every candidate); None: s0 as it is (robust PS's ``used``
            observations hold no gloss).

    Returns:
        (median depth, relative residual there).
    """
    import scipy.optimize  # its only use here; ~0.6 s to import
    pixels = _search_pixels(np.isfinite(shape) & to_numpy(inputs.mask).astype(bool))
    pix_t = torch.from_numpy(pixels).to(inputs.stokes.device)
    s0 = inputs.stokes[:, 0][:, pix_t].to(torch.float64)  # (K, P)
    obs = used[:, pix_t]  # (K, P)
    view = inputs.view[pix_t].to(torch.float64)  # (P, 3)
    weight = obs.to(torch.float64)
    total = float((weight * s0**2).sum().clamp_min(torch.finfo(torch.float64).tiny))
    rays = camera.unproject(np.ones(shape.shape))[pixels]  # (P, 3) points at unit depth (orthographic: z = 1)
    rel = shape[pixels]
    med = float(np.nanmedian(shape))

    def points_at(d: float) -> np.ndarray:  # as place_depth(shape, d) does, on the search's pixels
        if camera.projection == "perspective":
            return rays * (rel * (d / med))[:, None]
        return np.concatenate([rays[:, :2], (rel + (d - med))[:, None]], axis=1)

    if model is not None:  # the observations the model's correction holds for, at the starting placement
        l_ref, e_ref = lights.illuminate(torch.from_numpy(points_at(reference_depth)).to(s0.device))
        obs = obs & model.usable(l_ref, e_ref, view, pix_t)
        weight = obs.to(torch.float64)
        total = float((weight * s0**2).sum().clamp_min(torch.finfo(torch.float64).tiny))

    def objective(log_d: float) -> float:
        pts = points_at(math.exp(log_d))
        if _light_inside(lights, pts):
            return math.inf
        l_pix, e_pix = lights.illuminate(torch.from_numpy(pts).to(s0.device))  # (K, P, 3), (K, P)
        if model is not None:
            return float((model.profiled(s0, l_pix, e_pix, view, pix_t, obs)[0] ** 2).sum()) / total
        normals, albedo = lambertian_ps(s0, l_pix, e_pix, obs, view_dirs=view, allow_degenerate=True)
        pred = lambertian_stokes(normals.unsqueeze(0), l_pix, view.unsqueeze(0), k_d=math.pi * albedo)[..., 0] * e_pix
        return float((weight * (s0 - pred) ** 2).sum()) / total

    grid = np.linspace(math.log(reference_depth / search_factor), math.log(reference_depth * search_factor), scan_points)
    with warnings.catch_warnings(), _quiet(logging.getLogger("polarshape.recover.photometric")):
        warnings.simplefilter("ignore")  # degenerate pixels at absurd placements are expected during the scan
        values = np.array([objective(g) for g in grid])
        if not np.isfinite(values).any():
            return math.nan, math.nan
        # every local minimum of the scan, lowest first: the basin of the true placement can be narrow
        # (a far-off rig), and a far placement where the lights look alike fits loosely everywhere
        padded = np.concatenate([[np.inf], np.where(np.isfinite(values), values, np.inf), [np.inf]])
        minima = [i for i in range(len(grid)) if padded[i + 1] <= padded[i] and padded[i + 1] <= padded[i + 2]]
        best_d, best_v = math.nan, math.inf
        for i in sorted(minima, key=lambda j: values[j])[:_REFINED_MINIMA]:
            lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
            found = scipy.optimize.minimize_scalar(objective, bounds=(lo, hi), method="bounded", options={"xatol": 1e-5})
            d, v = (float(found.x), float(found.fun)) if found.fun <= values[i] else (float(grid[i]), float(values[i]))
            if v < best_v:
                best_d, best_v = d, v
    return float(math.exp(best_d)), best_v


# --- the loop ---


def _search(inputs: RecoveryInputs, used: Tensor, normals: np.ndarray, mask: np.ndarray, camera: Camera,
            lights: Lights, integrate: Callable[[np.ndarray, np.ndarray, np.ndarray | None], np.ndarray],
            depth_m: float, estimate: bool, model: ModelShading | None) -> tuple[np.ndarray, float, float]:
    """Integrate ``normals`` (H, W, 3) and search the shape's median depth near the current ``depth_m`` (when
    ``estimate``). Returns (shape (H, W), the distance found (``depth_m`` without a search or when it finds
    nothing), the search residual (NaN without one))."""
    shape = integrate(normals, mask & np.all(np.isfinite(normals), -1), None)
    if not estimate:
        return shape, depth_m, math.nan
    found, residual = estimate_depth_placement(inputs, used, shape, camera, lights, reference_depth=depth_m,
                                               search_factor=1.25, scan_points=24, model=model)
    return shape, (found if math.isfinite(found) else depth_m), residual


def _place(inputs: RecoveryInputs, shape: np.ndarray, depth_m: float, camera: Camera, lights: Lights
           ) -> tuple[np.ndarray, RecoveryInputs]:
    """The ``shape`` placed at ``depth_m`` (:func:`place_depth`), the rig checked against it, and L and E moved to
    its points: (depth (H, W), relit inputs)."""
    depth = place_depth(shape, depth_m, camera.projection)
    surface = np.isfinite(depth)
    check_near_field_lights(lights, camera.unproject(np.where(surface, depth, np.nan))[surface])
    l_pix, e_pix = pixel_lights(lights, _filled_points(camera, depth, depth_m), like=inputs.stokes)
    return depth, dataclasses.replace(inputs, lights=l_pix, irradiance=e_pix)


def _record(it: int, kind: str, depth: np.ndarray | None, prev_depth: np.ndarray | None, normals: np.ndarray,
            prev_normals: np.ndarray, mask: np.ndarray, depth_m: float, reference_depth: float, camera: Camera,
            residual: float, t0: float, relaxation: float = math.nan) -> NearFieldIteration:
    """The :class:`NearFieldIteration` of a round (changes against the previous round's normals and depth)."""
    both = mask & np.all(np.isfinite(normals), -1) & np.all(np.isfinite(prev_normals), -1)
    change = float(np.mean(angular_error_deg(normals, prev_normals, both)[both])) if both.any() else math.nan
    depth_change = math.nan
    if depth is not None and prev_depth is not None:
        common = np.isfinite(depth) & np.isfinite(prev_depth)
        depth_change = float(np.sqrt(np.mean((depth[common] - prev_depth[common]) ** 2))) / max(depth_m, 1e-12)
    median = float(np.nanmedian(depth)) if depth is not None else depth_m
    placement = depth_m / reference_depth if camera.projection == "perspective" else depth_m - reference_depth
    logger.info("nearfield round %d (%s normals): median depth %.5g m, normal change %.3g°, depth change %.3g",
                it, kind, median, change, depth_change)
    return NearFieldIteration(it, kind, median, placement, change, depth_change, residual, time.perf_counter() - t0,
                              relaxation)


def _model_rounds(
    inputs: RecoveryInputs, normals: np.ndarray, depth: np.ndarray | None, depth_m: float, model: ModelShading, *,
    mask: np.ndarray, camera: Camera, lights: Lights,
    integrate: Callable[[np.ndarray, np.ndarray, np.ndarray | None], np.ndarray], estimate: bool,
    options: NearFieldOptions, reference_depth: float, iterations: list[NearFieldIteration], it: int,
    skipped: list[str],
) -> tuple[RecoveryInputs, np.ndarray, np.ndarray | None, float, int]:
    """The cheap rounds with the model's material held (module docstring, step 2), damped.

    Each round integrates the current normals (H, W, 3), searches the distance with the model's
    non-Lambertian part taken out, moves L and E, re-fits k_s and re-solves the normals
    (:func:`corrected_normals`). The distance and the normals feed back into each other with a negative
    gain that can exceed 1 in size (a glossy sphere: the distance swung 0.3158 ↔ 0.3206 ↔ 0.3145 ↔
    0.3228 m, growing): the move to the distance found is under-relaxed in log-distance — all of it at first,
    halved (down to :data:`_MIN_RELAXATION`) each time the search's move changes sign (an overshoot). Settled:
    the normal change below ``tolerance_deg``, and the RMS depth change and the search's full move below
    ``depth_tolerance``. Not settled after ``max_iterations``: the state whose next search moved least (the
    one nearest the loop's fixed point) is kept.

    Appends the rounds to ``iterations`` (numbered on from ``it``) and a note to ``skipped`` when a round
    before the last is kept. Returns (inputs, normals, depth (H, W) or None, median depth, last round number).
    """
    relaxation, prev_gap = 1.0, math.nan
    best_gap, best = math.inf, None
    state = (inputs, normals, depth, depth_m, it)
    settled = False
    for _ in range(options.max_iterations):
        it += 1
        t0 = time.perf_counter()
        shape, found, residual = _search(inputs, inputs.valid, normals, mask, camera, lights, integrate, depth_m,
                                         estimate, model)
        gap = math.log(found / depth_m)  # the search's full move (0 without a search)
        if abs(gap) < best_gap:  # measured at the state this round starts from
            best_gap, best = abs(gap), state
        if gap * prev_gap < 0:  # overshoot: the distance swings around the fixed point
            relaxation = max(relaxation / 2, _MIN_RELAXATION)
        prev_gap = gap
        depth_m = depth_m * math.exp(relaxation * gap)
        new_depth, inputs = _place(inputs, shape, depth_m, camera, lights)
        model = model.at(inputs)
        new_normals = corrected_normals(inputs, model)
        model = dataclasses.replace(model, normals=torch.from_numpy(new_normals).to(model.normals))
        iterations.append(_record(it, "model-ps", new_depth, depth, new_normals, normals, mask, depth_m,
                                  reference_depth, camera, residual, t0, relaxation))
        depth, normals = new_depth, new_normals
        state = (inputs, normals, depth, depth_m, it)
        last = iterations[-1]
        if last.normal_change_deg < options.tolerance_deg and (not estimate or (
                last.depth_change < options.depth_tolerance and abs(gap) < options.depth_tolerance)):
            settled = True
            break
    if not settled and best is not None and best[-1] != it:
        inputs, normals, depth, depth_m, kept = best
        skipped.append(f"nearfield: the model rounds did not settle in {options.max_iterations} "
                       f"(nearfield.max_iterations); kept round {kept}, whose distance the next search moved least "
                       f"({100 * best_gap:.2g} %)")
        logger.info("nearfield: model rounds not settled; round %d kept (its search moved %.3g %%)", kept,
                    100 * best_gap)
    return inputs, normals, depth, depth_m, it


def _fully_observed(inputs: RecoveryInputs) -> tuple[Tensor, int]:
    """The mask pixels with the most usable observations: ((H, W) bool, the least count they have) — every
    light's where at least :data:`_MIN_FIT_FRACTION` of the mask has them all, else one fewer, and so on until
    they cover that share."""
    mask = inputs.mask
    count = (inputs.valid & mask).sum(0)  # (H, W)
    least = int(count[mask].max()) if bool(mask.any()) else 0
    while least > 1 and int((count >= least).sum()) < _MIN_FIT_FRACTION * int(mask.sum()):
        least -= 1
    return mask & (count >= least), least


def _fit_model(inputs: RecoveryInputs, albedo: Tensor,
               recover: Callable[..., NormalsResult], skipped: list[str]) -> NormalsResult:
    """The run's model fitted to ``inputs``; on a textured object, its material on the fully observed pixels.

    A textured object (albedo steps found in preprocessing: ``inputs.albedo_edges`` on at least
    :data:`_MIN_EDGE_FRACTION` of the mask, and the current ``albedo`` (H, W) above :data:`_BRIGHT_SHARE` of its
    90th percentile on at least :data:`_MIN_BRIGHT_FRACTION` of the mask, below it on at least
    :data:`_MIN_DARK_FRACTION`) under few lights: the fit of one material over every pixel settles in a wrong
    minimum. Measured on the checker-textured sphere of ``configs/scenes/textured.yaml`` (4 point lights,
    128²), given the true per-pixel L and E: over every pixel α 0.147, β 1.19 for the true 0.2, 2.0 (1.99° mean;
    the true material held: 1.39°); on the bright cells alone α 0.24, β 3.0 (1.66° held). Its dark cells'
    shading is mostly the untextured surface reflection, and at the rim and the terminators a pixel seen by one
    or two lights lets its normal and albedo absorb a wrong material. So the material (μ, α, β, κ) is fitted on
    the pixels with the most usable observations (:func:`_fully_observed`: there, all 4 lights'; dark cells
    included) — true L and E: α 0.200, β 2.02, 1.40° held — by the joint solve (``recovery.solver: joint``):
    the alternating one lands at α 0.09 on the same pixels at the first model round's lights (1.3 % near), the
    joint one at α 0.19. It is then held (``material_use: fixed``) in the run's own fit of every pixel's normal
    and albedos. ``recover(inputs)`` fits the model; ``recover(inputs, material)`` with a
    :class:`~polarshape.recover.coarse_to_fine.KnownMaterial` held; ``recover(inputs, solver="joint")`` with
    that recovery option changed. A note is added to ``skipped``.
    """
    mask = inputs.mask
    edges = inputs.albedo_edges
    known = mask & torch.isfinite(albedo)
    n_mask = int(mask.sum())
    if edges is None or int((edges & mask).sum()) < _MIN_EDGE_FRACTION * n_mask or not bool(known.any()):
        return recover(inputs)
    level = _BRIGHT_SHARE * torch.quantile(albedo[known].to(torch.float64), 0.9)
    n_bright = int((known & (albedo > level)).sum())
    if n_bright < _MIN_BRIGHT_FRACTION * n_mask or n_bright > (1 - _MIN_DARK_FRACTION) * n_mask:
        return recover(inputs)
    seen, least = _fully_observed(inputs)
    n_seen = int(seen.sum())
    if n_seen == n_mask or least < 3:
        return recover(inputs)
    on_seen = recover(dataclasses.replace(inputs, mask=seen), solver="joint")
    if on_seen.model != "fmbrdf":
        return recover(inputs)
    material = FMBRDFParams(**{k: float(on_seen.params[k]) for k in FMBRDF_PARAM_NAMES})
    note = (f"nearfield: textured object (albedo steps): the material fitted on the {n_seen} pixels of {n_mask} "
            f"with >= {least} of {inputs.valid.shape[0]} usable observations (joint solve), held for every pixel")
    if not any(item.startswith("nearfield: textured object") for item in skipped):
        skipped.append(note)
    logger.info("%s: ior %.3g, alpha %.3g, beta %.3g, kappa %.3g", note, material.ior, material.alpha, material.beta,
                material.kappa)
    return recover(inputs, KnownMaterial(material, "fixed"))


# --- the refinement ---------------------------------------------------------------------------


def refine_near_field(
    inputs: RecoveryInputs,
    result: NormalsResult,
    camera: Camera,
    lights: Lights,
    *,
    recover: Callable[..., NormalsResult],
    integrate: Callable[[np.ndarray, np.ndarray, np.ndarray | None], np.ndarray],
    reference_depth: float,
    options: NearFieldOptions = NearFieldOptions(),
    initial: InitialNormalsOptions = InitialNormalsOptions(),
) -> NearFieldResult:
    """Alternate normals ↔ depth ↔ per-pixel L and E until they settle (module docstring).

    Args:
        inputs: recovery inputs with L and E from the plane at ``reference_depth``.
        result: the run's model fitted to ``inputs`` (its mask and model are kept).
        camera: the super-pixel camera (orthographic with metric pixels, or perspective).
        lights: the capture's lights (point lights; directional ones are left as they are).
        recover: fits the run's model to inputs (the pipeline's ``recover_normals`` with its options);
            ``recover(inputs, material)`` with a :class:`~polarshape.recover.coarse_to_fine.KnownMaterial` holds
            that material, ``recover(inputs, solver=...)`` changes that recovery option (a textured object's
            material, fitted on its fully observed pixels by the joint solve: :func:`_fit_model`).
        integrate: (normals (H, W, 3), mask (H, W), depth_init or None) → depth (H, W), the run's
            integration (its gauge: median depth ``reference_depth`` without ``depth_init``).
        reference_depth: the starting guess of the median depth, metres.
        options: the ``nearfield`` section. initial: robust PS thresholds.

    Returns:
        :class:`NearFieldResult`.

    Raises:
        CaptureError: a point light inside the object's bounding box.
    """
    check_near_field_lights(lights)
    n_point = sum(isinstance(light, PointLight) for light in lights)
    skipped: list[str] = []
    estimate = options.estimate_depth
    if estimate and n_point < MIN_LIGHTS_FOR_DEPTH:
        warnings.warn(NearFieldDepthWarning(
            f"{n_point} point light(s): the absolute depth needs >= {MIN_LIGHTS_FOR_DEPTH} (with 3 every placement "
            f"fits the shading exactly); not estimated — the surface stays at integration.reference_depth_m "
            f"{reference_depth:g} m (set it to the object's distance)"
        ), stacklevel=2)
        estimate = False
    if not options.estimate_depth:
        skipped.append("nearfield: depth not estimated (nearfield.estimate_depth: false): median depth at "
                       "integration.reference_depth_m")
    mask = to_numpy(result.mask).astype(bool)
    iterations: list[NearFieldIteration] = []
    prev_normals = to_numpy(result.normals)
    prev_depth: np.ndarray | None = None
    depth_m = reference_depth
    converged = False
    current_normals = prev_normals
    used = initial_normals(inputs, initial).used
    if estimate:  # first the distance of a fronto-parallel plane: normals from far-off L would give a wild shape
        t0 = time.perf_counter()
        plane = np.where(mask, 1.0, np.nan)
        found, residual = estimate_depth_placement(inputs, used, plane, camera, lights, reference_depth=reference_depth,
                                                   search_factor=options.search_factor)
        if math.isfinite(found):
            depth_m = found
            l_pix, e_pix = pixel_lights(lights, camera.unproject(np.full(mask.shape, depth_m)), like=inputs.stokes)
            inputs = dataclasses.replace(inputs, lights=l_pix, irradiance=e_pix)
            ps = initial_normals(inputs, initial)
            used = ps.used
            current_normals = to_numpy(torch.where(inputs.mask[..., None], ps.normals,
                                                   torch.full_like(ps.normals, math.nan)))
        placement = depth_m / reference_depth if camera.projection == "perspective" else depth_m - reference_depth
        iterations.append(NearFieldIteration(0, "plane", depth_m, placement, math.nan, math.nan, residual,
                                             time.perf_counter() - t0))
    it = 0
    for _ in range(options.max_iterations):  # photometric-stereo rounds: cheap, while the geometry settles
        it += 1
        t0 = time.perf_counter()
        shape, depth_m, residual = _search(inputs, used, current_normals, mask, camera, lights, integrate, depth_m,
                                           estimate, None)
        depth, inputs = _place(inputs, shape, depth_m, camera, lights)
        ps = initial_normals(inputs, initial)
        used = ps.used
        new_normals = to_numpy(torch.where(inputs.mask[..., None], ps.normals, torch.full_like(ps.normals, math.nan)))
        iterations.append(_record(it, "ps", depth, prev_depth, new_normals, current_normals, mask, depth_m,
                                  reference_depth, camera, residual, t0))
        prev_depth, current_normals = depth, new_normals
        last = iterations[-1]
        converged = last.normal_change_deg < options.tolerance_deg and (
            not estimate or last.depth_change < options.depth_tolerance)
        if converged:
            break
    fit = recover  # the run's model fit; with κ forced once a fit kept it (below)
    for r in range(options.full_model_rounds):  # the run's model at the settled lights, then relit by it
        if r:
            model = ModelShading.of(result)
            if model is not None:  # cheap: the material held fixed
                inputs, current_normals, prev_depth, depth_m, it = _model_rounds(
                    inputs, current_normals, prev_depth, depth_m, model, mask=mask, camera=camera, lights=lights,
                    integrate=integrate, estimate=estimate, options=options, reference_depth=reference_depth,
                    iterations=iterations, it=it, skipped=skipped)
        it += 1
        t0 = time.perf_counter()
        result = _fit_model(inputs, result.albedo, fit, skipped)
        if fit is recover and result.model == "fmbrdf" and float(result.params.get("kappa", 0.0)) > 0:
            # κ, once kept by a fit's κ test, stays in the later fits: the test's gain moves with the lights
            # of each round (the 128² blob of configs/scenes/nearfield_blob.yaml, true κ 20: kept at 27.4 %
            # in the second fit, dropped at 21.8 % in the third — 1.45° mean instead of ~0.5°)
            fit = functools.partial(recover, fit_kappa=True)
            skipped.append(f"nearfield: κ {float(result.params['kappa']):.3g} kept by model fit {r + 1}: the later "
                           "fits keep fitting it (recovery.fit_kappa: true for them)")
        new_normals = to_numpy(result.normals)
        iterations.append(_record(it, "model", None, None, new_normals, current_normals, mask, depth_m,
                                  reference_depth, camera, math.nan, t0))
        current_normals = new_normals
    final = integrate(current_normals, mask & np.all(np.isfinite(current_normals), -1), prev_depth)
    if not converged:
        skipped.append(f"nearfield: not converged after {len(iterations)} rounds (nearfield.max_iterations)")
    return NearFieldResult(inputs=inputs, result=result, depth=final, iterations=iterations, converged=converged,
                           estimated=estimate, projection=camera.projection, reference_depth_m=reference_depth,
                           skipped=skipped)
